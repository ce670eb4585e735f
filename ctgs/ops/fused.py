"""Fused CPU kernels for dense per-element work of the model and the training loop (kernels/cpu/dense.cpp).

At 1-2M texels every [T, 3] PyTorch op of the texel activation, the optimiser and the texture
regulariser (each a full pass plus a fresh 10-20 MB temporary, page faults included) showed in the
profile of an iteration; these do the same math in one pass each. Everything falls back to
plain PyTorch off the CPU or where the extension cannot be built.
"""

from __future__ import annotations

import ctypes
import sys
from types import ModuleType

import torch

from ctgs.errors import UserError
from ctgs.ops.ext import load_cpu

_ext: ModuleType | None = None
_ext_failed = False

# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
# Blocks up to this size come from the heap and are reused (glibc's largest allowed mmap threshold).
MMAP_THRESHOLD_BYTES = 32 << 20
# Free memory kept at the top of the heap instead of being returned to the kernel.
TRIM_THRESHOLD_BYTES = 512 << 20


def tune_allocator() -> bool:
    """Make glibc keep freed large blocks for reuse (returns whether it applied).

    PyTorch allocates every [T, 3] temporary afresh; by default glibc hands blocks over its dynamic
    mmap threshold back to the kernel, so each new 10-20 MB tensor costs a page fault per 4 KiB on
    first touch. Measured on the 192x144 demo at 1.4M texels: ~10000 minor faults per training
    iteration before, ~900 after, and 25-30% less time per iteration (faults are expensive in a VM).
    Results do not change. No-op off Linux/glibc.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD,
                                                                                  TRIM_THRESHOLD_BYTES))


def cpu_ext() -> ModuleType | None:
    """The compiled CPU extension, or None if it cannot be built here (then callers use PyTorch)."""
    global _ext, _ext_failed
    if _ext is None and not _ext_failed:
        try:
            _ext = load_cpu()
        except UserError:
            _ext_failed = True
    return _ext


def fusable(*tensors: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" and t.is_contiguous() and t.dtype in (torch.float32, torch.float64)
               for t in tensors) and cpu_ext() is not None


def all_finite(t: torch.Tensor) -> bool:
    """True when t holds no NaN and no +-inf. min/max propagate NaN and expose +-inf in one pass, without a bool
    temporary of t's size (textures are big)."""
    with torch.no_grad():
        lo, hi = torch.aminmax(t.detach())
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


class _DeferredTexelL1:
    """The texture regulariser's backward, handed from texel_l1 to the activation's backward (one holder
    per texel_activation output). Autograd runs texel_l1's backward first (it consumes y), which records
    (weight, tex_offset, tex_res, its upstream gradient) here and returns no tensor; the activation's
    backward then adds that term's gradient to the render's gradient of y in its own pass
    (torch.ops.ctgs.texel_activation_backward_l1): bit-identical to the plain chain (a [T, 3] gradient from the
    regulariser, autograd's sum of the two gradients of y, the activation backward), one pass instead of
    three over the texel buffer (~1 ms per step at 2.4M texel values on the dev VM). The term's gradient
    w.r.t. y itself is therefore never formed: torch.autograd.grad(loss, y) misses it; ask for raw's."""

    __slots__ = ("terms",)

    def __init__(self):
        self.terms: list = []


class _TexelActivation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, raw, deferred):
        y = torch.ops.ctgs.texel_activation(raw, torch.get_num_threads())
        ctx.save_for_backward(y)
        ctx.deferred = deferred
        return y

    @staticmethod
    def backward(ctx, grad):
        (y,) = ctx.saved_tensors
        terms, ctx.deferred.terms = ctx.deferred.terms, []
        grad = grad.contiguous()
        # More than one regulariser term on the same y (not done by the trainer): all but the last are added
        # the plain way, in the order autograd ran them.
        for weight, off, res, scale in terms[:-1]:
            grad = grad + torch.ops.ctgs.texel_abs_backward(y, weight, off, res, scale, torch.get_num_threads())
        if terms:
            weight, off, res, scale = terms[-1]
            return torch.ops.ctgs.texel_activation_backward_l1(y, grad, weight, off, res, scale,
                                                              torch.get_num_threads()), None
        return torch.ops.ctgs.texel_activation_backward(y, grad, torch.get_num_threads()), None


def texel_activation(raw: torch.Tensor) -> torch.Tensor:
    """Activated texel offsets 2 sigmoid(raw) - 1 (= tanh(raw / 2)), in [-1, 1], differentiable."""
    if fusable(raw):
        deferred = _DeferredTexelL1()
        y = _TexelActivation.apply(raw, deferred)
        if y.requires_grad:
            y._ctgs_deferred_l1 = deferred  # texel_l1(textures=y) finds it here
        return y
    return 2.0 * torch.sigmoid(raw) - 1.0


class _TexelL1Deferred(torch.autograd.Function):
    """texel_l1 on activated offsets y from texel_activation: the value here, the gradient in the
    activation's backward (_DeferredTexelL1)."""

    @staticmethod
    def forward(ctx, y, weight, tex_offset, tex_res, deferred):
        ctx.save_for_backward(weight, tex_offset, tex_res)
        ctx.deferred = deferred
        return torch.ops.ctgs.texel_abs_forward(y, weight, tex_offset, tex_res, torch.get_num_threads())

    @staticmethod
    def backward(ctx, grad):
        weight, tex_offset, tex_res = ctx.saved_tensors
        ctx.deferred.terms.append((weight, tex_offset, tex_res, float(grad)))
        return None, None, None, None, None


