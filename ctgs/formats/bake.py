"""Textured surfels -> untextured ones that carry the texture's detail: one small flat Gaussian per texel.

Gaussian viewers (3DGS PLY, .splat, .spz) know one colour per splat, so the plain exports fold each texture into
its mean colour (ctgs.formats.plain_ply), which loses the detail the content-aware method puts in textures (9.7 dB on
the `make demo` model: docs/reference/model_format.md). `bake_texels` instead replaces every textured surfel by a lattice of
coplanar Gaussians, one at each texel centre, which any Gaussian viewer draws:

- position: the texel centre on the surfel's plane, mu + lx u + ly v, with lx = (i - (r_u - 1) / 2) k_u (the
  renderer's texel layout: centres at integer texel coordinates, the grid centred on the surfel);
- shape: the surfel's rotation, both tangent scales BAKE_SIGMA x the texel size (neighbours overlap, so the
  colours blend between centres much as the renderer's bilinear lookup does);
- colour: the surfel's SH with the texel added to the DC band (dc + texel / C0); texels outside the grid read 0,
  as in the renderer;
- opacity: the surfel's alpha at that texel centre, A = o exp(-rho / 2) (0 past 3 sigma), split over the lattice:
  a is the peak opacity with which a uniform lattice of these splats composites to A on the mean over a texel
  cell (1 - prod_j (1 - a w_j(x)) averaged over CELL_SAMPLES^2 points x of the cell; w_j the lattice splats'
  Gaussian weights there), so the lattice reproduces the surfel's coverage where its alpha varies slowly.
  Lattice points whose a is below the renderer's 1/255 are dropped.
The lattice covers the texture grid and, where the surfel's active extent (alpha >= 1/255) reaches past the grid,
up to MAX_RINGS more rings of texels (whose texture is 0). A surfel whose texels are wider than LATTICE_MAX_TEXEL x
its smaller sigma (a few coarse texels, whose centres may lie outside the surfel: its texture is a gentle gradient
across it) stays one splat with its texture folded into one colour, as in the plain exports; so do untextured ones.

With a splat budget (`ctgs export --bake-max-splats`, and .spz's 10M points), plan_levels bakes each surfel on its
own texels, on 2^l x 2^l blocks of them averaged (one splat per block), or folded, choosing per surfel by the detail
each option drops against the splats it saves: flat textures go coarse first (docs/reference/model_format.md).

What is approximate: coplanar splats composite in depth order rather than summing, so between texel centres the
nearer splat weighs more than a bilinear lookup would; a lattice of half-texel Gaussians covers at most 90% of a
cell even at the largest alpha (an opaque surfel lets 10% of what lies behind through, which in a trained scene
is more surface: the `make demo` model's baked render covers 99.94% of a training view, the exact one 99.91%);
and the splats of overlapping surfels sort among each other by their own depths, where the renderer sorted the
whole surfels. Measured on training views while choosing BAKE_SIGMA (0.35-0.6: 0.5 best on the `make demo` model,
0.04-0.18 dB above 0.45 and 0.55) and LATTICE_MAX_TEXEL (0.5 / 1 / 2 / 4: 2 best), and on test views in
benchmarks/export_formats.py (the `--bake-textures` rows). Wider splats where the surfel is opaque (to cover the whole cell) and
sharpening the texels first were tried there too and did not help (-0.06 and -0.8 dB).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import torch

from ctgs.errors import UserError
from ctgs.formats.plain_ply import FLAT_SCALE_RATIO, SH_C0, surfels_from_gaussians, texture_means
from ctgs.model.extent import active_half_extent
from ctgs.model.jagged import texel_coords
from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.render.constants import CUTOFF_RHO, MAX_ALPHA, MIN_ALPHA
from ctgs.render.geometry import quat_to_rotmat

BAKE_SIGMA = 0.5  # sub-splat standard deviation, in texel spacings
MAX_RINGS = 64  # lattice rings past the texture grid where the surfel's active extent reaches beyond it
LATTICE_MAX_TEXEL = 2.0  # a texel wider than this x the surfel's smaller sigma: the surfel stays one splat, folded
FLAT_LOG_RATIO = math.log(FLAT_SCALE_RATIO)  # the splats' third (normal) scale, as the plain exports write it
CELL_SAMPLES = 4  # per axis: where in a lattice cell the composite alpha is matched (its mean over them)
CHUNK_SPLATS = 1 << 18  # lattice points baked at a time (float64 intermediates: about 1 KB each at SH degree 3)


def lattice_weights(sigma: float = BAKE_SIGMA) -> torch.Tensor:
    """[S, J] weights of the lattice Gaussians j around a cell at S sample points spread over the cell (float64):
    a lattice of peak opacity a composites there to 1 - prod_j (1 - a w[s, j])."""
    reach = math.ceil(math.sqrt(CUTOFF_RHO) * sigma) + 1
    d = torch.arange(-reach, reach + 1, dtype=torch.float64)
    du, dv = torch.meshgrid(d, d, indexing="ij")
    offs = (torch.arange(CELL_SAMPLES, dtype=torch.float64) + 0.5) / CELL_SAMPLES - 0.5  # in (-1/2, 1/2)
    su, sv = torch.meshgrid(offs, offs, indexing="ij")
    rho = ((su.reshape(-1, 1) - du.reshape(1, -1)) ** 2 + (sv.reshape(-1, 1) - dv.reshape(1, -1)) ** 2) / sigma**2
    return torch.exp(-0.5 * rho) * (rho <= CUTOFF_RHO)


@functools.lru_cache(maxsize=16)
def _coverage_table(sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(peak opacities a, the cell-mean alpha a uniform lattice of them composites to), increasing."""
    table_a = torch.linspace(0.0, MAX_ALPHA, 1001, dtype=torch.float64)
    w = lattice_weights(sigma)
    return table_a, 1.0 - torch.prod(1.0 - table_a[:, None, None] * w[None], dim=2).mean(1)


