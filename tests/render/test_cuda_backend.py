"""CUDA backend (kernels/cuda) vs the C++ CPU backend: identical tile lists, forward images, per-primitive
error statistics and gradients w.r.t. every input, on the CPU tests' scenes and the extremes sweep.

Everything but the last two tests needs a GPU (skipped cleanly without one). The last two always run:
the cuda backend fails with one clear UserError on a machine without a GPU, and the CUDA sources compile
with nvcc (`kernels/check_cuda_build.py`, skipped only if nvcc is missing).

Tolerances: the CUDA and CPU kernels call the same header math (kernels/include/ctgs) in the same
per-pixel order and nvcc builds with -fmad=false, so they differ only by the last bits of exp() and sqrt()
(CUDA's are not glibc's) and by the order of atomic sums over pixels. Each tolerance below is the worst
error observed on an H200 over every case of this file, times 10, rounded up to 1, 2 or 5 x 10^k
(benchmarks/results/cuda_agreement/aad8882.md, written by benchmarks/cuda_agreement.py from a run with
CTGS_AGREEMENT_LOG; the table names the case of each worst error).
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from scenes import FLOAT_INPUTS, bad_value_cases, cast, make_surfels, pinhole, quat_axis_angle, random_scene, with_grad

import ctgs.render.api as api
from ctgs.errors import UserError
from ctgs.render import render

HAS_CUDA = torch.cuda.is_available()
# Measurement hooks for the agreement table (benchmarks/cuda_agreement.py): with CTGS_AGREEMENT_LOG=FILE every
# comparison below appends its observed error (one JSON line: test, kind, name, dtype, err, scale, tol) to
# FILE before it asserts; CTGS_AGREEMENT_RECORD_ONLY=1 also skips the asserts (a measuring run, so that one
# failure does not hide the comparisons after it). Neither is set in a normal test run.
AGREEMENT_LOG = os.environ.get("CTGS_AGREEMENT_LOG", "")
RECORD_ONLY = os.environ.get("CTGS_AGREEMENT_RECORD_ONLY", "") == "1"
# CTGS_CUDA_TESTS_ON_CPU=1 on a machine without a GPU runs the GPU tests with the CPU backend on both sides:
# it checks this file's own code (helpers, shapes, thresholds), never the CUDA kernels.
DRY_RUN = not HAS_CUDA and os.environ.get("CTGS_CUDA_TESTS_ON_CPU", "") == "1"
GPU = "cpu" if DRY_RUN else "cuda"  # device and backend name of the side under test
needs_cuda = pytest.mark.skipif(not (HAS_CUDA or DRY_RUN),
                                reason="no CUDA device (torch.cuda.is_available() is False)")

# Observed worst cases in brackets: the larger of two runs on an H200 (the rasterizer kernels
# were the same in both; the second had the preprocessing kernels of kernels/cuda/dense.cu on the GPU side,
# where the first used PyTorch ops, which is why its means/quats gradients differed more from the CPU's).
# benchmarks/results/cuda_agreement/aad8882.md (second run) and cuda_agreement/first_9b2c345.md (first run).
# Images: max |cuda - cpu| / max(1, |cpu|) per pixel (absolute for rgb and alpha in [0, 1], relative for
# depths beyond 1, which reach 1e8 in the extremes sweep where float32 rounds them to 8 units).
ATOL_F64 = 1e-13  # [5.7e-15 depth, 5.0e-15 alpha]
ATOL_F32 = 5e-5  # [3.0e-6 depth, 2.7e-6 alpha]
# Gradients: max |cuda - cpu| / max |cpu gradient| per input (atomics sum in arbitrary order).
GRAD_RTOL_F64 = 1e-12  # [5.7e-14 quats, first run]
GRAD_RTOL_F32 = 2e-4  # [1.7e-5 quats, 1.1e-5 means, first run; 700 surfels on 3x3 tiles]
# Statistics contrib / err: absolute (sums of w and e w over a primitive's pixels).
STATS_ATOL_F64 = 2e-12  # [1.1e-13 contrib]
STATS_ATOL_F32 = 5e-4  # [4.6e-5 contrib]
# The preprocessing kernels against their PyTorch definitions (values and gradients, relative as above).
PRE_TOL_F64 = 2e-14  # [1.6e-15 SH degree 3 colour]
PRE_TOL_F32 = 1e-5  # [6.5e-7 SH degree 3 colour]
# float32 statistics: a pixel whose alpha lies within an ulp of MIN_ALPHA (or whose T of T_EPS) can be
# blended by one backend and not the other; a handful of such pixels in a whole scene is tolerated
# (observed: 0).
MAX_COUNT_MISMATCH_F32 = 3

SEEDS = (0, 1, 2)
DTYPES = [torch.float64, torch.float32]
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _poison(monkeypatch):
    """Fresh outputs start as NaN on both backends: a pixel a kernel never wrote shows up."""
    monkeypatch.setattr(api, "POISON_OUTPUTS", True)


def _to(s, device):
    return replace(s, **{f: getattr(s, f).to(device) for f in FLOAT_INPUTS + ("tex_res", "tex_offset")})


def _loss(out, seed: int):
    g = torch.Generator().manual_seed(100 + seed)
    return sum((o * (torch.rand(o.shape, generator=g, dtype=torch.float64).to(o.dtype).to(o.device) - 0.3)).sum()
               for o in (out.rgb, out.alpha, out.depth, out.depth2))


def _render_both(s, cam, dtype, *, background=None, error_image=None, grads=False, seed=0):
    """Render on the CPU backend (CPU tensors) and the CUDA backend (same values on the GPU). Returns
    {backend: (RenderOutput on the CPU, gradients of _loss w.r.t. FLOAT_INPUTS + background or None)}."""
    res = {}
    for backend, device in (("cpu", "cpu"), ("cuda", GPU)):
        sd = _to(s, device)
        sd = with_grad(sd) if grads else sd
        bg = None
        if background is not None:
            bg = background.to(device).detach().clone().requires_grad_(grads)
        err = None if error_image is None else error_image.to(device)
        out = render(sd, cam.to(device, dtype), backend=backend if device != "cpu" else "cpu", background=bg,
                     error_image=err)
        g = None
        if grads:
            inputs = [getattr(sd, n) for n in FLOAT_INPUTS] + ([bg] if bg is not None else [])
            g = [t.cpu() for t in torch.autograd.grad(_loss(out, seed), inputs)]
        cpu_out = replace(out, rgb=out.rgb.detach().cpu(), alpha=out.alpha.detach().cpu(),
                          depth=out.depth.detach().cpu(), median_depth=out.median_depth.cpu(),
                          depth2=out.depth2.detach().cpu(),
                          stats=None if out.stats is None else replace(
                              out.stats, count=out.stats.count.cpu(), contrib=out.stats.contrib.cpu(),
                              err=out.stats.err.cpu()))
        res[backend] = (cpu_out, g)
    return res


def _max_abs_diff(x: torch.Tensor, y: torch.Tensor, mixed: bool = False) -> float:
    """max |x - y| in float64 (mixed: max |x - y| / max(1, |y|)); inf where either side is non-finite and they
    differ (NaN never passes)."""
    if x.numel() == 0:
        return 0.0
    x, y = x.double(), y.double()
    d = torch.where(x == y, torch.zeros_like(x), (x - y).abs())  # equal infinities differ by 0, not NaN
    if mixed:
        d = d / y.abs().clamp_min(1.0)
    return float(torch.nan_to_num(d, nan=math.inf).max())


def _record(kind: str, name: str, dtype, err: float, scale: float | None, tol: float) -> None:
    """Append one observed error to CTGS_AGREEMENT_LOG (no-op when unset). err: absolute for images and
    statistics, relative to `scale` (max |CPU gradient|) for gradients, as each assert compares it."""
    if not AGREEMENT_LOG:
        return
    import json

    rec = {"test": os.environ.get("PYTEST_CURRENT_TEST", "").split(" ")[0], "kind": kind, "name": name,
           "dtype": str(dtype).replace("torch.", ""), "err": err, "scale": scale, "tol": tol}
    with open(AGREEMENT_LOG, "a") as fh:
        fh.write(json.dumps(rec) + "\n")


def _assert_images_close(a, b, dtype):
    atol = ATOL_F64 if dtype == torch.float64 else ATOL_F32
    for name in ("rgb", "alpha", "depth", "median_depth", "depth2"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == dtype and x.shape == y.shape, name
        err = _max_abs_diff(x, y, mixed=True) if bool(torch.isfinite(x).all()) else math.inf
        _record("image", name, dtype, err, None, atol)
        if RECORD_ONLY:
            continue
        assert torch.isfinite(x).all(), f"{name}: non-finite (or never written) pixels on cuda"
        assert err <= atol, f"{name}: max |cuda - cpu| / max(1, |cpu|) = {err:.3g} > {atol:.3g}"


def _assert_grads_close(ga, gb, names, dtype):
    rtol = GRAD_RTOL_F64 if dtype == torch.float64 else GRAD_RTOL_F32
    for name, x, y in zip(names, ga, gb):
        assert x.shape == y.shape, name
        scale = y.abs().max().item() if y.numel() else 0.0
        err = _max_abs_diff(x, y) if bool(torch.isfinite(x).all()) else math.inf
        _record("grad", name, dtype, err / max(scale, 1e-30), scale, rtol)
        if RECORD_ONLY:
            continue
        assert torch.isfinite(x).all(), f"{name}: non-finite gradient on cuda"
        assert err <= rtol * max(scale, 1e-30), f"{name}: max abs err {err:.3g} vs max |grad| {scale:.3g}"


def _case(seed: int, dtype: torch.dtype, n: int = 60, width: int = 64, height: int = 48):
    # The CPU backend tests' scene: non-square image, off-centre principal point, overlapping tilted
    # textured surfels, some partly off-screen (scenes.random_scene).
    case = random_scene(n, seed=seed, width=width, height=height, sh_degree=3, max_res=8)
    return cast(case.surfels, dtype), case.camera.to("cpu", dtype)


# ---- agreement with the CPU backend ---------------------------------------------------------------------


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n,width,height", [(60, 64, 48), (700, 40, 36), (40, 100, 70)],
                         ids=["cpu-test-scene", "multi-batch", "partial-tiles"])
def test_tile_lists_identical_to_cpu(dtype, n, width, height):
    """Same pairs, same per-tile order (centre depth, then index) as the CPU binning, bit for bit.
    "multi-batch": ~700 surfels on 3x3 tiles put more than one shared-memory batch in every tile."""
    from ctgs.ops.ext import load_cpu
    from ctgs.ops.ext_cuda import load_cuda
    from ctgs.render.preprocess import to_camera_space

    s, cam = _case(3, dtype, n, width, height)
    prims = to_camera_space(s.means, s.quats, s.sh, cam, 3)
    args = [prims.mu_c, prims.Rc, s.scales, s.opacities, prims.colors, s.texel_size.contiguous(), s.textures,
            s.tex_res, s.tex_offset, torch.zeros(3, dtype=dtype)]
    cam_args = (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.near)
    load_cpu() if DRY_RUN else load_cuda()
    a = torch.ops.ctgs.rasterize_forward(*[t.contiguous() for t in args], *cam_args, None, 1, True)
    b = torch.ops.ctgs.rasterize_forward(*[t.contiguous().to(GPU) for t in args], *cam_args, None, 2, True)
    offsets, lists = (a[5], b[5].cpu()), (a[6], b[6].cpu())
    same = torch.equal(offsets[0], offsets[1]) and torch.equal(lists[0], lists[1])
    _record("bins", f"tile lists ({n} prims, {width}x{height})", dtype, 0.0 if same else 1.0, None, 0.0)
    assert torch.equal(offsets[0], offsets[1])
    assert torch.equal(lists[0], lists[1])
    assert lists[0].numel() > 0
    if n == 700:
        assert int((offsets[0][1:] - offsets[0][:-1]).max()) > 256  # more than one batch per tile
    torch.testing.assert_close(b[0].cpu(), a[0], atol=ATOL_F64 if dtype == torch.float64 else ATOL_F32, rtol=0)


@needs_cuda
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_forward_and_stats_match_cpu(seed, dtype):
    s, cam = _case(seed, dtype)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    err = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    r = _render_both(s, cam, dtype, background=bg, error_image=err.to(dtype))
    a, b = r["cuda"][0], r["cpu"][0]
    assert b.alpha.mean() > 0.2  # the scene covers a good part of the image
    _assert_images_close(a, b, dtype)
    assert b.stats.count.sum() > 0
    mismatch = int((a.stats.count - b.stats.count).abs().sum())
    atol = STATS_ATOL_F64 if dtype == torch.float64 else STATS_ATOL_F32
    rtol = 0
    _record("stats", "count (pixels, summed |diff|)", dtype, float(mismatch), None,
            0.0 if dtype == torch.float64 else float(MAX_COUNT_MISMATCH_F32))
    for name in ("contrib", "err"):
        x, y = getattr(a.stats, name), getattr(b.stats, name)
        _record("stats", name, dtype, _max_abs_diff(x, y), float(y.abs().max()), atol)
    if RECORD_ONLY:
        return
    if dtype == torch.float64:
        assert torch.equal(a.stats.count, b.stats.count)
    else:
        assert mismatch <= MAX_COUNT_MISMATCH_F32
    torch.testing.assert_close(a.stats.contrib, b.stats.contrib, atol=atol, rtol=rtol)
    torch.testing.assert_close(a.stats.err, b.stats.err, atol=atol, rtol=rtol)


@needs_cuda
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_match_cpu(seed, dtype):
    s, cam = _case(seed, dtype)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    r = _render_both(s, cam, dtype, background=bg, grads=True, seed=seed)
    for name, y in zip(FLOAT_INPUTS + ("background",), r["cpu"][1]):
        assert y.abs().max() > 0, f"{name}: the CPU gradient is zero, the comparison would prove nothing"
    _assert_grads_close(r["cuda"][1], r["cpu"][1], FLOAT_INPUTS + ("background",), dtype)


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
def test_many_primitives_per_tile_forward_backward(dtype):
    """Several shared-memory batches per tile, forward (front to back) and backward (back to front)."""
    s, cam = _case(7, dtype, n=700, width=40, height=36)
    r = _render_both(s, cam, dtype, grads=True, seed=7)
    _assert_images_close(r["cuda"][0], r["cpu"][0], dtype)
    _assert_grads_close(r["cuda"][1], r["cpu"][1], FLOAT_INPUTS, dtype)


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("sh_lanes", ["0", "1"])
def test_preprocess_kernels_match_pytorch(dtype, sh_lanes, monkeypatch):
    """The per-primitive kernels (kernels/cuda/dense.cu: camera space, SH colour of every degree) against
    their PyTorch definitions on the same device, values and gradients; with the edge cases the CPU kernels
    are tested on: a zero quaternion (norm clamped), a mean at the camera centre (direction 0). The SH backward
    both ways: one thread per primitive, and lanes per coefficient (CTGS_CUDA_SH_LANES=1; 16 lanes for 16 SH
    rows, 4 for 4)."""
    monkeypatch.setenv("CTGS_CUDA_SH_LANES", sh_lanes)
    from ctgs.render.geometry import quat_to_rotmat
    from ctgs.render.preprocess import camera_space, camera_space_torch
    from ctgs.render.sh import sh_to_color, view_color, view_dirs

    g = torch.Generator().manual_seed(11)
    n = 300
    means = (torch.randn(n, 3, generator=g, dtype=torch.float64) * 2).to(dtype)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64).to(dtype)
    quats[0] = 0.0
    sh = torch.randn(n, 16, 3, generator=g, dtype=torch.float64).to(dtype)
    view = torch.eye(4, dtype=dtype)
    view[:3, :3] = quat_to_rotmat(torch.tensor([quat_axis_angle((0.3, -0.5, 0.8), 0.7)], dtype=dtype))[0]
    view[:3, 3] = torch.tensor([0.2, -0.4, 1.5], dtype=dtype)
    center = -view[:3, :3].T @ view[:3, 3]
    means[1] = center  # direction 0
    tol = PRE_TOL_F64 if dtype == torch.float64 else PRE_TOL_F32
    dev = torch.device(GPU)
    m, q, s_, v, c = (t.to(dev) for t in (means, quats, sh, view, center))
    cots = None
    for name, fused, plain, inputs in (
            ("camera_space", lambda a, b: camera_space(a, b, v), lambda a, b: camera_space_torch(a, b, v), (m, q)),
            *[(f"sh_color deg {d}", lambda a, b, d=d: (view_color(a, b, c, d),),
               lambda a, b, d=d: (sh_to_color(b, view_dirs(a, c), d),), (m, s_)) for d in range(4)],
            ("sh_color deg 1 of 4 rows", lambda a, b: (view_color(a, b, c, 1),),
             lambda a, b: (sh_to_color(b, view_dirs(a, c), 1),), (m, s_[:, :4].contiguous()))):
        xs = [t.detach().clone().requires_grad_(True) for t in inputs]
        ys = [t.detach().clone().requires_grad_(True) for t in inputs]
        out_f, out_p = fused(*xs), plain(*ys)
        gen = torch.Generator().manual_seed(5)
        cots = [torch.rand(o.shape, generator=gen, dtype=torch.float64).to(dtype).to(dev) - 0.5 for o in out_p]
        g_f = torch.autograd.grad(sum((o * w).sum() for o, w in zip(out_f, cots)), xs, allow_unused=True)
        g_p = torch.autograd.grad(sum((o * w).sum() for o, w in zip(out_p, cots)), ys, allow_unused=True)
        # (degree 0 does not depend on the means: PyTorch returns no gradient, the kernel zeros)
        g_f = [torch.zeros_like(x) if t is None else t for t, x in zip(g_f, xs)]
        g_p = [torch.zeros_like(x) if t is None else t for t, x in zip(g_p, ys)]
        for k, (a, b) in enumerate(zip(out_f, out_p)):
            err = _max_abs_diff(a.detach(), b.detach(), mixed=True)
            _record("preprocess", f"{name} output {k}", dtype, err, None, tol)
            if not RECORD_ONLY:
                assert err <= tol, f"{name} output {k}: {err:.3g}"
        for k, (a, b) in enumerate(zip(g_f, g_p)):
            scale = float(b.abs().max())
            err = _max_abs_diff(a, b) / max(scale, 1e-30)
            _record("preprocess", f"{name} grad {k}", dtype, err, scale, tol)
            if not RECORD_ONLY:
                assert torch.isfinite(a).all() and err <= tol, f"{name} grad {k}: {err:.3g}"
    assert cots is not None


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("aggregate", ["1", "0"])
def test_texel_gradients_aggregated_per_warp_match_cpu(dtype, aggregate, monkeypatch):
    """The backward's texel gradients summed per run of warp lanes that share a texel (scatter_texel_grad, the
    default) and one atomic per lane (CTGS_CUDA_TEX_AGG=0) both equal the CPU backend's: surfels covering most
    of a 96x64 image with texels from 1/4 pixel to 20 pixels wide, so that runs are long, short, interleaved
    and broken by texture edges."""
    monkeypatch.setenv("CTGS_CUDA_TEX_AGG", aggregate)
    for k, texel in enumerate((0.002, 0.02, 0.1, 0.4)):
        case = random_scene(12, seed=20 + k, width=96, height=64, sh_degree=1, max_res=16)
        s = cast(case.surfels, dtype)
        s = replace(s, scales=s.scales * 4, texel_size=torch.full_like(s.texel_size, texel))
        r = _render_both(s, case.camera.to("cpu", dtype), dtype, grads=True, seed=k)
        _assert_images_close(r["cuda"][0], r["cpu"][0], dtype)
        _assert_grads_close(r["cuda"][1], r["cpu"][1], FLOAT_INPUTS, dtype)


def _jagged_case(dtype, seed=3):
    from ctgs.model.surfels import jagged_offsets

    g = torch.Generator().manual_seed(seed)
    n, m = 40, 57
    sizes = torch.tensor([0, 2, 4, 8, 6])
    old_res = sizes[torch.randint(0, 5, (n, 2), generator=g)]
    old_res[old_res.min(1).values == 0] = 0  # a primitive has a texture on both axes or none
    old_res = old_res.to(torch.int32)
    old_off = jagged_offsets(old_res)
    t_old = int((old_res.long()[:, 0] * old_res.long()[:, 1]).sum())
    bufs = [torch.randn(t_old, 3, generator=g, dtype=torch.float64).to(dtype) for _ in range(3)]
    src = torch.randint(0, n, (m,), generator=g)  # repeats: duplicated primitives (splits)
    shift = torch.randint(-2, 3, (m, 2), generator=g)
    new_res = sizes[torch.randint(0, 5, (m, 2), generator=g)]
    new_res[new_res.min(1).values == 0] = 0
    new_res[-1] = 0  # a layout that ends in an empty texture
    return bufs, old_res, old_off, src, shift, new_res.to(torch.int32)


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
def test_jagged_remap_kernel_matches_cpu(dtype, monkeypatch):
    """The CUDA re-layout of textures and their Adam moments (kernels/cuda/dense.cu jagged_remap_kernel) copies
    exactly what the CPU kernel and the PyTorch definition copy: crops, pads, shifts, repeats, empty textures;
    and jagged.replace_blocks (upscale/downscale) through it."""
    from ctgs.model import jagged

    bufs, old_res, old_off, src, shift, new_res = _jagged_case(dtype)
    want, off_cpu = jagged.remap(bufs, old_res, old_off, src, shift, new_res)
    dev = torch.device(GPU)
    moved = [x.to(dev) for x in (old_res, old_off, src, shift, new_res)]
    got, off = jagged.remap([b.to(dev) for b in bufs], *moved)
    assert torch.equal(off.cpu(), off_cpu)
    for a, b in zip(got, want):
        assert a.shape == b.shape and a.dtype == b.dtype and a.device.type == dev.type and torch.equal(a.cpu(), b)
    # the PyTorch index arithmetic on the same device
    plain = jagged._torch_remap([b.to(dev) for b in bufs], *moved[:-1], moved[-1].to(torch.int32),
                                off.to(dev))
    for a, b in zip(plain, want):
        assert torch.equal(a.cpu(), b)
    # replace_blocks: primitives 1 and 5 get new 4x2 blocks, the rest keep theirs.
    res2 = old_res.clone()
    prims = torch.tensor([1, 5])
    res2[prims] = torch.tensor([4, 2], dtype=torch.int32)
    vals = [torch.full((2, 2, 4, 3), float(k + 1), dtype=dtype) for k in range(3)]
    want2, _ = jagged.replace_blocks(bufs, old_res, old_off, res2, [(prims, vals)])
    got2, _ = jagged.replace_blocks([b.to(dev) for b in bufs], old_res.to(dev), old_off.to(dev), res2.to(dev),
                                    [(prims.to(dev), [v.to(dev) for v in vals])])
    for a, b in zip(got2, want2):
        assert torch.equal(a.cpu(), b)


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
def test_value_checks_in_one_kernel_match_the_cpu(dtype):
    """surfel_value_flags on the GPU (one kernel; validate_inputs' check of CUDA inputs) passes valid surfels and
    flags every value problem the CPU check flags, anywhere in a texture buffer of many blocks; render() then names
    the argument as on the CPU."""
    from ctgs.ops.ext import load_cpu
    from ctgs.ops.ext_cuda import load_cuda

    load_cpu() if DRY_RUN else load_cuda()
    case = random_scene(50, seed=4, dtype=dtype, max_res=8)
    s, cam = case.surfels, case.camera
    s = replace(s, textures=torch.cat([s.textures, torch.rand(70000, 3, dtype=dtype) - 0.5]))
    dev = torch.device(GPU)

    def flags(x):
        t = [getattr(x, k).contiguous().to(dev) for k in api._SURFEL_FLOATS]
        return int(torch.ops.ctgs.surfel_value_flags(*t, x.tex_res.to(dev), x.tex_offset.to(dev), 0))

    assert flags(s) == 0 and flags(replace(s, sh=s.sh[:, :4])) == 0
    for name, b in bad_value_cases(s):
        assert flags(b) != 0, name
        on_gpu = replace(b, **{k: getattr(b, k).to(dev) for k in (*api._SURFEL_FLOATS, "tex_res", "tex_offset")})
        with pytest.raises(ValueError, match=name):
            api.validate_inputs(on_gpu, cam.to(GPU, dtype), None, None)


@needs_cuda
def test_auto_uses_cuda_for_gpu_tensors_and_rejects_cpu_tensors():
    s, cam = _case(0, torch.float32)
    sd, camd = _to(s, GPU), cam.to(GPU, torch.float32)
    auto = render(sd, camd, backend="auto")
    cuda = render(sd, camd, backend="cuda" if not DRY_RUN else "cpu")
    assert auto.rgb.device == sd.means.device and torch.equal(auto.rgb, cuda.rgb)
    if not DRY_RUN:
        with pytest.raises(ValueError, match="CUDA tensors"):
            render(s, cam, backend="cuda")


# ---- extremes: finite everywhere, and equal to the CPU backend -------------------------------------------

MAGNITUDES = (1e-8, 1e-4, 1.0, 1e4, 1e8)


def _pair(dtype, *, depth=2.0, scale=0.5, texel=0.1, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), res=(6, 6)):
    """Two overlapping textured surfels in front of an identity camera (as in test_cpu_extremes)."""
    return make_surfels(means=[[0.0, 0.0, depth], [0.2, 0.1, depth * 1.3]],
                        quats=[list(quat), quat_axis_angle((0.3, 1.0, 0.0), 0.4)],
                        scales=[[scale, scale * 0.7], [scale * 0.8, scale]], opacities=[opacity, 0.5],
                        sh=[[0.3, 0.2, 0.1], [0.1, 0.4, 0.2]], texel_size=[texel, texel * 1.3],
                        tex_res=[list(res), [3, 2]], dtype=dtype, seed=3)


def _extreme(s, cam, dtype):
    r = _render_both(s, cam, dtype, grads=True)
    _assert_images_close(r["cuda"][0], r["cpu"][0], dtype)
    _assert_grads_close(r["cuda"][1], r["cpu"][1], FLOAT_INPUTS, dtype)
    return r["cuda"][0]


def _cam(dtype, w=24, h=20, f=20.0, near=0.01):
    return pinhole(w, h, f, near=near).to("cpu", dtype)


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("mag", MAGNITUDES)
def test_extreme_scales_distances_texels(dtype, mag):
    _extreme(_pair(dtype, scale=mag), _cam(dtype), dtype)
    _extreme(_pair(dtype, depth=mag, scale=0.2 * mag, texel=0.05 * mag), _cam(dtype, near=1e-9 if mag < 1e-2 else 0.01),
             dtype)
    _extreme(_pair(dtype, texel=mag), _cam(dtype), dtype)


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
def test_extreme_opacity_grazing_near_plane_resolutions(dtype):
    for opacity in (0.0, 1.0):
        _extreme(_pair(dtype, opacity=opacity), _cam(dtype), dtype)
    for angle_deg in (89.0, 89.9999, 90.0):
        out = _extreme(_pair(dtype, quat=quat_axis_angle((0.0, 1.0, 0.0), math.radians(angle_deg))), _cam(dtype), dtype)
        assert out.alpha.max() > 0  # the screen-space fallback keeps an edge-on surfel visible
    for res in ((1, 1), (256, 256), (1, 7)):
        _extreme(_pair(dtype, res=res, texel=1.0 / max(res)), _cam(dtype), dtype)
    near = make_surfels(
        means=[[0.0, 0.0, -1.0], [0.1, 0.0, 0.3], [0.0, 0.1, 0.011], [0.0, 0.0, 1.5]],
        quats=[[1.0, 0.0, 0.0, 0.0], quat_axis_angle((0.0, 1.0, 0.0), 1.2), quat_axis_angle((1.0, 0.0, 0.0), 0.3),
               [1.0, 0.0, 0.0, 0.0]],
        scales=[[1.0, 1.0], [0.6, 0.2], [0.5, 0.5], [0.4, 0.4]], opacities=[0.9, 0.8, 0.7, 0.6],
        sh=[[0.3, 0.2, 0.1]] * 4, texel_size=[0.05] * 4, tex_res=[[4, 4]] * 4, dtype=dtype, seed=4)
    assert _extreme(near, _cam(dtype, 32, 24, 25.0), dtype).alpha.max() > 0.5
    _extreme(_pair(dtype), _cam(dtype, 1, 1, 2.0), dtype)  # a 1x1 image


@needs_cuda
@pytest.mark.parametrize("dtype", DTYPES)
def test_no_texels_and_empty_scene(dtype):
    s = replace(_pair(dtype), tex_res=torch.zeros(2, 2, dtype=torch.int32),
                tex_offset=torch.zeros(2, dtype=torch.int64), textures=torch.zeros(0, 3, dtype=dtype))
    _extreme(s, _cam(dtype), dtype)
    empty = make_surfels(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 2),
                         opacities=torch.zeros(0), sh=torch.zeros(0, 1, 3), texel_size=torch.zeros(0),
                         tex_res=torch.zeros(0, 2), dtype=dtype)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype, device=GPU, requires_grad=True)
    sg = with_grad(_to(empty, GPU))
    out = render(sg, _cam(dtype).to(GPU, dtype), backend="cpu" if DRY_RUN else "cuda", background=bg,
                 error_image=torch.ones(20, 24, dtype=dtype, device=GPU))
    assert torch.equal(out.rgb, bg.detach().expand(20, 24, 3))
    assert out.alpha.abs().max() == 0 and out.stats.count.shape == (0,)
    (g_bg, g_means) = torch.autograd.grad(out.rgb.sum(), [bg, sg.means])
    assert torch.equal(g_bg.cpu(), torch.full((3,), 480.0, dtype=dtype)) and g_means.shape == (0, 3)


# ---- always run ------------------------------------------------------------------------------------------


@pytest.mark.skipif(HAS_CUDA, reason="checks the message shown on machines without a GPU")
def test_cuda_backend_without_gpu_is_one_clear_user_error():
    s = _pair(torch.float32)
    with pytest.raises(UserError, match=r"needs an NVIDIA GPU.*--backend cpu"):
        render(s, _cam(torch.float32), backend="cuda")


def _check_cuda_build_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("check_cuda_build", ROOT / "kernels" / "check_cuda_build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# What nvcc -Xptxas -v prints for two kernels (a register-capped one with spills, one without shared memory).
PTXAS_SAMPLE = """\
ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function '_ZN4ctgs3gpu12_GLOBAL__N_115backward_kernelIfLi3EEEvv' for 'sm_90'
ptxas info    : Function properties for _ZN4ctgs3gpu12_GLOBAL__N_115backward_kernelIfLi3EEEvv
    32 bytes stack frame, 48 bytes spill stores, 52 bytes spill loads
ptxas info    : Used 80 registers, used 1 barriers, 32 bytes cumulative stack size, 33796 bytes smem
ptxas info    : Compiling entry function '_ZN4ctgs3gpu4noopIdEEvv' for 'sm_80'
ptxas info    : Function properties for _ZN4ctgs3gpu4noopIdEEvv
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 6 registers, used 0 barriers
"""


def test_ptxas_resources_are_parsed_per_kernel_and_arch():
    mod = _check_cuda_build_module()
    rows = mod.parse_ptxas(PTXAS_SAMPLE)
    assert rows == [
        {"kernel": "_ZN4ctgs3gpu12_GLOBAL__N_115backward_kernelIfLi3EEEvv", "arch": "sm_90", "stack": 32,
         "spill_stores": 48, "spill_loads": 52, "registers": 80, "smem": 33796},
        {"kernel": "_ZN4ctgs3gpu4noopIdEEvv", "arch": "sm_80", "stack": 0, "spill_stores": 0, "spill_loads": 0,
         "registers": 6, "smem": 0},
    ]
    table = mod.resource_table(rows)
    assert "| 80 | 48 / 52 | 32 | 33796 |" in table
    if shutil.which("c++filt"):
        assert "`backward_kernel<float, 3>`" in table and "`noop<double>`" in table


# ~100 s of nvcc and g++ on 2 cores (the binding's torch headers and cub's radix sort dominate): tests/render/conftest.py
# starts it in the background when collection ends, and cuda_check waits for its result
@pytest.mark.slow
@pytest.mark.skipif(shutil.which("nvcc") is None, reason="nvcc not on PATH")
def test_cuda_sources_compile_with_nvcc(cuda_check):
    p = cuda_check
    assert p.returncode == 0, p.stdout + p.stderr
    n_cu = len(list((ROOT / "kernels" / "cuda").glob("*.cu")))
    assert n_cu >= 4
    assert p.stdout.count("ok ") >= n_cu, p.stdout  # every .cu compiled (plus the binding if checked)
    # ptxas reported the float backward kernel for both architectures (the occupancy figures docs/guide/gpu.md cites)
    for arch in ("sm_80", "sm_90"):
        assert any("backward_kernel<float" in line and f"| {arch} |" in line for line in p.stdout.splitlines()), \
            p.stdout
