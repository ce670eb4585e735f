"""C++ CPU backend vs the pure-PyTorch reference (docs/reference/renderer.md): forward images, per-primitive error
statistics and gradients w.r.t. every input with random cotangents."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from scenes import FLOAT_INPUTS, cast, random_scene, with_grad

from ctgs.render import render

# float64: both sides evaluate the same formulas in a different order (kernel loops vs dense tensor ops);
# observed worst abs error 1.5e-14 (depth) and 2.1e-14 relative to the largest gradient entry (quats).
ATOL_F64 = 1e-11
GRAD_RTOL_F64 = 1e-11
# float32: accumulated rounding (division-based T recovery, long per-primitive sums); observed worst
# 8.7e-6 abs on images (depth ~3 world units) and 9e-6 relative to the largest gradient entry (means).
ATOL_F32 = 1e-4
GRAD_RTOL_F32 = 2e-4

SEEDS = (0, 1, 2)


def _case(seed: int, dtype: torch.dtype):
    # 64x48 (non-square), principal point off-centre, 60 overlapping tilted textured surfels, some
    # partly off-screen (scenes.random_scene).
    case = random_scene(60, seed=seed, width=64, height=48, sh_degree=3, max_res=8)
    return cast(case.surfels, dtype), case.camera.to("cpu", dtype)


def _loss(out, seed: int):
    g = torch.Generator().manual_seed(100 + seed)
    return sum((o * (torch.rand(o.shape, generator=g, dtype=torch.float64).to(o.dtype) - 0.3)).sum()
               for o in (out.rgb, out.alpha, out.depth))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_forward_matches_reference(seed, dtype):
    s, cam = _case(seed, dtype)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    err = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    err = err.to(dtype)
    a = render(s, cam, backend="cpu", background=bg, error_image=err)
    b = render(s, cam, backend="reference", background=bg, error_image=err)
    atol = ATOL_F64 if dtype == torch.float64 else ATOL_F32
    assert a.alpha.mean() > 0.2  # the scene covers a good part of the image
    for name in ("rgb", "alpha", "depth"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == dtype and x.shape == y.shape
        assert torch.isfinite(x).all()
        torch.testing.assert_close(x, y, atol=atol, rtol=0, msg=name)
    assert torch.equal(a.stats.count, b.stats.count)
    assert a.stats.count.sum() > 0
    torch.testing.assert_close(a.stats.contrib, b.stats.contrib, atol=atol * 100, rtol=1e-4 if dtype == torch.float32 else 0)
    torch.testing.assert_close(a.stats.err, b.stats.err, atol=atol * 100, rtol=1e-4 if dtype == torch.float32 else 0)


@pytest.mark.parametrize("seed", SEEDS)
def test_median_depth_matches_reference(seed):
    """The median depth (no gradient) on the overlapping random scene: the same hit depth at every pixel."""
    s, cam = _case(seed, torch.float64)
    a = render(s, cam, backend="cpu")
    b = render(s, cam, backend="reference")
    assert a.median_depth.shape == (cam.height, cam.width) and not a.median_depth.requires_grad
    assert (a.median_depth > 0).float().mean() > 0.2
    # a median that is not the mean: several surfels overlap at different depths
    assert float((a.median_depth - a.depth / a.alpha.clamp_min(1e-9)).abs().max()) > 0.05
    torch.testing.assert_close(a.median_depth, b.median_depth, atol=ATOL_F64, rtol=0)


@pytest.mark.parametrize("seed", SEEDS)
def test_depth2_and_its_gradients_match_reference(seed):
    """depth2 (sum of w z^2, the depth distortion's third sum) and the gradients of a random cotangent on it alone."""
    s, cam = _case(seed, torch.float64)
    g = torch.Generator().manual_seed(200 + seed)
    v = torch.rand(cam.height, cam.width, generator=g, dtype=torch.float64) - 0.3
    outs, grads = {}, {}
    for backend in ("cpu", "reference"):
        sg = with_grad(s)
        out = render(sg, cam, backend=backend)
        outs[backend] = out.depth2.detach()
        grads[backend] = torch.autograd.grad((out.depth2 * v).sum(), [getattr(sg, n) for n in FLOAT_INPUTS])
    assert float(outs["cpu"].max()) > 1.0  # depths beyond 1: z^2 differs from z
    torch.testing.assert_close(outs["cpu"], outs["reference"], atol=ATOL_F64 * 10, rtol=0)
    for name, x, y in zip(FLOAT_INPUTS, grads["cpu"], grads["reference"]):
        scale = y.abs().max().item()
        if name in ("means", "quats", "scales", "opacities"):  # what the depth depends on
            assert scale > 0, f"{name}: the reference gradient is zero, the test would prove nothing"
        torch.testing.assert_close(x, y, atol=GRAD_RTOL_F64 * max(scale, 1.0), rtol=0, msg=name)


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_median_depth_is_where_the_transmittance_falls_below_half(backend):
    """Two fronto-parallel surfels on the optical axis, at depths 2 and 3: the median is the front one when it alone
    takes T below 0.5, else the back one; 0 where nothing is drawn."""
    from scenes import make_surfels

    from ctgs.render.camera import Camera

    cam = Camera(fx=40.0, fy=40.0, cx=8.0, cy=8.0, width=16, height=16, viewmat=torch.eye(4, dtype=torch.float64))
    for front, expected in ((0.4, 3.0), (0.7, 2.0)):
        s = make_surfels(means=[[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], quats=[[1.0, 0, 0, 0]] * 2,
                         scales=[[0.05, 0.05], [0.05, 0.05]], opacities=[front, 0.9], sh=[[0.0, 0.0, 0.0]] * 2,
                         texel_size=[0.01, 0.01], tex_res=[[0, 0], [0, 0]])
        m = render(s, cam, backend=backend).median_depth
        assert float(m[8, 8]) == pytest.approx(expected, abs=1e-9), front
        assert float(m[0, 0]) == 0.0


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gradients_match_reference(seed, dtype):
    s, cam = _case(seed, dtype)
    rtol = GRAD_RTOL_F64 if dtype == torch.float64 else GRAD_RTOL_F32
    grads = {}
    for backend in ("cpu", "reference"):
        sg = with_grad(s)
        bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype, requires_grad=True)
        out = render(sg, cam, backend=backend, background=bg)
        inputs = [getattr(sg, n) for n in FLOAT_INPUTS] + [bg]
        grads[backend] = torch.autograd.grad(_loss(out, seed), inputs)
    for name, x, y in zip(FLOAT_INPUTS + ("background",), grads["cpu"], grads["reference"]):
        scale = y.abs().max().item()
        assert scale > 0, f"{name}: the reference gradient is zero, the test would prove nothing"
        assert torch.isfinite(x).all(), name
        err = (x - y).abs().max().item()
        assert err <= rtol * scale, f"{name}: max abs err {err:.3g} vs max |grad| {scale:.3g}"


def test_scalar_texel_size_broadcast_and_lower_sh_degree():
    """texel_size [N] means the same on both axes; sh_degree below K's maximum uses the first bands."""
    case = random_scene(30, seed=5, width=40, height=30, sh_degree=3)
    s = replace(case.surfels, texel_size=case.surfels.texel_size[:, 0].contiguous())
    sg_c, sg_r = with_grad(s), with_grad(s)
    a = render(sg_c, case.camera, backend="cpu", sh_degree=1)
    b = render(sg_r, case.camera, backend="reference", sh_degree=1)
    torch.testing.assert_close(a.rgb, b.rgb, atol=ATOL_F64, rtol=0)
    ga = torch.autograd.grad(_loss(a, 0), [sg_c.texel_size, sg_c.sh])
    gb = torch.autograd.grad(_loss(b, 0), [sg_r.texel_size, sg_r.sh])
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, atol=GRAD_RTOL_F64 * y.abs().max().item(), rtol=0)
    assert ga[1][:, 4:].abs().max() == 0  # bands above sh_degree get no gradient


