"""A mesh against the exact surfaces of the demo scene (its rectangles, `demo_meta.json`): Chamfer distance, normal
consistency and F-score, as surface-reconstruction benchmarks (DTU, Tanks and Temples) report them.

- accuracy: mean distance from points sampled on the mesh (area-uniform) to the true surfaces (exact, to the nearest
  rectangle); completeness: mean distance from points sampled on the true surfaces that a camera sees (in its image,
  facing it, nothing in between) to the mesh (to the nearest of dense mesh samples: off by at most about half their
  spacing, which the result reports); Chamfer = their mean (DTU's "overall").
- normal consistency: mean |n_mesh . n_true| over both sample sets (each point against its nearest counterpart's
  normal), 1 for parallel surfaces: orientation-free, as Occupancy Networks defines it.
- F-score at tau: the harmonic mean of precision (mesh samples within tau of the truth) and recall (true samples
  within tau of the mesh), as Tanks and Temples defines it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

OCCLUSION_EPS = 1e-4  # relative: a rectangle occludes a point only if hit strictly between camera and point


def _rects(meta: dict) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]]:
    return [(np.asarray(s["center"], float), np.asarray(s["u"], float), np.asarray(s["v"], float),
             np.asarray(s["normal"], float), tuple(s["half_extents"])) for s in meta["surfaces"]]


def sample_surfaces(meta: dict, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(points [count, 3], unit normals [count, 3]) area-uniform on the demo's rectangles."""
    rng = np.random.default_rng(seed)
    rects = _rects(meta)
    areas = np.array([4 * h[0] * h[1] for *_, h in rects])
    per = rng.multinomial(count, areas / areas.sum())
    pts, nrm = [], []
    for (c, u, v, n, h), k in zip(rects, per):
        a, b = rng.uniform(-h[0], h[0], k), rng.uniform(-h[1], h[1], k)
        pts.append(c + a[:, None] * u + b[:, None] * v)
        nrm.append(np.repeat(n[None], k, 0))
    return np.concatenate(pts), np.concatenate(nrm)


def visible(points: np.ndarray, normals: np.ndarray, meta: dict, cameras) -> np.ndarray:
    """[P] bool: points some camera sees (projects into its image, on the side the surface faces, not hidden by
    another rectangle). cameras: ctgs Cameras (viewmat world -> camera)."""
    rects = _rects(meta)
    seen = np.zeros(len(points), bool)
    for cam in cameras:
        vm = cam.viewmat.detach().cpu().double().numpy()
        rot, t = vm[:3, :3], vm[:3, 3]
        origin = -rot.T @ t
        pc = points @ rot.T + t
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * pc[:, 0] / z + cam.cx
            v = cam.fy * pc[:, 1] / z + cam.cy
        ok = (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height) & ~seen
        ok &= ((origin[None] - points) * normals).sum(1) > 0
        idx = np.nonzero(ok)[0]
        ray = points[idx] - origin  # from the camera, t = 1 at the point
        blocked = np.zeros(len(idx), bool)
        for c, ru, rv, n, h in rects:
            denom = ray @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                s = ((c - origin) @ n) / denom
            hit = origin + s[:, None] * ray
            inside = (np.abs((hit - c) @ ru) <= h[0]) & (np.abs((hit - c) @ rv) <= h[1])
            blocked |= np.isfinite(s) & (s > OCCLUSION_EPS) & (s < 1 - OCCLUSION_EPS) & inside
        seen[idx[~blocked]] = True
    return seen


def distance_to_surfaces(points: np.ndarray, meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """(distance [P] to the nearest rectangle, that rectangle's unit normal [P, 3]), exact."""
    best = np.full(len(points), np.inf)
    normal = np.zeros((len(points), 3))
    for c, u, v, n, h in _rects(meta):
        rel = points - c
        a = np.clip(rel @ u, -h[0], h[0])
        b = np.clip(rel @ v, -h[1], h[1])
        d = np.linalg.norm(rel - a[:, None] * u - b[:, None] * v, axis=1)
        closer = d < best
        best = np.where(closer, d, best)
        normal[closer] = n
    return best, normal


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(points [count, 3], unit face normals [count, 3]) area-uniform on the mesh."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(vertices, np.float64)[faces]  # [F, 3, 3]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    pick = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    pts = (tri[pick] * w[:, :, None]).sum(1)
    return pts, cross[pick] / area[pick, None]


def mesh_accuracy(vertices: np.ndarray, faces: np.ndarray, meta: dict, cameras, samples: int = 400_000,
                  taus: tuple[float, ...] = (0.01, 0.02, 0.05), seed: int = 0) -> dict:
    """The figures above for a mesh (world units of the demo scene, ~metres)."""
    mp, mn = sample_mesh(vertices, faces, samples, seed)
    gp, gn = sample_surfaces(meta, samples, seed + 1)
    keep = visible(gp, gn, meta, cameras)
    gp, gn = gp[keep], gn[keep]
    d_acc, n_true = distance_to_surfaces(mp, meta)
    tree = cKDTree(mp)
    d_comp, nearest = tree.query(gp)
    nc_acc = np.abs((mn * n_true).sum(1))
    nc_comp = np.abs((gn * mn[nearest]).sum(1))
    spacing = float(np.sqrt(np.linalg.norm(np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1).sum()
        / 2 / samples))
    out = {"accuracy": float(d_acc.mean()), "completeness": float(d_comp.mean()),
           "chamfer": float((d_acc.mean() + d_comp.mean()) / 2),
           "accuracy_median": float(np.median(d_acc)), "completeness_median": float(np.median(d_comp)),
           "normal_consistency": float((nc_acc.mean() + nc_comp.mean()) / 2),
           "mesh_samples": int(len(mp)), "true_samples_seen": int(len(gp)), "mesh_sample_spacing": spacing,
           "fscore": {}}
    for tau in taus:
        p, r = float((d_acc < tau).mean()), float((d_comp < tau).mean())
        out["fscore"][str(tau)] = {"precision": p, "recall": r, "f": 2 * p * r / (p + r) if p + r else 0.0}
    return out
