"""Where a model spends its texels: texels per unit area on each kind of surface of the demo scene.

Used by the content-aware allocation test and the benchmark table (demo_meta.json lists the planar
surfaces, their kind photo/flat/smooth, frame and area).
"""

from __future__ import annotations

import numpy as np

# A primitive belongs to a surface if its centre lies within this distance of the plane (world units)
# and inside the rectangle grown by this fraction: the demo scene is a box room ~5 units across.
PLANE_TOL = 0.15
EDGE_GROW = 0.05


def texel_density_by_kind(model, meta: dict) -> dict[str, float]:
    """{kind: allocated texels of the primitives on surfaces of that kind / total area of those surfaces}."""
    means = model.means.detach().cpu().numpy().astype(np.float64)
    tex = (model.tex_res[:, 0].long() * model.tex_res[:, 1].long()).cpu().numpy()
    best = np.full(len(means), np.inf)
    kind = np.full(len(means), "", dtype=object)
    for s in meta["surfaces"]:
        c, n, u, v = (np.asarray(s[k], dtype=np.float64) for k in ("center", "normal", "u", "v"))
        d = means - c
        dist = np.abs(d @ n)
        hu, hv = (h * (1 + EDGE_GROW) for h in s["half_extents"])
        sel = (np.abs(d @ u) <= hu) & (np.abs(d @ v) <= hv) & (dist < PLANE_TOL) & (dist < best)
        best[sel] = dist[sel]
        kind[sel] = s["kind"]
    out = {}
    for k in sorted({s["kind"] for s in meta["surfaces"]}):
        area = sum(s["area"] for s in meta["surfaces"] if s["kind"] == k)
        out[k] = float(tex[kind == k].sum() / area) if area > 0 else 0.0
    return out