def split_opacity(target: torch.Tensor, sigma: float = BAKE_SIGMA) -> torch.Tensor:
    """Per-splat peak opacity a in [0, MAX_ALPHA] whose uniform lattice of splats of `sigma` texels composites to
    `target` on the mean over a cell (interpolated in a table of the monotone map a -> mean alpha; float64).
    Targets above what that lattice can reach are capped there."""
    table_a, alpha = _coverage_table(sigma)
    t = target.double().clamp(0.0, float(alpha[-1]))
    i = torch.searchsorted(alpha, t).clamp(1, len(table_a) - 1)
    a0, a1, f0, f1 = table_a[i - 1], table_a[i], alpha[i - 1], alpha[i]
    return a0 + (a1 - a0) * ((t - f0) / (f1 - f0).clamp_min(1e-300))


def bake_texels(model: SurfelModel, sigma: float = BAKE_SIGMA, lattice_max_texel: float = LATTICE_MAX_TEXEL,
                max_splats: int | None = None, budget: int | None = None, levels: torch.Tensor | None = None,
                chunk_splats: int = CHUNK_SPLATS) -> SurfelModel:
    """`model` with every textured surfel replaced by its lattice of texel splats (module docstring); untextured,
    float32, texture_mode "none".

    budget: at most this many splats in all. Where the full bake has more, textures are baked on coarser texels
    where that costs least (plan_levels: each surfel's texels box-averaged over 2^l x 2^l blocks, or its texture
    folded into one colour), so flat textures give up their splats first. UserError if even one splat per surfel
    is more than the budget. levels: an explicit plan instead ([N]: the level per surfel, FOLD for one splat; a level
    a surfel cannot take is refused with ValueError).

    Surfels are baked a chunk at a time (at most `chunk_splats` lattice points each, one surfel past it when a
    single lattice is larger) in float64 and kept in float32, so memory grows with the splats written, not with
    the float64 intermediates. max_splats: raise UserError as soon as the count passes it (a format's limit),
    before the rest is baked."""
    n = model.num_primitives
    if budget is not None and levels is not None:
        raise ValueError("pass budget or levels, not both")
    if budget is not None:
        levels = plan_levels(model, budget, sigma, lattice_max_texel, chunk_splats)["level"]
    elif levels is None:
        levels = torch.where(_latticeable(model, lattice_max_texel, 0), 0, FOLD)
    for level in set(levels.tolist()) - {FOLD}:
        if not bool(_latticeable(model, lattice_max_texel, level)[levels == level].all()):
            raise ValueError(f"level {level} asked of surfels whose texture grid or texel size does not allow it")
    total = 0

    def counted(count: int) -> None:
        nonlocal total
        total += count
        if max_splats is not None and total > max_splats:
            raise UserError(f"baking the textures gives more than {max_splats} splats (the format's limit; the model "
                            f"has {n} surfels and {model.num_texels} texels): pass --bake-max-splats {max_splats}, "
                            "or export --format ply")

    keep = torch.nonzero(levels == FOLD).squeeze(1)  # surfels that stay one splat each
    counted(len(keep))
    parts = []
    for level in sorted(set(levels.tolist()) - {FOLD}):
        idx = torch.nonzero(levels == level).squeeze(1)
        coarse, shared = _level_model(model, level, levels == level)
        rings, lat = _lattice_sizes(coarse, idx, shared.half)
        sizes = lat[:, 0] * lat[:, 1]
        for chunk in _chunks(sizes, chunk_splats):
            parts.append(_to_surfels(_lattice(coarse, idx[chunk], rings[chunk], lat[chunk], shared, sigma)))
            counted(parts[-1].num_primitives)
    # The other surfels as one splat each, their texture folded into the DC band (as the plain exports do).
    log_s = model.log_scales.detach().double()[keep]
    sh = model.sh.detach().double()[keep].clone()
    sh[:, 0, :] += texture_means(model)[keep] / SH_C0
    folded = {
        "means": model.means.detach().double()[keep],
        "log_scales": torch.cat([log_s, (log_s.min(1).values + FLAT_LOG_RATIO)[:, None]], 1),
        "quats": model.quats.detach().double()[keep],
        "opacity_logits": model.opacity_logits.detach().double()[keep],
        "sh": sh,
    }
    parts.append(_to_surfels(folded))
    out = _concat(parts)
    out.sh_degree = model.sh_degree
    return out