def test_float32_agrees_with_float64():
    case = random_scene(60, seed=3, width=64, height=48)
    a = render(case.surfels, case.camera, backend="cpu")
    b = render(cast(case.surfels, torch.float32), case.camera.to("cpu", torch.float32), backend="cpu")
    torch.testing.assert_close(b.rgb.double(), a.rgb, atol=ATOL_F32, rtol=0)
    torch.testing.assert_close(b.alpha.double(), a.alpha, atol=ATOL_F32, rtol=0)


def test_deterministic_across_thread_counts():
    """Tiles are independent and per-primitive sums are reduced in thread order: 1 and 2 threads agree
    to rounding (forward bit-exact), whatever the tile scheduling."""
    case = random_scene(60, seed=4, width=64, height=48)
    old = torch.get_num_threads()
    outs = []
    try:
        for nt in (1, 2):
            torch.set_num_threads(nt)
            sg = with_grad(case.surfels)
            out = render(sg, case.camera, backend="cpu")
            outs.append((out.rgb.detach(), torch.autograd.grad(_loss(out, 0), [sg.means, sg.textures])))
    finally:
        torch.set_num_threads(old)
    assert torch.equal(outs[0][0], outs[1][0])
    for x, y in zip(outs[0][1], outs[1][1]):
        torch.testing.assert_close(x, y, atol=1e-12 * y.abs().max().item(), rtol=0)


