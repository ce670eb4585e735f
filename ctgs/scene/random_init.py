"""Initial points for a scene without SfM points: random points in the cameras' bounds, as 3DGS starts its synthetic
scenes (100,000 points uniform in a cube about the object, random colours).

The cube: where the cameras look. Its centre is the point nearest every camera's optical axis (least squares, as
instant-ngp's colmap2nerf centres a capture); its half side is 0.375 x the cameras' mean distance to that point,
which is instant-ngp's unit cube for the captures it normalises (cameras 4 units away, cube [-1.5, 1.5]) and within
15% of 3DGS's [-1.3, 1.3] for NeRF's Blender scenes (cameras 4.03 units away). A file that gives instant-ngp's
`aabb_scale` gives the box itself (ctgs.scene.transforms).
"""

from __future__ import annotations

import numpy as np

RANDOM_POINTS = 100_000  # 3DGS's count for its synthetic scenes
FOCUS_HALF_SIDE = 0.375  # x the cameras' mean distance to their focus point
SEED = 0  # the same points for every run of a scene


def focus_box(viewmats: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [3] of the cube the cameras (world -> camera [4, 4] each) look at."""
    rot = np.stack([np.asarray(v, np.float64)[:3, :3] for v in viewmats])  # [C, 3, 3]
    centres = -np.einsum("cji,cj->ci", rot, np.stack([np.asarray(v, np.float64)[:3, 3] for v in viewmats]))
    axes = rot[:, 2, :]  # [C, 3] viewing directions (camera z in world coordinates)
    # the point p minimising sum_c |(I - a a^T)(p - c)|^2: sum (I - a a^T) p = sum (I - a a^T) c
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    a, b = proj.sum(0), np.einsum("cij,cj->i", proj, centres)
    mean = centres.mean(0)
    spread = float(np.linalg.norm(centres - mean, axis=1).max())
    if len(viewmats) >= 2 and np.linalg.cond(a) < 1e6:
        focus = np.linalg.solve(a, b)
    else:  # parallel axes (or one camera): the point one spread ahead of the mean camera
        focus = mean + axes.mean(0) * max(spread, 1.0)
    distance = float(np.linalg.norm(centres - focus, axis=1).mean())
    if not (np.isfinite(focus).all() and distance > 0) or distance > 100 * max(spread, 1e-9):
        focus, distance = mean + axes.mean(0) * max(spread, 1.0), max(spread, 1.0)
    half = FOCUS_HALF_SIDE * distance
    return focus - half, focus + half


def random_points(lo: np.ndarray, hi: np.ndarray, count: int = RANDOM_POINTS,
                  seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """(points [count, 3] float64 uniform in the box, colours [count, 3] uint8 uniform)."""
    rng = np.random.default_rng(seed)
    points = lo + rng.random((count, 3)) * (np.asarray(hi) - np.asarray(lo))
    colors = rng.integers(0, 256, size=(count, 3), dtype=np.uint8)
    return points, colors