FOLD = -1  # plan level of a surfel baked as one splat, its texture folded into one colour


def bake_bound(model: SurfelModel, lattice_max_texel: float = LATTICE_MAX_TEXEL) -> int:
    """At least the full bake's splat count (its lattice points before the opacity cut), from per-surfel sizes
    alone: where it fits a budget, the full bake does and no plan is needed."""
    idx = torch.nonzero(_latticeable(model, lattice_max_texel, 0)).squeeze(1)
    _, lat = _lattice_sizes(model, idx, active_half_extent(model).double())
    return int((lat[:, 0] * lat[:, 1]).sum()) + model.num_primitives - len(idx)


def _latticeable(model: SurfelModel, lattice_max_texel: float, level: int) -> torch.Tensor:
    """[N] bool: textured surfels that bake to a lattice at `level` (texels 2^level x as wide, tiling the grid,
    no wider than lattice_max_texel x the smaller sigma)."""
    res = model.tex_res.long()
    if model.num_texels == 0 or model.texture_mode == "none":
        return torch.zeros(model.num_primitives, dtype=torch.bool)
    block = 1 << level
    tiles = (res[:, 0] % block == 0) & (res[:, 1] % block == 0) & (res[:, 0] * res[:, 1] > 0)
    k = model.texel_size.detach().double().max(1).values * block
    return tiles & (k <= lattice_max_texel * model.scales.detach().double().min(1).values)


def _texel_rows(model: SurfelModel, which: torch.Tensor):
    """(surfel, iu, iv, texture row) of every texel of the surfels `which` ([N] bool)."""
    prim, iu, iv = texel_coords(model.tex_res.long() * which[:, None])
    return prim, iu, iv, model.tex_offset.long()[prim] + iv * model.tex_res.long()[prim, 0] + iu


