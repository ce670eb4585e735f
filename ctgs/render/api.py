"""`render()`: input validation and backend dispatch (the autograd bridge is ctgs.render.rasterize).

Semantics: docs/reference/renderer.md. The extension backends get camera-space primitives from
`ctgs.render.preprocess` (PyTorch, differentiable); a torch.autograd.Function calls the compiled
forward/backward, whose gradients w.r.t. mu_c, Rc, colors... autograd carries back to means, quats, sh.
"""

from __future__ import annotations

import math

import torch

import ctgs.ops.ext as ext_mod
import ctgs.ops.ext_cuda as ext_cuda_mod
from ctgs.ops.fused import all_finite
from ctgs.render.camera import Camera
from ctgs.render.cuda_backend import render_cuda
from ctgs.render.rasterize import rasterize, rasterize_error_fn
from ctgs.render.reference import render_reference
from ctgs.render.types import BackwardStats, RenderOutput, SurfelInputs

BACKENDS = ("auto", "cpu", "cuda", "reference")
# Debug aid: fresh output buffers start as NaN so a pixel the kernel never wrote shows up (tests set it to True).
POISON_OUTPUTS = False


# ---- validation ------------------------------------------------------------------------------------------
def _fail(name: str, expected: str, t: torch.Tensor) -> None:
    raise ValueError(f"{name} must have shape {expected}, got {list(t.shape)} ({t.dtype}, {t.device})")


def _check_float(name: str, t: torch.Tensor, expected: str, shape_ok: bool, like: torch.Tensor,
                 finite: bool = True) -> None:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name} must be a tensor of shape {expected}, got {type(t).__name__}")
    if not shape_ok:
        _fail(name, expected, t)
    if t.dtype != like.dtype:
        raise ValueError(f"{name} must have dtype {like.dtype} (the dtype of means), shape {expected}; got {t.dtype}")
    if t.device != like.device:
        raise ValueError(f"{name} must be on {like.device} (the device of means), shape {expected}; got {t.device}")
    if finite and t.numel() and not all_finite(t):
        raise ValueError(f"{name} (shape {expected}) contains NaN or infinite values")


_SURFEL_FLOATS = ("means", "quats", "scales", "opacities", "sh", "texel_size", "textures")


def _values_ok_fused(s: SurfelInputs) -> bool:
    """True if the compiled check (one pass per tensor, no temporaries) found every value check of
    validate_inputs passed; False if it cannot run here or some check may fail (then the PyTorch checks run
    and name the problem). For CPU inputs whose shapes, dtypes and devices are already checked. A training
    step's inputs are ~1-2M values: the PyTorch checks cost ~0.6 ms."""
    # Only once the extension is loaded (by a CPU render): validating must never trigger its build, e.g. for
    # the reference backend.
    if ext_mod._cpu_module is None:
        return False
    with torch.no_grad():
        # (the SH of a step below degree 3 is a slice: a small copy)
        return bool(torch.ops.ctgs.surfel_values_ok(*[getattr(s, name).detach().contiguous() for name in _SURFEL_FLOATS],
                                                    s.tex_res.contiguous(), s.tex_offset.contiguous(),
                                                    torch.get_num_threads()))


def _values_ok_device(s: SurfelInputs, finite: list[torch.Tensor]) -> bool:
    """True if every value check of validate_inputs passes, found with one device-to-host transfer: the checks
    run as a few reductions on the inputs' device (for CUDA inputs whose shapes, dtypes and devices are already
    checked) and their flags come back together. The checks one by one synchronised ~16 times per render (0.5 ms
    at 1M textured surfels on an H200, and the CPU could not queue the render meanwhile); False sends the caller
    to them to name the problem. `finite`: more tensors that must hold finite values (camera, background).
    Once the CUDA extension is loaded the surfel checks are its one kernel (surfel_value_flags) instead of ~13
    PyTorch reductions."""
    with torch.no_grad():
        bad = [~torch.isfinite(t.detach()).all().to(s.means.device) for t in finite if t.numel()]
        if ext_cuda_mod._cuda_module is not None and s.means.is_cuda:
            bad.append(torch.ops.ctgs.surfel_value_flags(
                *[getattr(s, name).detach().contiguous() for name in _SURFEL_FLOATS], s.tex_res.contiguous(),
                s.tex_offset.contiguous(), 0) != 0)
            return not bool(torch.stack([b.reshape(()) for b in bad]).any())
        ext = {}
        for name in _SURFEL_FLOATS:
            t = getattr(s, name).detach()
            if t.numel():
                lo, hi = torch.aminmax(t)  # NaN propagates, +-inf shows
                ext[name] = (lo, hi)
                bad.append(~(torch.isfinite(lo) & torch.isfinite(hi)))
        if s.means.shape[0]:
            bad += [ext["scales"][0] <= 0, ext["texel_size"][0] <= 0, ext["opacities"][0] < 0,
                    ext["opacities"][1] > 1, (s.quats.detach().norm(dim=-1) == 0).any(), s.tex_res.min() < 0]
            sizes = s.tex_res[:, 0].long() * s.tex_res[:, 1].long()
            used = sizes > 0
            zero = torch.zeros_like(s.tex_offset)
            bad += [torch.where(used, s.tex_offset, zero).min() < 0,
                    torch.where(used, s.tex_offset + sizes, zero).max() > s.textures.shape[0]]
        if not bad:
            return True
        return not bool(torch.stack([b.reshape(()) for b in bad]).any())