class _TexelL1(torch.autograd.Function):
    """activated=False: x is textures_raw (the term on 2 sigmoid(x) - 1); True: x is already activated."""

    @staticmethod
    def forward(ctx, x, weight, tex_offset, tex_res, activated=False):
        ctx.save_for_backward(x, weight, tex_offset, tex_res)
        ctx.activated = activated
        fwd = torch.ops.ctgs.texel_abs_forward if activated else torch.ops.ctgs.texel_l1_forward
        return fwd(x, weight, tex_offset, tex_res, torch.get_num_threads())

    @staticmethod
    def backward(ctx, grad):
        x, weight, tex_offset, tex_res = ctx.saved_tensors
        bwd = torch.ops.ctgs.texel_abs_backward if ctx.activated else torch.ops.ctgs.texel_l1_backward
        g = bwd(x, weight, tex_offset, tex_res, float(grad), torch.get_num_threads())
        # The weights are constants of the loss (no gradient); one entry per input given to apply.
        return (g, None, None, None, None)[: len(ctx.needs_input_grad)]


def texel_l1(model, weight: torch.Tensor, textures: torch.Tensor | None = None) -> torch.Tensor:
    """sum_i weight[i] * (sum over primitive i's texels and channels of |activated texel| (model.textures)):
    a scalar, differentiable w.r.t. model.textures_raw, not w.r.t. weight. weight: [N] per-primitive
    factors (ctgs.train.step.loss.texture_weights: the rasterized mask, times 1 - transmittance on option);
    a bool mask is taken as 0/1. textures: the activated offsets this step's render used (its
    SurfelInputs.textures), if the caller has them: the term is then taken on them (no second activation;
    when they are texel_activation's own output, the term's gradient is added inside the activation's
    backward, see _DeferredTexelL1: differentiate w.r.t. textures_raw, not w.r.t. those offsets)."""
    raw = model.textures_raw
    n = model.tex_res.shape[0]
    if weight.shape != (n,):
        raise ValueError(f"texel_l1: weight must be [N] = [{n}] (one per primitive), got {list(weight.shape)}")
    weight = weight.detach().to(raw.dtype)
    if textures is not None and textures.shape == raw.shape and fusable(textures):
        deferred = getattr(textures, "_ctgs_deferred_l1", None)
        if deferred is not None and textures.requires_grad and torch.is_grad_enabled():
            return _TexelL1Deferred.apply(textures, weight.contiguous(), model.tex_offset.contiguous(),
                                          model.tex_res.contiguous(), deferred)
        return _TexelL1.apply(textures, weight.contiguous(), model.tex_offset.contiguous(),
                              model.tex_res.contiguous(), True)
    if fusable(raw):
        return _TexelL1.apply(raw, weight.contiguous(), model.tex_offset.contiguous(), model.tex_res.contiguous(),
                              False)
    sizes = model.tex_res[:, 0].long() * model.tex_res[:, 1].long()
    texel_w = torch.repeat_interleave(weight, sizes)  # [T]
    # (the render's activated offsets where the caller kept them: no second activation and graph, e.g. on a GPU)
    acts = textures if textures is not None and textures.shape == raw.shape else model.textures
    return (acts.abs().sum(1) * texel_w).sum()


class _PhotometricLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, render, gt, lambda_ssim, want_error):
        total, l1, s, grad, e = torch.ops.ctgs.photometric_loss(render, gt, float(lambda_ssim),
                                                               bool(ctx.needs_input_grad[0]), bool(want_error),
                                                               torch.get_num_threads())
        ctx.save_for_backward(grad)
        ctx.mark_non_differentiable(l1, s, e)
        return total, l1, s, e

    @staticmethod
    def backward(ctx, grad_total, _grad_l1, _grad_ssim, _grad_e):
        (grad,) = ctx.saved_tensors
        return grad * grad_total, None, None, None


def photometric_loss(render: torch.Tensor, gt: torch.Tensor, lambda_ssim: float, want_error: bool = False):
    """(1 - lambda_ssim) mean |render - gt| + lambda_ssim (1 - mean SSIM) of two [H, W, C] images in one compiled
    pass on the CPU: (total, differentiable w.r.t. render; mean L1 and mean SSIM, detached), and with want_error the
    error image of the same pass, e [H, W] = (1 - l) mean_c |render - gt| + l mean_c (1 - SSIM map) (detached).
    None where the extension does not apply (the caller computes it with PyTorch:
    ctgs.train.step.loss.photometric_loss).

    The pass computes the value and, if render needs it, the gradient (kernels/cpu/ssim.cpp; 5 blurred moment
    images, their adjoint for the gradient); it matches the PyTorch expression to float rounding
    (tests/train/test_fused.py)."""
    if render.shape != gt.shape or render.ndim != 3 or gt.requires_grad or gt.dtype != render.dtype:
        return None
    render_c, gt_c = render.contiguous(), gt.contiguous()
    if not fusable(render_c, gt_c):
        return None
    total, l1, s, e = _PhotometricLoss.apply(render_c, gt_c, float(lambda_ssim), bool(want_error))
    return (total, l1, s, e) if want_error else (total, l1, s)


def error_image(render: torch.Tensor, gt: torch.Tensor, lambda_ssim: float) -> torch.Tensor | None:
    """e [H, W] = (1 - l) mean_c |render - gt| + l mean_c (1 - SSIM map) in one compiled pass, or None where
    the extension does not apply (the caller computes it with PyTorch). Not differentiable."""
    if render.shape != gt.shape or render.ndim != 3 or gt.dtype != render.dtype:
        return None
    render_c, gt_c = render.detach().contiguous(), gt.detach().contiguous()
    if not fusable(render_c, gt_c):
        return None
    return torch.ops.ctgs.photometric_loss(render_c, gt_c, float(lambda_ssim), False, True,
                                          torch.get_num_threads())[4]