def _level_model(model: SurfelModel, level: int, which: torch.Tensor) -> tuple[SurfelModel, "_Shared"]:
    """`model` with the textures of surfels `which` box-averaged over 2^level x 2^level texel blocks (the grid
    centre stays where it was: every block tiles it), the others untextured; and its _Shared, whose activated
    textures are the averages."""
    if level == 0:
        return model, _Shared(model)
    block = 1 << level
    prim, iu, iv, row = _texel_rows(model, which)
    res = (model.tex_res.long() * which[:, None]) // block
    offsets = jagged_offsets(res.to(torch.int32))
    coarse = torch.zeros(int((res[:, 0] * res[:, 1]).sum()), 3)
    target = offsets[prim] + (iv // block) * res[prim, 0] + iu // block
    coarse.index_add_(0, target, model.textures.detach().float()[row])
    coarse /= block * block
    t2p = model.t2p_exp + level if model.texture_mode == "content_aware" else model.t2p_exp
    derived = dataclasses.replace(model, tex_res=res.to(torch.int32), tex_offset=offsets, t2p_exp=t2p,
                                  textures_raw=torch.zeros(len(coarse), 3))
    return derived, _Shared(derived, textures=coarse)


def plan_levels(model: SurfelModel, budget: int, sigma: float = BAKE_SIGMA,
                lattice_max_texel: float = LATTICE_MAX_TEXEL, chunk_splats: int = CHUNK_SPLATS,
                area: str = "pixels") -> dict:
    """Per surfel, the texel level to bake at so that the splats fit `budget`: {"level": [N] (0 = the texels as
    trained, l = 2^l x 2^l blocks averaged, FOLD = one splat), "splats": the total, "error": the plan's error}.

    Each surfel's options are scored by the detail they drop, E = sum over its texels of alpha x texel area x
    |texel - what the option shows there|^2 (the block mean, or the folded colour), and the splats S they bake to
    (counted as the bake counts them). The plan minimises sum E + lambda sum S, lambda the least (by bisection)
    for which sum S fits the budget: flat textures (E ~ 0 at every level) go coarse first, detailed ones last."""
    n = model.num_primitives
    if n > budget:
        raise UserError(f"a bake to {budget} splats: the model has {n} surfels and bakes to at least one splat each; "
                        f"pass --bake-max-splats of at least {n}")
    levels, errors, counts = [FOLD], [torch.zeros(n, dtype=torch.float64)], [torch.ones(n, dtype=torch.float64)]
    lattice_ok = _latticeable(model, lattice_max_texel, 0)
    if bool(lattice_ok.any()):
        _lattice_options(model, budget, lattice_ok, levels, errors, counts, sigma=sigma,
                         lattice_max_texel=lattice_max_texel, chunk_splats=chunk_splats, area=area)
    return _cheapest_plan(torch.stack(errors, 1), torch.stack(counts, 1), levels, lattice_ok, budget)


def _lattice_options(model: SurfelModel, budget: int, lattice_ok: torch.Tensor, levels: list, errors: list,
                     counts: list, *, sigma: float, lattice_max_texel: float, chunk_splats: int, area: str) -> None:
    """Append to levels, errors [N], counts [N] each lattice level 0, 1, ... a surfel can bake at (inf where it
    cannot), until no surfel can or the full bake fits `budget`; errors[0] (FOLD) becomes the folded colour's."""
    n = model.num_primitives
    prim, iu, iv, row = _texel_rows(model, lattice_ok)
    tex = model.textures.detach().double()[row]  # [T', 3]
    res = model.tex_res.long()
    k = model.texel_size.detach().double()[prim]  # [T', 2]
    lx = (iu.double() - (res[prim, 0].double() - 1) / 2) * k[:, 0]
    ly = (iv.double() - (res[prim, 1].double() - 1) / 2) * k[:, 1]
    scales = model.scales.detach().double()[prim]
    rho = (lx / scales[:, 0]) ** 2 + (ly / scales[:, 1]) ** 2
    texel_area = k[:, 0] * k[:, 1]  # world units^2
    if area == "pixels":  # in pixels of the closest training camera (k_min: its pixel's world size there)
        texel_area = texel_area / model.k_min.detach().double()[prim] ** 2
    weight = model.opacities.detach().double()[prim] * torch.exp(-0.5 * rho) * (rho <= CUTOFF_RHO) * texel_area

    def error_against(shown: torch.Tensor) -> torch.Tensor:  # [T', 3] -> [N]
        return torch.zeros(n, dtype=torch.float64).index_add_(0, prim, weight * ((tex - shown) ** 2).sum(1))

    errors[0] = torch.where(lattice_ok, error_against(texture_means(model)[prim]), 0.0)
    level = 0
    while True:
        ok = _latticeable(model, lattice_max_texel, level)
        if not bool(ok.any()):
            break
        coarse, shared = _level_model(model, level, ok)
        idx = torch.nonzero(ok).squeeze(1)
        rings, lat = _lattice_sizes(coarse, idx, shared.half)
        count = torch.full((n,), math.inf, dtype=torch.float64)
        for chunk in _chunks(lat[:, 0] * lat[:, 1], chunk_splats):
            owner = _lattice_points(coarse, idx[chunk], rings[chunk], lat[chunk], shared, sigma)[0]
            count[idx[chunk]] = torch.bincount(owner, minlength=len(idx[chunk])).double()
        if level == 0:
            err = torch.zeros(n, dtype=torch.float64)
        else:
            block = 1 << level
            cres = coarse.tex_res.long()
            on = ok[prim]
            crow = coarse.tex_offset.long()[prim] + (iv // block) * cres[prim, 0] + iu // block
            shown = torch.where(on[:, None], shared.textures.double()[torch.where(on, crow, 0)], tex)
            err = error_against(shown)
        levels.append(level)
        errors.append(torch.where(ok, err, math.inf))
        counts.append(count)
        if level == 0 and float(torch.where(lattice_ok, count, 1.0).sum()) <= budget:
            break  # the full bake fits: no coarser level needed
        level += 1


def _cheapest_plan(E: torch.Tensor, S: torch.Tensor, levels: list, lattice_ok: torch.Tensor, budget: int) -> dict:
    """The choice per surfel (E, S: [N, options], option 0 = FOLD) minimising sum E + lambda sum S, lambda the least
    (by geometric bisection) for which sum S fits `budget`; plan_levels' result."""
    S_safe = torch.where(torch.isfinite(E), S, math.inf)
    choice_of = lambda lam: torch.argmin(torch.where(torch.isfinite(E), E + lam * S_safe, math.inf), 1)  # noqa: E731

    def total(choice: torch.Tensor) -> float:
        return float(S_safe.gather(1, choice[:, None]).sum())

    finest = torch.where(lattice_ok, levels.index(0) if 0 in levels else 0, 0)  # the unbudgeted bake's plan
    choice = finest
    if total(finest) > budget:  # bisect lambda (geometrically): sum S falls as lambda grows
        lo, hi = 0.0, 1.0
        while total(choice_of(hi)) > budget:
            lo, hi = hi, hi * 4.0
        for _ in range(200):
            mid = hi / 2 if lo == 0.0 else math.sqrt(lo * hi)
            if total(choice_of(mid)) > budget:
                lo = mid
            else:
                hi = mid
            if lo > 0.0 and hi / lo < 1.0 + 1e-9:
                break
        choice = choice_of(hi)
    level_of = torch.tensor(levels)[choice]
    return {"level": level_of, "splats": int(total(choice)), "full_splats": int(total(finest)),
            "error": float(E.gather(1, choice[:, None]).sum())}


class _Shared:
    """Per-model arrays every chunk reads (computed once: the texel activation is over all texels)."""

    def __init__(self, model: SurfelModel, textures: torch.Tensor | None = None):
        self.textures = model.textures.detach().float() if textures is None else textures  # [T, 3] activated
        self.half = active_half_extent(model).double()  # [N, 2] where alpha can reach 1/255
        self.opacity = model.opacities.detach().double()  # [N]


def _lattice_sizes(model: SurfelModel, idx: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """([M, 2] rings past the texture grid, [M, 2] lattice size) of surfels `idx`."""
    res = model.tex_res.long()[idx]
    k = model.texel_size.detach().double()[idx]
    grid_half = (res.double() - 1) / 2  # texel coordinate of the grid's centre
    rings = torch.ceil(half[idx] / k - grid_half).clamp(0, MAX_RINGS).long()
    return rings, res + 2 * rings


def _chunks(sizes: torch.Tensor, limit: int) -> list[slice]:
    """Consecutive slices of `sizes` summing to at most `limit` each (a single larger entry is its own slice)."""
    out, start, acc = [], 0, 0
    for i, s in enumerate(sizes.tolist()):
        if acc and acc + s > limit:
            out.append(slice(start, i))
            start, acc = i, 0
        acc += s
    out.append(slice(start, len(sizes)))
    return out


def _to_surfels(g: dict) -> SurfelModel:
    """A float64 Gaussian dict -> float32 untextured surfels (the third scale is always the smallest here, so every
    quaternion is kept as is)."""
    return surfels_from_gaussians(g["means"], g["log_scales"], g["quats"], g["opacity_logits"], g["sh"])


def _concat(parts: list[SurfelModel]) -> SurfelModel:
    """One untextured model of `parts`, field by field, each part's field freed once copied (peak: the result and
    one field of the parts)."""
    fields = ("means", "log_scales", "quats", "opacity_logits", "sh", "k_min", "t2p_exp", "tex_res", "tex_offset")
    cat = {}
    for name in fields:
        cat[name] = torch.cat([getattr(p, name) for p in parts])
        for p in parts:
            setattr(p, name, None)
    return SurfelModel(**cat, textures_raw=torch.zeros(0, 3), sh_degree=0, texture_mode="none")


def _lattice(model: SurfelModel, idx: torch.Tensor, rings: torch.Tensor, lat: torch.Tensor, shared: _Shared,
             sigma: float) -> dict:
    """The texel splats of surfels `idx` (all textured; rings and lattice sizes from _lattice_sizes), as float64
    Gaussian arrays."""
    res = model.tex_res.long()[idx]  # [M, 2]
    k = model.texel_size.detach().double()[idx]  # [M, 2] world units per texel
    owner, iu, iv, lx, ly, a = _lattice_points(model, idx, rings, lat, shared, sigma)
    surfel = idx[owner]
    inside = (iu >= 0) & (iu < res[owner, 0]) & (iv >= 0) & (iv < res[owner, 1])
    row = model.tex_offset.long()[surfel] + iv.clamp(min=0) * res[owner, 0] + iu.clamp(min=0)
    texel = torch.where(inside[:, None], shared.textures[torch.where(inside, row, 0)].double(), 0.0)  # 0 outside
    quats = model.quats.detach()[surfel].double()
    rot = quat_to_rotmat(quats)  # [L, 3, 3] columns u, v, n
    means = model.means.detach()[surfel].double() + lx[:, None] * rot[:, :, 0] + ly[:, None] * rot[:, :, 1]
    tangent = torch.log(sigma * k[owner])  # [L, 2]
    sh = model.sh.detach()[surfel].double()
    sh[:, 0, :] += texel / SH_C0
    return {
        "means": means,
        "log_scales": torch.cat([tangent, (tangent.min(1).values + FLAT_LOG_RATIO)[:, None]], 1),
        "quats": quats,
        "opacity_logits": torch.log(a / (1.0 - a)),
        "sh": sh,
    }


def _lattice_points(model: SurfelModel, idx: torch.Tensor, rings: torch.Tensor, lat: torch.Tensor, shared: _Shared,
                    sigma: float):
    """(owner, iu, iv, lx, ly, a) of the lattice points of surfels `idx` that bake to a splat: owner = position in
    idx, (iu, iv) texel coordinates in the grid (outside it in the rings), (lx, ly) local position, a the peak
    opacity (split_opacity of the surfel's alpha there, >= 1/255)."""
    res = model.tex_res.long()[idx]  # [M, 2]
    k = model.texel_size.detach().double()[idx]  # [M, 2] world units per texel
    scales = model.scales.detach().double()[idx]  # [M, 2]
    grid_half = (res.double() - 1) / 2  # [M, 2] texel coordinate of the grid's centre
    sizes = lat[:, 0] * lat[:, 1]
    owner = torch.repeat_interleave(torch.arange(len(idx)), sizes)  # [L] which surfel (position in idx)
    local = torch.arange(int(sizes.sum())) - torch.repeat_interleave(torch.cumsum(sizes, 0) - sizes, sizes)
    iu = local % lat[owner, 0] - rings[owner, 0]  # [L] texel coordinates in the texture grid (may be outside)
    iv = local // lat[owner, 0] - rings[owner, 1]
    lx = (iu.double() - grid_half[owner, 0]) * k[owner, 0]
    ly = (iv.double() - grid_half[owner, 1]) * k[owner, 1]
    rho = (lx / scales[owner, 0]) ** 2 + (ly / scales[owner, 1]) ** 2
    target = shared.opacity[idx][owner] * torch.exp(-0.5 * rho) * (rho <= CUTOFF_RHO)
    a = split_opacity(target, sigma)
    on = a >= MIN_ALPHA
    return owner[on], iu[on], iv[on], lx[on], ly[on], a[on]
