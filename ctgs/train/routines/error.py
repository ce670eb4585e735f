"""Per-primitive error E_i over all training views (paper 3.3, METHOD_NOTES formula)."""

from __future__ import annotations

import torch

from ctgs.metrics.ssim import ssim_map
from ctgs.ops.fused import error_image as fused_error_image
from ctgs.train.step.loss import masked


def error_image(render: torch.Tensor, gt: torch.Tensor, lambda_ssim: float = 0.2) -> torch.Tensor:
    """e [H, W] = (1-l) |gt - render|_meanRGB + l (1 - SSIM map)_meanRGB (one compiled pass on the CPU
    when no gradient is needed)."""
    if not torch.is_grad_enabled() or not (render.requires_grad or gt.requires_grad):
        e = fused_error_image(render, gt, lambda_ssim)
        if e is not None:
            return e
    l1 = (gt - render).abs().mean(-1)
    ds = (1 - ssim_map(render, gt)).mean(-1)
    return (1 - lambda_ssim) * l1 + lambda_ssim * ds


def accumulate_error(stats_per_view: list[tuple[torch.Tensor, torch.Tensor, int]]) -> torch.Tensor:
    """E [N] = sum_v (err_v/HW)(contrib_v/HW) / sum_v (contrib_v/HW); 0 where a primitive is never blended.

    stats_per_view: (err_v [N], contrib_v [N], H*W) per view.
    """
    num = None
    den = None
    for err, contrib, hw in stats_per_view:
        c = contrib.double() / hw
        term = (err.double() / hw) * c
        num = term if num is None else num + term
        den = c if den is None else den + c
    e = torch.where(den > 0, num / den.clamp_min(1e-30), torch.zeros_like(num))
    return e.float()


@torch.no_grad()
def compute_E(model, views, render_fn, lambda_ssim: float = 0.2, with_support: bool = False, gains=None):
    """E over ALL `views` (objects with .camera and .image_t [H,W,3] tensors); render_fn(inputs, cam, err)
    with err a function of the rendered rgb (ctgs.render.render's error_image).

    gains: optional {view name: [C] gain} (exposure compensation's, config exposure_in_E): each view's render is
    scaled by its gain before the error, as in its training loss, so that E holds what the model fails to explain
    and not the photo's exposure.

    with_support: return (E, support) where support [N] is each primitive's blend weight summed over the pixels
    of the view where it weighs most (the image area it covers at best, in pixels)."""
    inputs = model.render_inputs()
    inputs = type(inputs)(**{k: (v.detach() if torch.is_tensor(v) else v) for k, v in vars(inputs).items()})
    acc = []
    support = None
    for view in views:
        # The error image of this very render (one pass on the CPU backend, see ctgs.render.render).
        g = None if gains is None else gains.get(view.name)
        stats = render_fn(inputs, view.camera,
                          lambda rgb, gt=view.image_t, g=g, m=getattr(view, "mask_t", None):
                          error_image(*masked((rgb if g is None else rgb * g).clamp(0, 1), gt, m), lambda_ssim)).stats
        acc.append((stats.err, stats.contrib, view.image_t.shape[0] * view.image_t.shape[1]))
        if with_support:
            support = stats.contrib.clone() if support is None else torch.maximum(support, stats.contrib)
    E = accumulate_error(acc)
    if not with_support:
        return E
    return E, (support if support is not None else torch.zeros_like(E))


def top_fraction_mask(values: torch.Tensor, fraction: float) -> torch.Tensor:
    """[N] bool: values strictly above the (1 - fraction) quantile, and > 0 (E = 0 means never seen)."""
    n = values.numel()
    if n == 0 or fraction <= 0:
        return torch.zeros(n, dtype=torch.bool, device=values.device)
    k = int(round(n * (1 - fraction)))  # rank of the threshold (1-based: k-th smallest)
    if k <= 0:
        return values > 0
    thr = torch.kthvalue(values.float().cpu(), k).values.to(values.device)
    return (values > thr) & (values > 0)


class StepErrors:
    """E accumulated over training steps (config error_from_steps): each step's backward sums its loss's error image
    per primitive (ctgs.render.BackwardStats), and the steps since the last full routine stand for E's views, with
    accumulate_error's formula (in float64 running sums). A change of the primitives (a routine) starts it afresh."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.num = self.den = self.support = None
        self.steps = 0

    @torch.no_grad()
    def add(self, contrib: torch.Tensor, err: torch.Tensor, hw: int) -> None:
        c = contrib.detach().double() / hw
        if self.num is None or self.num.shape != c.shape:
            self.num, self.den = torch.zeros_like(c), torch.zeros_like(c)
            self.support, self.steps = torch.zeros_like(contrib.detach()), 0
        self.num += (err.detach().double() / hw) * c
        self.den += c
        self.support = torch.maximum(self.support, contrib.detach())
        self.steps += 1

    def covers(self, n: int) -> bool:
        """Statistics of at least one step of the current n primitives."""
        return self.steps > 0 and self.num is not None and self.num.shape[0] == n

    def E(self) -> torch.Tensor:
        return torch.where(self.den > 0, self.num / self.den.clamp_min(1e-30), torch.zeros_like(self.num)).float()

    def state_dict(self) -> dict:
        return {"num": self.num, "den": self.den, "support": self.support, "steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        self.num, self.den, self.support = state["num"], state["den"], state["support"]
        self.steps = int(state["steps"])
