"""Texel-size adaptation and jagged (re)allocation (paper sections 3.2-3.3).

Texel size = k_min * 2**t2p_exp (world units). Resolutions are powers of two, capped per axis.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ctgs.model import jagged
from ctgs.model.extent import CUTOFF_SIGMA, active_half_extent, active_resolution, texel_size
from ctgs.render.constants import CUTOFF_RHO
from ctgs.train.routines import edit
from ctgs.train.routines.kmin import compute_k_min

LOGIT_EPS = 1e-4  # activated texels are stored as logits; keep them finite at +-1


ALLOC_MODES = ("pow2", "mult4")


def needed_res(model, cap: int, mode: str = "pow2", sigma: float = CUTOFF_SIGMA,
               tsize: torch.Tensor | None = None) -> torch.Tensor:
    """[N, 2] int32 allocation: the active extent (at most +-sigma standard deviations) + 1 texel of bilinear
    padding, rounded up, in [2, cap] (cap is a power of two).

    mode "pow2" rounds up to a power of two (the authors' code); "mult4" to a multiple of 4 (2 below 3), which
    keeps every size even after a x2 downscale - so texel centres never move by half a texel when a
    texture is re-centred - with at most 3 padding texels per axis instead of up to 2x the needed size.
    tsize [N]: world units per texel to size for (default: the model's, texel_size).
    """
    half = torch.minimum(active_half_extent(model), sigma * model.scales.detach())
    ts = texel_size(model) if tsize is None else tsize
    n = torch.ceil(2 * half / ts[:, None] + 1).clamp(min=2, max=cap)
    if mode == "pow2":
        p = torch.pow(2.0, torch.ceil(torch.log2(n)))
    elif mode == "mult4":
        p = torch.where(n <= 2, torch.full_like(n, 2.0), 4 * torch.ceil(n / 4))
    else:
        raise ValueError(f"texture allocation mode must be one of {ALLOC_MODES}, got {mode!r}")
    return p.clamp(max=cap).to(torch.int32)


@torch.no_grad()
def start_textures(model, opt, start_texels: float, min_exp: int, cap: int, mode: str = "pow2",
                   sigma: float = CUTOFF_SIGMA, ceil: bool = False) -> None:
    """Texture start: t2p_exp so the smaller active extent spans ~start_texels texels (paper: "smallest axis is
    8 texels wide"; a power of two, the nearest or with ceil the next coarser as the authors' code takes it, so at
    most start_texels; exponent >= min_exp), then allocate zero-offset textures (activated 0: the image does not
    change)."""
    extent = 2 * active_half_extent(model).min(1).values.clamp_min(1e-12)
    e = (torch.ceil if ceil else torch.round)(torch.log2(extent / (start_texels * model.k_min)))
    model.t2p_exp = e.clamp(min=min_exp, max=60).to(torch.int32)
    realloc(model, opt, cap, mode, sigma)


@torch.no_grad()
def realloc(model, opt, cap: int, mode: str = "pow2", sigma: float = CUTOFF_SIGMA, fresh_moments: bool = False) -> int:
    """Resize every texture to its needed resolution (needed_res), content centred, Adam moments with it (with
    fresh_moments: zeroed for every texture whose size changes, as the authors' code does); returns the texel count."""
    if model.texture_mode != "content_aware":
        return model.num_texels
    new_res = needed_res(model, cap, mode, sigma)
    changed = (new_res != model.tex_res).any(1) if fresh_moments and opt is not None else None
    edit.relayout(model, opt, new_res)
    if changed is not None:
        edit.zero_texture_moments(model, opt, changed)
    return model.num_texels


def _split_by_key(keys: torch.Tensor):
    """[(key, rows)] for each distinct key in increasing order, rows ascending: one stable sort and one transfer of
    the keys and counts, instead of a boolean mask (a host synchronisation on a GPU) per key."""
    sorted_keys, order = torch.sort(keys, stable=True)
    uniq, counts = torch.unique_consecutive(sorted_keys, return_counts=True)
    return list(zip(uniq.tolist(), torch.split(order, counts.tolist())))


def _groups(res: torch.Tensor, mask: torch.Tensor):
    """Yield (ru, rv, prims) for the masked primitives grouped by resolution (groups by increasing (ru, rv),
    primitives ascending)."""
    idx = torch.nonzero(mask).flatten()
    if idx.numel() == 0:
        return
    keys = res[idx, 0].long() * 100000 + res[idx, 1].long()
    for key, rows in _split_by_key(keys):
        yield int(key // 100000), int(key % 100000), idx[rows]


def upscale_selection(model, mask: torch.Tensor, min_exp: int) -> torch.Tensor:
    """[N] bool: the masked primitives upscale would upscale (t2p_exp > min_exp, a texture)."""
    return mask & (model.t2p_exp > min_exp) & (model.tex_res.min(1).values > 0)


@torch.no_grad()
def upscale(model, opt, mask: torch.Tensor, min_exp: int, crop: tuple | None = None,
            fresh_moments: bool = False) -> torch.Tensor:
    """Halve the texel size (t2p_exp - 1) of masked primitives with t2p_exp > min_exp; each texel becomes
    2x2 (nearest neighbour), Adam moments too (with fresh_moments: zeroed, as the authors' code does). Returns the
    [N] bool mask actually upscaled.

    crop (cameras, cap, mode, sigma): each upscaled texture is cropped, centred, to what the routine's next
    reallocation (realloc with those arguments, after compute_k_min(cameras)) gives it, as it is made, instead
    of allocating all of 2x its resolution and letting realloc drop the padding: the same final textures and
    moments (realloc finds them at their size), without 4x the upscaled texels at once (on a GPU at the paper's
    scale, 2.4 GB of blocks and most of 6.4 GB of re-laid-out buffers at a routine's peak:
    benchmarks/results/gpu_train_probe/memory_after_ba45e3f.md). Primitives whose centre no camera sees are not
    cropped (their k_min follows the other primitives', which the routine's pruning may change)."""
    sel = upscale_selection(model, mask, min_exp)
    if not bool(sel.any()):
        return sel
    new_res = model.tex_res.clone()
    new_res[sel] = model.tex_res[sel] * 2
    if crop is not None:
        cameras, cap, mode, sigma = crop
        k_min, seen = compute_k_min(model.means.detach(), cameras, return_seen=True)
        exp = model.t2p_exp.to(k_min.dtype) - sel.to(k_min.dtype)
        target = needed_res(model, cap, mode, sigma, tsize=k_min * torch.pow(2.0, exp))
        use = sel & seen
        new_res[use] = torch.minimum(new_res[use], target[use])
    bufs = [model.textures_raw.detach(), opt.exp_avg["textures_raw"], opt.exp_avg_sq["textures_raw"]]
    blocks = []
    for ru, rv, prims in _groups(model.tex_res, sel):
        vals = [jagged.blocks(b, model.tex_offset, prims, ru, rv).repeat_interleave(2, 1).repeat_interleave(2, 2)
                for b in bufs]  # [G, 2rv, 2ru, C]
        if crop is None:
            blocks.append((prims, vals))
            continue
        # Sub-groups by target size, cropped as jagged.remap would: new (iu, iv) <- old (iu + (2ru - nu) // 2, ...)
        tgt = new_res[prims].long()
        keys = tgt[:, 0] * 100000 + tgt[:, 1]
        for key, rows in _split_by_key(keys):
            nu, nv = int(key // 100000), int(key % 100000)
            du, dv = (2 * ru - nu) // 2, (2 * rv - nv) // 2
            blocks.append((prims[rows], [v[rows, dv:dv + nv, du:du + nu].contiguous() for v in vals]))
        del vals
    edit.replace_blocks(model, opt, new_res, blocks)
    model.t2p_exp[sel] -= 1
    if fresh_moments:
        edit.zero_texture_moments(model, opt, sel)
    return sel


def texel_weights(model, prims: torch.Tensor, ru: int, rv: int) -> torch.Tensor:
    """[G, rv, ru] Gaussian falloff of each texel centre (zero past 3 sigma) for primitives of one res."""
    k = texel_size(model)[prims]  # [G]
    s = model.scales.detach()[prims]  # [G, 2]
    xu = (torch.arange(ru, device=k.device, dtype=k.dtype) - (ru - 1) / 2)[None, None, :] * k[:, None, None]
    xv = (torch.arange(rv, device=k.device, dtype=k.dtype) - (rv - 1) / 2)[None, :, None] * k[:, None, None]
    rho = (xu / s[:, 0, None, None]) ** 2 + (xv / s[:, 1, None, None]) ** 2
    return torch.exp(-0.5 * rho) * (rho <= CUTOFF_RHO)


def _roundtrips(model, sel: torch.Tensor, corners: bool = False):
    """Yield (ru, rv, prims, down, E_d) per resolution group of the selected primitives: the x2 bicubic
    antialiased downsampling of their activated textures [G, 3, rv/2, ru/2] and E_d [G] (see downscale). corners:
    both resamplings with align_corners=True (the authors' code: the corner texels stay put, so the content of a
    downscaled texture shrinks towards its centre by (n - 1) / (n - 2) for n texels); False keeps texel centres."""
    for ru, rv, prims in _groups(model.tex_res, sel):
        raw = jagged.blocks(model.textures_raw.detach(), model.tex_offset, prims, ru, rv)  # [G, rv, ru, 3]
        act = (2 * torch.sigmoid(raw) - 1).permute(0, 3, 1, 2)  # [G, 3, rv, ru]
        down = F.interpolate(act, size=(rv // 2, ru // 2), mode="bicubic", antialias=True, align_corners=corners)
        up = F.interpolate(down, size=(rv, ru), mode="bicubic", align_corners=corners)
        diff = (up - act).mean(1).abs()  # [G, rv, ru]
        w = texel_weights(model, prims, ru, rv)
        yield ru, rv, prims, down, (diff * w).sum((1, 2)) / w.sum((1, 2)).clamp_min(1e-12)


@torch.no_grad()
def downscale_error(model, candidates: torch.Tensor) -> torch.Tensor:
    """[N] E_d of the candidates that can halve their resolution (> 2 texels on both axes), NaN elsewhere;
    nothing changes."""
    e_d = torch.full((model.num_primitives,), float("nan"), device=model.means.device)
    for _, _, prims, _, ed in _roundtrips(model, candidates & (model.tex_res.min(1).values > 2)):
        e_d[prims] = ed
    return e_d


@torch.no_grad()
def downscale(model, opt, candidates: torch.Tensor, tau_ds: float, thin: bool = False,
              fresh_moments: bool = False, corners: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Double the texel size of candidates whose texture survives a x2 bicubic antialiased down/up round trip.

    E_d = Gaussian-weighted mean over texels of |mean_RGB(recon - orig)| (activated values). Accepted
    (E_d < tau_ds, resolution > 2 on both axes) keep the downsampled texture, t2p_exp + 1; their Adam
    moments are 2x2 averaged (with fresh_moments: zeroed, as the authors' code does). corners: the round trip with
    align_corners=True, as the authors' code resamples (_roundtrips). thin=True also takes textures 2 texels wide on
    one axis and wider on the other (the authors' code: any axis above 2); the thin axis is then 1 texel until the
    routine's realloc pads it again.
    Returns (accepted [N] bool, E_d [N] with NaN where not evaluated).
    """
    n = model.num_primitives
    e_d = torch.full((n,), float("nan"), device=model.means.device)
    res = model.tex_res
    sel = candidates & ((res.min(1).values >= 2) & (res.max(1).values > 2) if thin else (res.min(1).values > 2))
    accepted = torch.zeros(n, dtype=torch.bool, device=model.means.device)
    if not bool(sel.any()):
        return accepted, e_d
    new_res = model.tex_res.clone()
    blocks = []
    for ru, rv, prims, down, ed in _roundtrips(model, sel, corners):
        e_d[prims] = ed
        rows = torch.nonzero(ed < tau_ds).flatten()  # (one host sync per group on a GPU, not three)
        if rows.numel() == 0:
            continue
        p = prims[rows]
        d = down[rows].clamp(-1 + LOGIT_EPS, 1 - LOGIT_EPS)
        new_raw = torch.logit((d + 1) / 2).permute(0, 2, 3, 1)  # [G', rv/2, ru/2, 3]
        moms = []
        for name in ("exp_avg", "exp_avg_sq"):
            mb = jagged.blocks(getattr(opt, name)["textures_raw"], model.tex_offset, p, ru, rv).permute(0, 3, 1, 2)
            moms.append(F.avg_pool2d(mb, 2).permute(0, 2, 3, 1))
        new_res[p] = torch.tensor([ru // 2, rv // 2], dtype=torch.int32, device=new_res.device)
        blocks.append((p, [new_raw, moms[0], moms[1]]))
        accepted[p] = True
    if blocks:
        edit.replace_blocks(model, opt, new_res, blocks)
        model.t2p_exp[accepted] += 1
        if fresh_moments:
            edit.zero_texture_moments(model, opt, accepted)
    return accepted, e_d


@torch.no_grad()
def fit_texels(model, opt, max_texels: int, cap: int, mode: str = "pow2", sigma: float = CUTOFF_SIGMA,
               keep: torch.Tensor | None = None, support: torch.Tensor | None = None, trim_eps: float = 0.0,
               reallocate: bool = True, steps: int = 16) -> dict:
    """Coarsen textures until the model holds at most max_texels texels (a parameter budget), cheapest first.

    Coarsening a texture one level (downscale with no threshold: texel size x2, a quarter of its texels) loses
    about E_d (its round-trip error, per unit of image area) over the image area it covers, and saves about 3/4
    of its texels; so textures go in increasing order of E_d x image area per texel, where the image area per texel
    is support / texels (support [N]: the surfel's blend weight summed over the pixels of the training view where
    it weighs most, when the caller rendered them) or else 4**t2p_exp (a texel's area in pixels of the closest
    camera). Each step coarsens just enough textures to cover the excess, then reallocates (reallocate: the
    resolutions round up, as between routines), until the count fits or nothing can be coarsened (textures of 2
    texels on an axis, and `keep` [N] bool: left alone, e.g. just upscaled). With trim_eps > 0 the texels counted
    are those the final trim will keep (trim_res): padding that trim drops does not count against the budget.
    Returns {"budget_downscaled", "budget_texels"} (the count as measured, trimmed or not).
    """
    def sizes() -> torch.Tensor:
        res = trim_res(model, trim_eps) if trim_eps > 0 else model.tex_res
        return res.long().prod(1)

    n_down = 0
    for _ in range(steps):
        counts = sizes()
        excess = int(counts.sum()) - max_texels
        if excess <= 0:
            break
        cand = (model.tex_res.min(1).values > 2) & (counts > 0)
        if keep is not None:
            cand &= ~keep
        if not bool(cand.any()):
            break
        e_d = downscale_error(model, cand)
        idx = torch.nonzero(cand).flatten()
        n_tex = counts[idx].to(e_d.dtype)
        if support is None:
            per_texel = torch.pow(4.0, model.t2p_exp[idx].to(e_d.dtype))
        else:
            per_texel = support[idx].to(e_d.dtype) / n_tex
        order = torch.argsort(e_d[idx] * per_texel, stable=True)
        saved = torch.cumsum(0.75 * n_tex[order], 0)
        k = min(int(torch.searchsorted(saved, saved.new_tensor(float(excess)))) + 1, len(order))
        chosen = torch.zeros_like(cand)
        chosen[idx[order[:k]]] = True
        down, _ = downscale(model, opt, chosen, float("inf"))
        n_down += int(down.sum())
        if reallocate:
            realloc(model, opt, cap, mode, sigma)
    return {"budget_downscaled": n_down, "budget_texels": int(sizes().sum())}


@torch.no_grad()
def trim_res(model, eps: float) -> torch.Tensor:
    """[N, 2] int32: each texture cropped symmetrically to the texels whose activated offset reaches eps in some
    channel ((0, 0) where none does). Primitives without a texture keep (0, 0).

    A symmetric crop by c texels per side keeps every remaining texel at its world position (the renderer
    centres texel i at (i - (res - 1) / 2) x texel size), and a texel outside the grid reads as offset 0, so
    the crop changes each texture lookup by less than eps per channel: every rendered colour (a weighted sum
    of lookups, weights <= 1, then max(., 0)) moves by less than eps.
    """
    res = model.tex_res.long()
    n = res.shape[0]
    if model.num_texels == 0 or n == 0:
        return res.to(torch.int32)
    pid, iu, iv = jagged.texel_coords(model.tex_res)
    act = 2 * torch.sigmoid(model.textures_raw.detach()) - 1  # [T, 3]
    keep = act.abs().amax(1) >= eps
    big = torch.iinfo(torch.int64).max
    lo = torch.full((n, 2), big, dtype=torch.long, device=res.device)
    hi = torch.full((n, 2), -1, dtype=torch.long, device=res.device)
    p = pid[keep]
    for axis, coord in ((0, iu[keep]), (1, iv[keep])):
        lo[:, axis].scatter_reduce_(0, p, coord, "amin")
        hi[:, axis].scatter_reduce_(0, p, coord, "amax")
    has = hi[:, 0] >= 0
    crop = torch.minimum(lo, res - 1 - hi).clamp_min(0)  # texels that may go on each side
    out = torch.where(has[:, None], res - 2 * crop, torch.zeros_like(res))
    return out.to(torch.int32)


@torch.no_grad()
def trim(model, opt, eps: float) -> dict:
    """Crop every texture to what it holds (trim_res), Adam moments with it (opt may be None: a trained model
    alone). Returns {"textures_dropped", "texels_before", "texels_after"}."""
    if model.texture_mode != "content_aware" or eps <= 0 or model.num_texels == 0:
        return {"textures_dropped": 0, "texels_before": model.num_texels, "texels_after": model.num_texels}
    before, had = model.num_texels, model.tex_res.long().prod(1) > 0
    edit.relayout(model, opt, trim_res(model, eps))
    dropped = int((had & (model.tex_res.long().prod(1) == 0)).sum())
    return {"textures_dropped": dropped, "texels_before": before, "texels_after": model.num_texels}