def validate_inputs(s: SurfelInputs, camera: Camera, background: torch.Tensor | None,
                    error_image: torch.Tensor | None) -> None:
    """Raise ValueError naming the argument and its expected shape for any malformed input."""
    m = s.means
    if not isinstance(m, torch.Tensor) or m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"means must have shape [N, 3], got {list(getattr(m, 'shape', []))}")
    if m.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"means must be float32 or float64 with shape [N, 3], got {m.dtype}")
    n = m.shape[0]
    floats = (("means", m, "[N, 3]", True),
              ("quats", s.quats, f"[{n}, 4]", tuple(s.quats.shape) == (n, 4)),
              ("scales", s.scales, f"[{n}, 2]", tuple(s.scales.shape) == (n, 2)),
              ("opacities", s.opacities, f"[{n}]", tuple(s.opacities.shape) == (n,)),
              ("sh", s.sh, f"[{n}, K, 3] with K in (1, 4, 9, 16)",
               s.sh.ndim == 3 and s.sh.shape[0] == n and s.sh.shape[2] == 3 and s.sh.shape[1] in (1, 4, 9, 16)),
              ("texel_size", s.texel_size, f"[{n}] or [{n}, 2]", tuple(s.texel_size.shape) in ((n,), (n, 2))),
              ("textures", s.textures, "[T, 3]", s.textures.ndim == 2 and s.textures.shape[1] == 3))
    for name, t, expected, shape_ok in floats:
        _check_float(name, t, expected, shape_ok, m, finite=False)
    for name, t, dtype, expected in (("tex_res", s.tex_res, torch.int32, f"[{n}, 2] int32"),
                                     ("tex_offset", s.tex_offset, torch.int64, f"[{n}] int64")):
        want = (n, 2) if name == "tex_res" else (n,)
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != want:
            raise ValueError(f"{name} must have shape {expected}, got {list(getattr(t, 'shape', []))}")
        if t.dtype != dtype:
            raise ValueError(f"{name} must have dtype {dtype} (shape {expected}), got {t.dtype}")
        if t.device != m.device:
            raise ValueError(f"{name} must be on {m.device} (the device of means), shape {expected}; got {t.device}")
    if camera.width < 1 or camera.height < 1:
        raise ValueError(f"camera must be at least 1x1 pixels, got {camera.width}x{camera.height}")
    if not all(math.isfinite(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy, camera.near)) or \
            camera.fx == 0 or camera.fy == 0:
        raise ValueError("camera fx, fy, cx, cy, near must be finite and fx, fy non-zero")
    vm = camera.viewmat
    if not isinstance(vm, torch.Tensor) or tuple(vm.shape) != (4, 4):
        raise ValueError("camera.viewmat must be a finite [4, 4] tensor")
    on_host = m.device.type == "cpu"
    if background is not None:
        _check_float("background", background, "[3]", tuple(background.shape) == (3,), m, finite=on_host)
    if error_image is not None:
        _check_float("error_image", error_image, f"[{camera.height}, {camera.width}]",
                     tuple(error_image.shape) == (camera.height, camera.width), m, finite=on_host)
    # The value checks (finite, ranges, layout): one compiled pass on the CPU, one transfer from a GPU; where
    # that finds a problem (or cannot run), the checks below name it.
    if on_host:
        checked = _values_ok_fused(s) and bool(torch.isfinite(vm).all())
    else:
        checked = _values_ok_device(s, [t for t in (vm, background, error_image) if t is not None])
    if checked:
        return
    for name, t, expected, _ in floats:
        if t.numel() and not all_finite(t):
            raise ValueError(f"{name} (shape {expected}) contains NaN or infinite values")
    with torch.no_grad():
        if n and bool((s.scales <= 0).any()):
            raise ValueError(f"scales (shape [{n}, 2], world units) must be > 0")
        if n and bool((s.texel_size <= 0).any()):
            raise ValueError(f"texel_size (shape [{n}] or [{n}, 2], world units per texel) must be > 0")
        if n and bool(((s.opacities < 0) | (s.opacities > 1)).any()):
            raise ValueError(f"opacities (shape [{n}]) must lie in [0, 1]")
        if n and bool((s.quats.norm(dim=-1) == 0).any()):
            raise ValueError(f"quats (shape [{n}, 4]) must have non-zero norm")
        if n and bool((s.tex_res < 0).any()):
            raise ValueError(f"tex_res (shape [{n}, 2] int32) must be >= 0")
        sizes = s.tex_res[:, 0].long() * s.tex_res[:, 1].long()
        used = sizes > 0
        if bool(used.any()):
            end = s.tex_offset[used] + sizes[used]
            if bool((s.tex_offset[used] < 0).any()) or int(end.max()) > s.textures.shape[0]:
                raise ValueError(f"tex_offset (shape [{n}] int64) + res_u*res_v must stay within textures "
                                 f"[T={s.textures.shape[0]}, 3]")
        if not bool(torch.isfinite(vm).all()):
            raise ValueError("camera.viewmat must be a finite [4, 4] tensor")
        for name, t, expected in (("background", background, "[3]"),
                                  ("error_image", error_image, f"[{camera.height}, {camera.width}]")):
            if t is not None and t.numel() and not all_finite(t):
                raise ValueError(f"{name} (shape {expected}) contains NaN or infinite values")