@pytest.mark.parametrize("layout", ["packed", "gaps", "reversed", "shared"])
def test_texel_gradients_with_two_threads_any_block_layout(layout):
    """With 2 threads the second thread's texel gradients go to a private copy: zeroed and added per primitive
    block when the blocks are in primitive order (packed, or with unused texels between them and untextured
    primitives among them), whole otherwise (stored in reverse, or one block shared by every textured
    primitive). Whatever the layout the texel gradients agree with one thread's to rounding, and texels that
    belong to no primitive get exactly zero."""

    case = random_scene(60, seed=5, width=64, height=48)
    s = case.surfels
    sizes = (s.tex_res[:, 0] * s.tex_res[:, 1]).long()
    if layout == "reversed":  # the same blocks, stored last primitive first
        order = torch.arange(s.num_primitives - 1, -1, -1)
        starts = torch.zeros_like(sizes)
        starts[order] = torch.cumsum(sizes[order], 0) - sizes[order]
        tex = torch.zeros_like(s.textures)
        for i in range(s.num_primitives):
            n = int(sizes[i])
            tex[int(starts[i]):int(starts[i]) + n] = s.textures[int(s.tex_offset[i]):int(s.tex_offset[i]) + n]
        s = replace(s, textures=tex, tex_offset=starts)
    elif layout == "shared":  # every textured primitive reads the first block of the largest size
        big = int(torch.argmax(sizes))
        res = s.tex_res.clone()
        res[sizes > 0] = s.tex_res[big]
        s = replace(s, tex_res=res, tex_offset=torch.where(sizes > 0, s.tex_offset[big], s.tex_offset))
    elif layout == "gaps":  # primitive order, 5 unused texels before each block, every third primitive untextured
        res = s.tex_res.clone()
        res[::3] = 0
        sizes = (res[:, 0] * res[:, 1]).long()
        starts = torch.cumsum(sizes + 5, 0) - sizes
        tex = torch.full((int(starts[-1]) + 1, 3), 0.3, dtype=s.textures.dtype)
        for i in range(s.num_primitives):
            n = int(sizes[i])
            tex[int(starts[i]):int(starts[i]) + n] = s.textures[int(s.tex_offset[i]):int(s.tex_offset[i]) + n]
        s = replace(s, textures=tex, tex_res=res, tex_offset=starts)
        assert int(sizes.gt(0).sum()) > 10
    old = torch.get_num_threads()
    grads = []
    try:
        for nt in (1, 2):
            torch.set_num_threads(nt)
            sg = with_grad(s)
            out = render(sg, case.camera, backend="cpu")
            grads.append(torch.autograd.grad(_loss(out, 0), [sg.textures])[0])
    finally:
        torch.set_num_threads(old)
    assert grads[0].abs().sum() > 0
    torch.testing.assert_close(grads[1], grads[0], atol=1e-12 * grads[0].abs().max().item(), rtol=0)
    if layout == "gaps":
        owned = torch.zeros(s.textures.shape[0], dtype=torch.bool)
        for i in range(s.num_primitives):
            owned[int(s.tex_offset[i]):int(s.tex_offset[i]) + int(s.tex_res[i, 0] * s.tex_res[i, 1])] = True
        assert torch.equal(grads[1][~owned], torch.zeros_like(grads[1][~owned]))


_FETCH_SCRIPT = """
import sys, torch
sys.path.insert(0, {tests!r})
from scenes import FLOAT_INPUTS, cast, random_scene, with_grad
from ctgs.render import render
torch.set_num_threads(1)  # the forward's statistics are summed per thread, in the order threads take tiles
case = random_scene(60, seed=5, width=64, height=48, sh_degree=3, max_res=8)
s, cam = with_grad(cast(case.surfels, torch.float32)), case.camera.to("cpu", torch.float32)
out = render(s, cam, backend="cpu", error_image=torch.rand(48, 64, generator=torch.Generator().manual_seed(1)))
g = torch.Generator().manual_seed(7)
loss = sum((o * (torch.rand(o.shape, generator=g) - 0.3)).sum() for o in (out.rgb, out.alpha, out.depth))
grads = torch.autograd.grad(loss, [getattr(s, n) for n in FLOAT_INPUTS])
torch.save([out.rgb, out.alpha, out.depth, out.stats.err, *grads], {path!r})
"""


def test_texel_fetch_with_and_without_avx2_gathers_gives_the_same_bits(tmp_path):
    """Float lanes fetch texels with AVX2 gathers where the CPU has them, else lane by lane (CTGS_CPU_GATHER=0, or
    a CPU without AVX2): the same products summed in the same order, so the same images and gradients, bit for bit."""
    results = []
    for gather in ("1", "0"):
        path = tmp_path / f"gather{gather}.pt"
        script = _FETCH_SCRIPT.format(tests=str(Path(__file__).parent), path=str(path))
        env = {**os.environ, "CTGS_CPU_GATHER": gather}
        subprocess.run([sys.executable, "-c", script], env=env, check=True, timeout=600)
        results.append(torch.load(path))
    assert results[0][-1].abs().max() > 0  # the texel gradients (the last float input) are not all zero
    for x, y in zip(*results):
        assert torch.equal(x, y)
