"""Structural edits of (model, optimiser) together: select/duplicate primitives, re-lay-out textures.

Every edit rebuilds the parameters as fresh leaf tensors and moves the Adam moments with them
(gathered rows for primitives, cropped/padded/resampled texels for textures).
"""

from __future__ import annotations

import torch

from ctgs.model import jagged
from ctgs.train.step.adam import PRIM_PARAMS, TEX_PARAM, SurfelAdam

PRIM_BUFFERS = ("k_min", "t2p_exp", "tex_res")


def _leaf(t: torch.Tensor) -> torch.Tensor:
    return t.detach().contiguous().requires_grad_(True)


@torch.no_grad()
def select(model, opt: SurfelAdam, idx: torch.Tensor, fresh: torch.Tensor | None = None,
           tex_shift: torch.Tensor | None = None) -> None:
    """Keep primitives idx [N'] (repeats allowed: duplicates), in that order.

    fresh [N'] bool: rows whose Adam moments start at zero (new primitives, as 3DGS does; their texels keep theirs:
    zero_texture_moments).
    tex_shift [N', 2] int64: texel shift of each new primitive's texture (split children).
    """
    idx = idx.long()
    keep = None if fresh is None else (~fresh).to(torch.float32)
    for name in PRIM_PARAMS:
        setattr(model, name, _leaf(getattr(model, name)[idx]))
        for st in (opt.exp_avg, opt.exp_avg_sq):
            g = st[name][idx]
            if keep is not None:
                g = g * keep.view(-1, *([1] * (g.ndim - 1))).to(g.dtype)
            st[name] = g
    old_res, old_off = model.tex_res, model.tex_offset
    for name in PRIM_BUFFERS:
        setattr(model, name, getattr(model, name)[idx].clone())
    if tex_shift is None:
        tex_shift = torch.zeros(len(idx), 2, dtype=torch.long, device=idx.device)
    bufs = [model.textures_raw.detach(), opt.exp_avg[TEX_PARAM], opt.exp_avg_sq[TEX_PARAM]]
    (raw, m, v), off = jagged.remap(bufs, old_res, old_off, idx, tex_shift, model.tex_res)
    _set_textures(model, opt, raw, m, v, off)


@torch.no_grad()
def relayout(model, opt: SurfelAdam | None, new_res: torch.Tensor) -> None:
    """Give every primitive resolution new_res [N, 2], keeping content centred (crop or pad); opt None: a
    trained model alone (no Adam moments to move)."""
    n = model.num_primitives
    idx = torch.arange(n, device=model.means.device)
    shift = torch.zeros(n, 2, dtype=torch.long, device=model.means.device)
    bufs = [model.textures_raw.detach()]
    if opt is not None:
        bufs += [opt.exp_avg[TEX_PARAM], opt.exp_avg_sq[TEX_PARAM]]
    out, off = jagged.remap(bufs, model.tex_res, model.tex_offset, idx, shift, new_res)
    model.tex_res = new_res.to(torch.int32).clone()
    if opt is None:
        model.textures_raw = _leaf(out[0])
        model.tex_offset = off
    else:
        _set_textures(model, opt, *out, off)


@torch.no_grad()
def replace_blocks(model, opt: SurfelAdam, new_res: torch.Tensor, new_blocks) -> None:
    """Swap the textures of some primitives for resampled ones (see jagged.replace_blocks)."""
    bufs = [model.textures_raw.detach(), opt.exp_avg[TEX_PARAM], opt.exp_avg_sq[TEX_PARAM]]
    (raw, m, v), off = jagged.replace_blocks(bufs, model.tex_res, model.tex_offset, new_res, new_blocks)
    model.tex_res = new_res.to(torch.int32).clone()
    _set_textures(model, opt, raw, m, v, off)


@torch.no_grad()
def zero_texture_moments(model, opt: SurfelAdam, prims: torch.Tensor) -> None:
    """Zero the Adam moments of the texels of the primitives `prims` [N] bool (their textures then train as new
    parameters do, as the authors' code has it for every texture it resizes)."""
    if not bool(prims.any()) or model.num_texels == 0:
        return
    per_texel = torch.repeat_interleave(prims, model.tex_res.long().prod(1))
    for st in (opt.exp_avg, opt.exp_avg_sq):
        st[TEX_PARAM][per_texel] = 0


def _set_textures(model, opt, raw, m, v, off) -> None:
    model.textures_raw = _leaf(raw)
    model.tex_offset = off
    opt.exp_avg[TEX_PARAM] = m
    opt.exp_avg_sq[TEX_PARAM] = v
