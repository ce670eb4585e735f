"""3DGS/2DGS adaptive density control for the baselines (`2dgs`, `fixed_texture`): clone / split by the
accumulated view-space positional gradient, prune, opacity reset. The content-aware method does not use it.
"""

from __future__ import annotations

import torch

from ctgs.render.geometry import quat_to_rotmat
from ctgs.train.routines import edit

SPLIT_CHILDREN = 2
SPLIT_SCALE_DIV = 0.8 * SPLIT_CHILDREN  # 3DGS: children scale = parent / (0.8 N)


class GradAccumulator:
    """Sum over views of |d loss / d mean2D| in 3DGS NDC units, and how often each primitive was seen."""

    def __init__(self, n: int, device):
        self.sum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)

    @torch.no_grad()
    def add_view(self, means: torch.Tensor, means_grad: torch.Tensor, camera) -> None:
        """Approximate the 2D gradient from the 3D one: v_pix = v_cam_xy * z / f, NDC = pix * size / 2."""
        vm = camera.viewmat.to(means.device, means.dtype)
        z = (means.detach() @ vm[2, :3] + vm[2, 3]).clamp_min(1e-6)
        v_cam = means_grad @ vm[:3, :3].T
        gx = v_cam[:, 0] * z / camera.fx * camera.width * 0.5
        gy = v_cam[:, 1] * z / camera.fy * camera.height * 0.5
        seen = means_grad.abs().sum(1) > 0
        self.sum += torch.sqrt(gx * gx + gy * gy) * seen
        self.count += seen.float()

    def reset(self, n: int, device) -> None:
        self.sum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)

    def state_dict(self) -> dict:
        return {"sum": self.sum, "count": self.count}

    def load_state_dict(self, s: dict) -> None:
        self.sum, self.count = s["sum"], s["count"]


@torch.no_grad()
def densify_and_prune(model, opt, acc: GradAccumulator, cfg, extent: float, gen: torch.Generator,
                      prune_big: bool, prune_faint: bool = True) -> dict:
    """One 3DGS densification step; returns counts. prune_faint=False skips the opacity test (see
    ctgs.train.strategies.densify.RESET_RECOVERY_STEPS)."""
    n = model.num_primitives
    dev = model.means.device
    avg = acc.sum / acc.count.clamp_min(1)
    big_grad = avg >= cfg.densify_grad_threshold
    max_scale = model.scales.detach().max(1).values
    small = max_scale <= cfg.percent_dense * extent
    clone = big_grad & small
    splt = big_grad & ~small
    if cfg.max_primitives > 0:
        # Each clone or split adds one primitive net: keep the largest gradients that fit the budget.
        room = max(0, cfg.max_primitives - n)
        if int(big_grad.sum()) > room:
            order = torch.argsort(torch.where(big_grad, avg, torch.full_like(avg, -1.0)), descending=True)
            allowed = torch.zeros_like(big_grad)
            allowed[order[:room]] = True
            clone &= allowed
            splt &= allowed
    keep = torch.nonzero(~splt).flatten()
    cl = torch.nonzero(clone).flatten()
    sp = torch.nonzero(splt).flatten()
    idx = torch.cat([keep, cl] + [sp] * SPLIT_CHILDREN)
    fresh = torch.cat([torch.zeros(len(keep), dtype=torch.bool), torch.ones(len(idx) - len(keep), dtype=torch.bool)]).to(dev)
    # Offsets of split children: a sample of the parent's Gaussian in its tangent plane.
    scales = model.scales.detach()[sp].repeat(SPLIT_CHILDREN, 1)
    rot = quat_to_rotmat(model.quats.detach()[sp]).repeat(SPLIT_CHILDREN, 1, 1)
    sample = torch.randn(len(scales), 2, generator=gen).to(dev) * scales
    offs = rot[:, :, 0] * sample[:, :1] + rot[:, :, 1] * sample[:, 1:]
    edit.select(model, opt, idx, fresh=fresh)
    s0 = len(keep) + len(cl)
    if len(sp):
        model.means.data[s0:] += offs
        model.log_scales.data[s0:] -= torch.log(torch.tensor(SPLIT_SCALE_DIV))
    drop = model.opacities.detach() < cfg.prune_opacity_2dgs
    if not prune_faint:
        drop = torch.zeros_like(drop)
    # World size only: 3DGS/2DGS also test a 2D radius > 20 px, but their densification_postfix has zeroed the radii
    # by then, so that test prunes nothing in the published code (docs/guide/training.md, baseline overlays).
    if prune_big:
        drop |= model.scales.detach().max(1).values > 0.1 * extent
    edit.select(model, opt, torch.nonzero(~drop).flatten())
    acc.reset(model.num_primitives, dev)
    return {"cloned": len(cl), "split": len(sp), "pruned": int(drop.sum())}


RESET_OPACITY = 0.01  # 3DGS's reset value


@torch.no_grad()
def reset_opacity(model, opt, value: float = RESET_OPACITY) -> None:
    """3DGS opacity reset: clamp opacities to <= value and zero their Adam moments."""
    o = torch.minimum(model.opacities.detach(), torch.tensor(value))
    model.opacity_logits.data.copy_(torch.log(o / (1 - o)))
    opt.exp_avg["opacity_logits"].zero_()
    opt.exp_avg_sq["opacity_logits"].zero_()