def render(surfels: SurfelInputs, camera: Camera, *, backend: str = "auto", sh_degree: int | None = None,
           background: torch.Tensor | None = None, error_image: torch.Tensor | None = None,
           backward_stats: BackwardStats | None = None) -> RenderOutput:
    """Render `surfels` (SurfelInputs) from `camera`.

    Args:
        backend: "auto" | "cpu" | "cuda" | "reference".
        sh_degree: active SH degree (default: the largest the K of `surfels.sh` allows).
        background: [3] colour behind everything (default black).
        error_image: optional [H, W] per-pixel error; when given, `RenderOutput.stats` holds the
            per-primitive error statistics (no gradient flows through them). May also be a function
            rgb [H, W, 3] -> [H, W] error of this very render (one pass instead of two on the cpu
            backend when no gradient is wanted; the statistics are the same).
        backward_stats: a BackwardStats whose error image, set after this render, the cpu backend's backward
            sums per primitive as well (no second render); other backends leave it empty.
    Returns: RenderOutput.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if callable(error_image):
        return _render_error_fn(surfels, camera, backend, sh_degree, background, error_image)
    validate_inputs(surfels, camera, background, error_image)
    k_coeffs = surfels.sh.shape[1]
    max_degree = math.isqrt(k_coeffs) - 1
    degree = max_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= max_degree:
        raise ValueError(f"sh_degree must be in [0, {max_degree}] for sh of shape [N, {k_coeffs}, 3], got {degree}")
    if backend == "auto":
        backend = "cuda" if surfels.means.is_cuda else "cpu"
    if backend == "reference":
        return render_reference(surfels, camera, sh_degree=degree, background=background, error_image=error_image)
    means = surfels.means
    bg = background if background is not None else means.new_zeros(3)
    if backend == "cuda":
        return render_cuda(surfels, camera, degree, bg, error_image, POISON_OUTPUTS)
    if means.device.type != "cpu":
        raise ValueError(f"the cpu backend needs CPU tensors (means is on {means.device}); pass backend='auto'")
    return rasterize(surfels, camera, degree, bg, error_image, device="cpu", knob=torch.get_num_threads(),
                     poison=POISON_OUTPUTS, backward_stats=backward_stats)


def _render_error_fn(surfels: SurfelInputs, camera: Camera, backend: str, sh_degree: int | None,
                     background: torch.Tensor | None, error_fn) -> RenderOutput:
    """render() with error_image = error_fn(rgb of this render): one pass on the CPU backend (when no
    gradient is wanted), else a render and a second render with the error image."""
    validate_inputs(surfels, camera, background, None)

    def check(e: torch.Tensor) -> None:
        _check_float("error_image", e, f"[{camera.height}, {camera.width}]",
                     isinstance(e, torch.Tensor) and tuple(e.shape) == (camera.height, camera.width), surfels.means)

    means = surfels.means
    wants_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in vars(surfels).values() if isinstance(t, torch.Tensor))
    resolved = ("cuda" if means.is_cuda else "cpu") if backend == "auto" else backend
    if resolved == "cpu" and means.device.type == "cpu" and not wants_grad:
        k_coeffs = surfels.sh.shape[1]
        degree = math.isqrt(k_coeffs) - 1 if sh_degree is None else int(sh_degree)
        if not 0 <= degree <= math.isqrt(k_coeffs) - 1:
            raise ValueError(f"sh_degree must be in [0, {math.isqrt(k_coeffs) - 1}] for sh of shape "
                             f"[N, {k_coeffs}, 3], got {degree}")
        bg = background if background is not None else means.new_zeros(3)
        return rasterize_error_fn(surfels, camera, degree, bg, error_fn, check, knob=torch.get_num_threads(),
                                  poison=POISON_OUTPUTS)
    first = render(surfels, camera, backend=backend, sh_degree=sh_degree, background=background)
    e = error_fn(first.rgb)
    check(e)
    stats = render(surfels, camera, backend=backend, sh_degree=sh_degree, background=background,
                   error_image=e.detach()).stats
    return RenderOutput(rgb=first.rgb, alpha=first.alpha, depth=first.depth, stats=stats,
                        median_depth=first.median_depth, depth2=first.depth2)
