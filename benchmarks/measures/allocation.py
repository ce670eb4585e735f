"""Where a model spends its texels: texels per unit area on each kind of surface of the demo scene.

Used by the content-aware allocation test and the benchmark table (demo_meta.json lists the planar
surfaces, their kind photo/flat/smooth, frame and area). Two measures, both reported by the benchmark:
- `texel_density_by_kind` (the test's): all of a primitive's texels are counted on the surface its centre
  lies on (edge primitives count wholly on one side).
- `texel_position_density_by_kind`: every allocated texel is placed where it lies in the world (its centre
  on the primitive's tangent plane) and counted on the surface it lies on, so a primitive straddling a
  photo/flat edge counts on both sides. It depends more on PLANE_TOL (measured: the photo:flat ratio of
  one model goes 9.4x -> 12.8x -> 14.6x at tolerances 0.15 / 0.05 / 0.03).
"""

from __future__ import annotations

import numpy as np
import torch

from ctgs.render.geometry import quat_to_rotmat

# A primitive belongs to a surface if its centre lies within this distance of the plane (world units)
# and inside the rectangle grown by this fraction: the demo scene is a box room ~5 units across.
PLANE_TOL = 0.15
EDGE_GROW = 0.05


def _surface_kind(points: np.ndarray, meta: dict) -> np.ndarray:
    """[P] kind of the nearest surface within PLANE_TOL whose (grown) rectangle holds the point, else ''."""
    best = np.full(len(points), np.inf)
    kind = np.full(len(points), "", dtype=object)
    for s in meta["surfaces"]:
        c, n, u, v = (np.asarray(s[k], dtype=np.float64) for k in ("center", "normal", "u", "v"))
        d = points - c
        dist = np.abs(d @ n)
        hu, hv = (h * (1 + EDGE_GROW) for h in s["half_extents"])
        sel = (np.abs(d @ u) <= hu) & (np.abs(d @ v) <= hv) & (dist < PLANE_TOL) & (dist < best)
        best[sel] = dist[sel]
        kind[sel] = s["kind"]
    return kind


def _per_area(counts: dict, meta: dict) -> dict[str, float]:
    out = {}
    for k in sorted({s["kind"] for s in meta["surfaces"]}):
        area = sum(s["area"] for s in meta["surfaces"] if s["kind"] == k)
        out[k] = float(counts.get(k, 0) / area) if area > 0 else 0.0
    return out


def texel_position_density_by_kind(model, meta: dict) -> dict[str, float]:
    """{kind: allocated texels lying on surfaces of that kind / total area of those surfaces}.

    Texel (i, j) of primitive p lies at mean_p + ((i - (W-1)/2) u_p + (j - (H-1)/2) v_p) * texel size (the
    renderer's uv mapping, docs/reference/renderer.md) and is counted like a primitive centre (within PLANE_TOL of a
    plane, inside its grown rectangle); texels on no surface (floaters, padding in the air) count nowhere.
    Near the demo box (0.9 units across, less than 7x PLANE_TOL) texels of one face also count on the
    perpendicular face next to it.
    """
    counts: dict = {}
    if model.num_texels == 0:
        return _per_area(counts, meta)
    with torch.no_grad():
        rot = quat_to_rotmat(model.quats.detach().double().cpu())  # [N, 3, 3]
        ts = model.texel_size.detach().double().cpu()  # [N, 2]
        means = model.means.detach().double().cpu()
        res = model.tex_res.cpu()
        for ru, rv in {tuple(r) for r in res.tolist() if r[0] * r[1] > 0}:
            idx = torch.nonzero((res[:, 0] == ru) & (res[:, 1] == rv))[:, 0]
            gu = (torch.arange(ru, dtype=torch.float64) - (ru - 1) / 2)  # [ru]
            gv = (torch.arange(rv, dtype=torch.float64) - (rv - 1) / 2)  # [rv]
            lu = gu[None, None, :] * ts[idx, 0][:, None, None]  # [G, 1, ru]
            lv = gv[None, :, None] * ts[idx, 1][:, None, None]  # [G, rv, 1]
            pts = (means[idx][:, None, None, :] + lu[..., None] * rot[idx][:, None, None, :, 0]
                   + lv[..., None] * rot[idx][:, None, None, :, 1])  # [G, rv, ru, 3]
            kind = _surface_kind(pts.reshape(-1, 3).numpy(), meta)
            for k, c in zip(*np.unique(kind, return_counts=True)):
                if k:
                    counts[k] = counts.get(k, 0) + int(c)
    return _per_area(counts, meta)


