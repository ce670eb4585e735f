"""render() input validation (ValueError naming the argument and its shape), backend dispatch, the
lazy JIT build and its error messages, and the NaN-poisoned output buffers."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace

import pytest
import torch
from scenes import make_surfels, pinhole

import ctgs.ops.ext as ext
import ctgs.render.api as api
from ctgs.errors import UserError
from ctgs.render import render


def _scene(dtype=torch.float32):
    s = make_surfels(means=[[0.0, 0.0, 2.0], [0.1, 0.1, 3.0]], quats=[[1.0, 0.0, 0.0, 0.0]] * 2,
                     scales=[[0.3, 0.3]] * 2, opacities=[0.5, 0.6], sh=[[0.1, 0.2, 0.3]] * 2,
                     texel_size=[0.1, 0.1], tex_res=[[2, 2], [3, 1]], dtype=dtype)
    return s, pinhole(16, 12, 10.0).to("cpu", dtype)


BAD_SHAPES = [
    ("means", torch.zeros(2, 4), "[N, 3]"),
    ("quats", torch.zeros(2, 3), "[2, 4]"),
    ("scales", torch.ones(2), "[2, 2]"),
    ("opacities", torch.ones(2, 1), "[2]"),
    ("sh", torch.zeros(2, 2, 3), "[2, K, 3]"),
    ("texel_size", torch.ones(3), "[2] or [2, 2]"),
    ("textures", torch.zeros(7, 4), "[T, 3]"),
    ("tex_res", torch.ones(2, 3, dtype=torch.int32), "[2, 2] int32"),
    ("tex_offset", torch.zeros(2, 1, dtype=torch.int64), "[2] int64"),
]


@pytest.mark.parametrize("name,bad,shape", BAD_SHAPES, ids=[b[0] for b in BAD_SHAPES])
def test_wrong_shape_names_argument_and_shape(name, bad, shape):
    s, cam = _scene()
    with pytest.raises(ValueError) as info:
        render(replace(s, **{name: bad}), cam, backend="cpu")
    assert name in str(info.value) and shape in str(info.value)


FLOATS = ["quats", "scales", "opacities", "sh", "texel_size", "textures"]


@pytest.mark.parametrize("name", FLOATS)
def test_wrong_dtype(name):
    s, cam = _scene()
    with pytest.raises(ValueError, match=name):
        render(replace(s, **{name: getattr(s, name).double()}), cam, backend="cpu")


@pytest.mark.parametrize("name,dtype", [("tex_res", torch.int64), ("tex_offset", torch.int32)])
def test_wrong_index_dtype(name, dtype):
    s, cam = _scene()
    with pytest.raises(ValueError, match=name):
        render(replace(s, **{name: getattr(s, name).to(dtype)}), cam, backend="cpu")


@pytest.mark.parametrize("name", FLOATS + ["tex_res"])
def test_wrong_device(name):
    s, cam = _scene()
    with pytest.raises(ValueError, match=name):
        render(replace(s, **{name: getattr(s, name).to("meta")}), cam, backend="cpu")


@pytest.mark.parametrize("name", ["means"] + FLOATS)
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite(name, value):
    s, cam = _scene()
    t = getattr(s, name).clone()
    t.view(-1)[-1] = value
    with pytest.raises(ValueError, match=name):
        render(replace(s, **{name: t}), cam, backend="cpu")


@pytest.mark.parametrize("name,value", [("scales", 0.0), ("texel_size", -1.0), ("opacities", 1.5),
                                        ("opacities", -0.1)])
def test_out_of_range_values(name, value):
    s, cam = _scene()
    t = getattr(s, name).clone()
    t.view(-1)[0] = value
    with pytest.raises(ValueError, match=name):
        render(replace(s, **{name: t}), cam, backend="cpu")


def test_jagged_layout_out_of_range():
    s, cam = _scene()
    with pytest.raises(ValueError, match="tex_offset"):
        render(replace(s, tex_offset=torch.tensor([0, 5], dtype=torch.int64)), cam, backend="cpu")
    with pytest.raises(ValueError, match="tex_res"):
        render(replace(s, tex_res=torch.tensor([[2, 2], [-1, 1]], dtype=torch.int32)), cam, backend="cpu")


def test_background_error_image_backend_and_degree():
    s, cam = _scene()
    with pytest.raises(ValueError, match=r"background.*\[3\]"):
        render(s, cam, backend="cpu", background=torch.zeros(4))
    with pytest.raises(ValueError, match=r"error_image.*\[12, 16\]"):
        render(s, cam, backend="cpu", error_image=torch.zeros(16, 12))
    with pytest.raises(ValueError, match="backend"):
        render(s, cam, backend="gpu")
    with pytest.raises(ValueError, match="sh_degree"):
        render(s, cam, backend="cpu", sh_degree=1)
    # backend="cuda" with CPU tensors: without a GPU the CUDA extension is unavailable (UserError); with one,
    # the tensors are on the wrong device (ValueError). Either way the message names cuda.
    expected = ValueError if torch.cuda.is_available() else UserError
    with pytest.raises(expected, match="cuda"):
        render(s, cam, backend="cuda")


def test_non_contiguous_inputs_match_contiguous():
    s, cam = _scene()
    nc = replace(s, means=s.means.t().contiguous().t(), sh=s.sh.transpose(0, 1).contiguous().transpose(0, 1))
    assert not nc.means.is_contiguous()
    torch.testing.assert_close(render(nc, cam, backend="cpu").rgb, render(s, cam, backend="cpu").rgb, atol=0, rtol=0)


def test_binding_checks_shapes_too():
    """The extension validates on its own (a caller bypassing render() gets an error, not a crash)."""
    ext.load_cpu()
    forward = torch.ops.ctgs.rasterize_forward
    z = torch.zeros
    with pytest.raises(RuntimeError, match=r"Rc must have shape \[N, 3, 3\]"):
        forward(z(1, 3), z(1, 3), z(1, 2), z(1), z(1, 3), z(1, 2), z(0, 3), z(1, 2, dtype=torch.int32),
                z(1, dtype=torch.int64), z(3), 1.0, 1.0, 0.0, 0.0, 4, 4, 0.01, None, 1, False)
    with pytest.raises(RuntimeError, match="exceeds the texel count"):
        forward(z(1, 3), z(1, 3, 3), z(1, 2), z(1), z(1, 3), z(1, 2), z(3, 3), torch.tensor([[2, 2]], dtype=torch.int32),
                z(1, dtype=torch.int64), z(3), 1.0, 1.0, 0.0, 0.0, 4, 4, 0.01, None, 1, False)


def test_poisoned_outputs_are_all_overwritten(monkeypatch):
    """Poisoning works (fresh buffers are NaN / -1) and the kernel overwrites every pixel of them."""
    s, cam = _scene()
    from ctgs.render.preprocess import to_camera_space

    p = to_camera_space(s.means, s.quats, s.sh, cam, 0)
    args = (p.mu_c, p.Rc, s.scales, s.opacities, p.colors, s.texel_size[:, None].expand(-1, 2).contiguous(),
            s.textures, s.tex_res, s.tex_offset, torch.zeros(3), cam.fx, cam.fy, cam.cx, cam.cy, 37, 21, cam.near,
            None, 2, True)
    ext.load_cpu()
    rgb, alpha, depth, final_T, n_contrib = torch.ops.ctgs.rasterize_forward(*args)[:5]
    for t in (rgb, alpha, depth, final_T):
        assert torch.isfinite(t).all()
    assert (n_contrib >= 0).all()


def test_import_does_not_build_extension():
    code = ("import ctgs, ctgs.render, ctgs.render.api, ctgs.ops.ext as e, sys; "
            "assert e._cpu_module is None; assert 'torch.utils.cpp_extension' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_build_errors_say_what_to_do(monkeypatch):
    monkeypatch.setattr(ext, "_cpu_module", None)
    monkeypatch.setenv("CXX", "no-such-compiler-ctgs")
    with pytest.raises(UserError, match="--backend reference"):
        ext.load_cpu()
    monkeypatch.delenv("CXX")
    monkeypatch.setattr(ext, "CPU_SOURCES", ["cpu/missing.cpp"])
    with pytest.raises(UserError, match="--backend reference"):
        ext.load_cpu()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_backward_reusing_the_forward_setup_matches_recomputing_it(dtype):
    """The CPU forward hands its per-primitive setup to its backward (no second binning pass); the gradients
    are bit-identical to a backward that recomputes it, and a setup of another render is refused."""
    from ctgs.render.preprocess import to_camera_space
    from scenes import random_scene

    case = random_scene(60, seed=3, dtype=dtype, width=40, height=28)
    s, cam = case.surfels, case.camera
    p = to_camera_space(s.means, s.quats, s.sh, cam, 2)
    scene = (p.mu_c.contiguous(), p.Rc.contiguous(), s.scales, s.opacities, p.colors.contiguous(),
             s.texel_size.contiguous(), s.textures, s.tex_res, s.tex_offset, torch.zeros(3, dtype=dtype))
    cam_args = (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.near)
    ext.load_cpu()
    forward, backward = torch.ops.ctgs.rasterize_forward, torch.ops.ctgs.rasterize_backward
    outs = forward(*scene, *cam_args, None, 2, False)
    assert len(outs) == 14  # ... setup_prims, setup_spans, median, depth2
    final_T, n_contrib, tile_offsets, tile_list, setup_prims, setup_spans = (
        outs[3], outs[4], outs[5], outs[6], outs[10], outs[11])
    assert setup_prims.dtype == torch.uint8 and setup_prims.numel() > 0 and setup_spans.numel() > 0
    g = torch.Generator().manual_seed(0)
    v_rgb = torch.randn(cam.height, cam.width, 3, generator=g, dtype=torch.float64).to(dtype)
    v_alpha = torch.randn(cam.height, cam.width, generator=g, dtype=torch.float64).to(dtype)
    v_depth = torch.randn(cam.height, cam.width, generator=g, dtype=torch.float64).to(dtype)
    # One thread: with more, which thread sums which tile (dynamic schedule) varies from call to call.
    common = (*scene, *cam_args, tile_offsets, tile_list, final_T, n_contrib, v_rgb, v_alpha, v_depth, 1)
    reused = backward(*common, setup_prims, setup_spans)
    again = backward(*common, setup_prims, setup_spans)  # a second backward of the same render
    fresh = backward(*common, None, None)
    assert any(bool(t.abs().sum() > 0) for t in fresh)
    for a, b, c in zip(reused, again, fresh):
        torch.testing.assert_close(a, c, atol=0, rtol=0)
        torch.testing.assert_close(b, c, atol=0, rtol=0)
    with pytest.raises(RuntimeError, match="setup_prims must be forward_cpu's output of the same render"):
        backward(*common, setup_prims[:-8].contiguous(), setup_spans)


def test_zero_quaternion_is_refused():
    s, cam = _scene()
    q = s.quats.clone()
    q[1] = 0.0
    with pytest.raises(ValueError, match="non-zero norm"):
        render(replace(s, quats=q), cam, backend="cpu")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_value_check_agrees_with_pytorch(dtype):
    """validate_inputs takes the compiled one-pass check where it can (api._values_ok_fused) and the PyTorch
    checks otherwise: the compiled check passes valid inputs and flags every value problem the PyTorch
    checks raise on (anywhere in a tensor larger than one parallel chunk), so the messages stay theirs. The same
    for the one-transfer check of GPU inputs (api._values_ok_device: device-agnostic, run here on the CPU), which
    also covers the camera and background."""
    from scenes import bad_value_cases, random_scene

    ext.load_cpu()  # the compiled check runs once the extension is loaded (never builds it by itself)
    case = random_scene(50, seed=4, dtype=dtype, max_res=8)
    s, cam = case.surfels, case.camera
    big = torch.rand(70000, 3, dtype=dtype) - 0.5  # > 2 chunks of 16k values
    s = replace(s, textures=torch.cat([s.textures, big]))
    assert api._values_ok_fused(s)
    assert api._values_ok_fused(replace(s, sh=s.sh[:, :4]))  # a training step below the top SH degree: a slice
    assert api._values_ok_device(s, [cam.viewmat, torch.zeros(3, dtype=dtype)])
    assert api._values_ok_device(replace(s, sh=s.sh[:, :4]), [])
    api.validate_inputs(s, cam, None, None)
    vm = cam.viewmat.clone()
    vm[1, 2] = float("nan")
    assert not api._values_ok_device(s, [vm]) and not api._values_ok_device(s, [torch.tensor([0.0, float("inf"), 0.0])])
    bad = bad_value_cases(s)
    flags = torch.ops.ctgs.surfel_value_flags  # the tensor form both backends have (the GPU path's)
    assert int(flags(*[getattr(s, k) for k in api._SURFEL_FLOATS], s.tex_res, s.tex_offset, 0)) == 0
    for name, b in bad:
        assert not api._values_ok_fused(b), name
        assert not api._values_ok_device(b, []), name
        assert int(flags(*[getattr(b, k).contiguous() for k in api._SURFEL_FLOATS], b.tex_res, b.tex_offset, 0)), name
        with pytest.raises(ValueError, match=name):
            api.validate_inputs(b, cam, None, None)


def test_validation_never_builds_the_extension():
    """render(backend='reference') validates its inputs without loading (or building) the CPU extension."""
    here = os.path.dirname(os.path.abspath(__file__))
    code = (f"import torch, sys; sys.path.insert(0, {here!r}); from scenes import random_scene; "
            "import ctgs.ops.ext as e; from ctgs.render import render; c = random_scene(5); "
            "render(c.surfels, c.camera, backend='reference'); assert e._cpu_module is None")
    subprocess.run([sys.executable, "-c", code], check=True)
