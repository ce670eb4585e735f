"""Resolution-aware splitting (paper 3.3) and pruning."""

from __future__ import annotations

import math

import torch

from ctgs.model.extent import active_half_extent, active_resolution, texel_size
from ctgs.render.geometry import quat_to_rotmat
from ctgs.train.routines import edit

CHILD_OPACITY_FACTOR = math.exp(-0.5)  # each child's opacity: parent's x exp(-1/2) (G at 1 sigma)


@torch.no_grad()
def split(model, opt, candidates: torch.Tensor, tau: float, max_primitives: int = 0,
          priority: torch.Tensor | None = None, carry: torch.Tensor | None = None, children_stay: bool = True,
          fresh_children: bool = False, scale_cap: bool = False, children_out: list | None = None,
          truncate: bool = False):
    """Split candidates whose active resolution on an axis exceeds tau (x axis first, then y).

    Children sit at +-(1/6 of the active extent) along the axis, quantised to whole texels, with half the
    scale on that axis and opacity x exp(-1/2); each child's texture is the parent's, shifted so texels
    stay at the same world positions. With max_primitives > 0, splits stop at the budget (largest
    `priority` first). Returns (number of splits, the [N'] bool candidate mask carried to children), and with
    `carry` (an [N] per-primitive tensor) a third item: carry for the N' primitives (children inherit the parent's).
    A child of an x split is a candidate for the y split as its parent was; children_stay=False then leaves every
    child out of the returned mask, as the authors' code zeroes the error of the primitives a split adds (so a
    routine does not upscale them).
    fresh_children: children start with zero Adam moments (the authors' code appends them as new tensors and drops
    the parent); False: they inherit the parent's. scale_cap: a child's scale on the split axis is at most
    tau texels / 3 (the authors' code), besides halved. truncate: the offset in texels is truncated (the authors'
    code), not rounded. children_out: a list that receives the [N'] bool mask of the children this call made.
    """
    total = 0
    is_child = torch.zeros(model.num_primitives, dtype=torch.bool, device=candidates.device)
    for axis in (0, 1):
        n = model.num_primitives
        sel = candidates & (active_resolution(model)[:, axis] > tau)
        if max_primitives > 0:
            budget = max(0, max_primitives - n)
            if int(sel.sum()) > budget:
                order = torch.argsort(priority if priority is not None else torch.zeros(n, device=sel.device), descending=True)
                ranked = order[sel[order]][:budget]
                sel = torch.zeros_like(sel)
                sel[ranked] = True
        m = int(sel.sum())
        if m == 0:
            continue
        total += m
        k = texel_size(model)  # [N]
        half = active_half_extent(model)[:, axis]  # [N]
        s = (torch.trunc if truncate else torch.round)((2 * half / 6) / k).long()  # texels
        keep_idx = torch.nonzero(~sel).flatten()
        par = torch.nonzero(sel).flatten()
        idx = torch.cat([keep_idx, par, par])
        sign = torch.cat([torch.zeros(len(keep_idx)), torch.ones(m), -torch.ones(m)]).to(model.means.device)
        shift = torch.zeros(len(idx), 2, dtype=torch.long, device=model.means.device)
        shift[:, axis] = (sign * s[idx]).long()
        # A child at +d along the axis sees its texel iu at the parent's iu + s.
        rot = quat_to_rotmat(model.quats.detach())[:, :, axis]  # [N, 3] tangent axis in world
        d_world = (s[idx] * k[idx] * sign)[:, None] * rot[idx]
        opac = model.opacities.detach()[idx]
        child = sign != 0
        edit.select(model, opt, idx, fresh=child if fresh_children else None, tex_shift=shift)
        if fresh_children:
            edit.zero_texture_moments(model, opt, child)
        model.means.data[child] += d_world[child]
        model.log_scales.data[child, axis] -= math.log(2.0)
        if scale_cap:
            cap = torch.log(tau * k[idx][child] / 3).to(model.log_scales.dtype)
            model.log_scales.data[child, axis] = torch.minimum(model.log_scales.data[child, axis], cap)
        o = (opac[child] * CHILD_OPACITY_FACTOR).clamp(1e-6, 1 - 1e-6)
        model.opacity_logits.data[child] = torch.log(o / (1 - o))
        candidates = candidates[idx]
        is_child = is_child[idx] | child
        if priority is not None:
            priority = priority[idx]
        if carry is not None:
            carry = carry[idx]
    if children_out is not None:
        children_out.append(is_child)
    if not children_stay:
        candidates = candidates & ~is_child
    if carry is not None:
        return total, candidates, carry
    return total, candidates


@torch.no_grad()
def prune(model, opt, min_opacity: float, extra: torch.Tensor | None = None) -> int:
    """Remove primitives with opacity < min_opacity (or `extra` [N] bool); returns how many."""
    drop = model.opacities.detach() < min_opacity
    if extra is not None:
        drop = drop | extra
    if not bool(drop.any()):
        return 0
    edit.select(model, opt, torch.nonzero(~drop).flatten())
    return int(drop.sum())