def texel_density_by_kind(model, meta: dict) -> dict[str, float]:
    """{kind: allocated texels of the primitives whose centre lies on surfaces of that kind / their area}."""
    means = model.means.detach().cpu().numpy().astype(np.float64)
    tex = (model.tex_res[:, 0].long() * model.tex_res[:, 1].long()).cpu().numpy()
    kind = _surface_kind(means, meta)
    return _per_area({k: int(tex[kind == k].sum()) for k in set(kind.tolist()) if k}, meta)


# The paper's parameter count: 59 per primitive (58 of 2DGS + the texel-size exponent) + 3 per texel
# (SurfelModel.num_params: fewer per primitive at a lower SH degree).
PARAMS_PER_PRIMITIVE = 59
PARAMS_PER_TEXEL = 3


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    if len(values) == 0 or weights.sum() <= 0:
        return float("nan")
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def allocation_measures(model, meta: dict) -> dict:
    """What the paper claims, per surface kind of the demo scene (primitives assigned by their centre):

    {kind: {"primitives", "texels", "area", "texel_size_prim" (median over primitives of the world-space texel
    size: k_min * 2**t2p_exp, or the fixed_texture grid spacing), "texel_size_texel" (the same, median over
    texels), "params_per_area" (59 per primitive + 3 per texel, per unit area), "texels_per_area"}}
    plus "ratios": texel size flat : photo (per primitive and per texel) and params per area photo : flat.
    Texel sizes are NaN for a model without textures.
    """
    means = model.means.detach().cpu().numpy().astype(np.float64)
    kind = _surface_kind(means, meta)
    tex = (model.tex_res[:, 0].long() * model.tex_res[:, 1].long()).cpu().numpy().astype(np.float64)
    textured = model.texture_mode != "none" and model.num_texels > 0
    if textured:
        ts = model.texel_size.detach().cpu().numpy().astype(np.float64)  # [N, 2]
        size = np.sqrt(ts[:, 0] * ts[:, 1])  # isotropic for content-aware; geometric mean for fixed grids
    n = model.num_primitives
    per_prim = (model.num_params() - PARAMS_PER_TEXEL * model.num_texels) / n if n else float(PARAMS_PER_PRIMITIVE)
    out: dict = {}
    for k in sorted({s["kind"] for s in meta["surfaces"]}):
        area = sum(s["area"] for s in meta["surfaces"] if s["kind"] == k)
        sel = kind == k
        rec = {"primitives": int(sel.sum()), "texels": int(tex[sel].sum()), "area": float(area)}
        has = sel & (tex > 0) if textured else np.zeros_like(sel)
        rec["texel_size_prim"] = float(np.median(size[has])) if has.any() else float("nan")
        rec["texel_size_texel"] = _weighted_median(size[has], tex[has]) if has.any() else float("nan")
        params = per_prim * rec["primitives"] + PARAMS_PER_TEXEL * rec["texels"]
        rec["params_per_area"] = params / area if area > 0 else float("nan")
        rec["texels_per_area"] = rec["texels"] / area if area > 0 else float("nan")
        out[k] = rec
    photo, flat = out.get("photo", {}), out.get("flat", {})

    def ratio(a, b):
        return float(a / b) if a == a and b == b and b > 0 else float("nan")  # NaN-safe

    out["ratios"] = {
        "texel_size_prim_flat_over_photo": ratio(flat.get("texel_size_prim", np.nan), photo.get("texel_size_prim", np.nan)),
        "texel_size_texel_flat_over_photo": ratio(flat.get("texel_size_texel", np.nan),
                                                  photo.get("texel_size_texel", np.nan)),
        "params_per_area_photo_over_flat": ratio(photo.get("params_per_area", np.nan), flat.get("params_per_area", np.nan)),
        "texels_per_area_photo_over_flat": ratio(photo.get("texels_per_area", np.nan), flat.get("texels_per_area", np.nan)),
    }
    return out
