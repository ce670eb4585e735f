"""Initial points on a far shell, where the training views see past the SfM points (sky, distant background).

SfM leaves no points in the sky, so nothing starts there, and a short run may never grow primitives into it: at
384x256 on herzjesu25 the content-aware `fast` runs left 4-7% of a validation view and 13-14% of the extrapolated
test view uncovered (docs/studies.md; benchmarks/results/archive/open_pixels/herzjesu25_384_3c82d75.md). `init_shell`
> 0 adds that many points on a sphere around the scene, in directions some training camera sees, each coloured by
the mean of the training pixels it projects to. They train like the other primitives with two differences: the split
and upscale routines leave them out (`far_mask`), so the top-E share the routines refine stays with the scene's own
primitives; and in training renders they show only where the view sees past the SfM points (`composite`), so they
cannot stand in for a transparent scene (off in every preset until measured). `Shell` is the component that does both
in a run.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from ctgs.train.hooks import Component
from ctgs.train.routines.far import far_mask

# Shell radius: this many times the radius holding 98% of the SfM points and every camera centre (around the SfM
# points' median), so the shell lies beyond the reconstructed scene.
SHELL_RADIUS_FACTOR = 3.0
# Candidate directions per requested point (Fibonacci sphere); the visible ones are thinned to the request.
CANDIDATES_PER_POINT = 40
# A shell point counts for a view only where no SfM point projects within about this many pixels (cells of this size,
# dilated by one): the shell fills what the views see past the reconstruction, not what lies behind it.
OCCUPANCY_CELL_PX = 8


def fibonacci_sphere(n: int) -> np.ndarray:
    """[n, 3] unit vectors spread evenly over the sphere."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def project(xyz: np.ndarray, R: np.ndarray, t: np.ndarray, c) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (u, w) of world points in camera c and whether each lands inside its image, in front."""
    p = xyz @ R.T + t
    z = p[:, 2]
    front = z > c.near
    zs = np.where(front, z, 1.0)
    u = np.where(front, c.fx * p[:, 0] / zs + c.cx, -1.0)
    w = np.where(front, c.fy * p[:, 1] / zs + c.cy, -1.0)
    return u, w, front & (u >= 0) & (u < c.width) & (w >= 0) & (w < c.height)


def scene_sphere(points: np.ndarray, views: list) -> tuple[np.ndarray, float]:
    """(centre [3], reach): the SfM points' median and the radius around it that holds 98% of them and every
    training camera centre."""
    pts = np.asarray(points, np.float64)
    centre = np.median(pts, 0) if len(pts) else np.zeros(3)
    cams = np.stack([v.camera.center.detach().double().cpu().numpy() for v in views])
    reach = max(float(np.quantile(np.linalg.norm(pts - centre, axis=1), 0.98)) if len(pts) else 0.0,
                float(np.linalg.norm(cams - centre, axis=1).max()), 1e-6)
    return centre, reach


def _occupied_cells(pts: np.ndarray, c) -> np.ndarray:
    """[gh + 2, gw + 2] bool grid of OCCUPANCY_CELL_PX cells (one cell of border) that SfM points reach in camera c,
    dilated by one cell."""
    R, t = c.R.detach().double().cpu().numpy(), c.t.detach().double().cpu().numpy()
    gw, gh = -(-c.width // OCCUPANCY_CELL_PX), -(-c.height // OCCUPANCY_CELL_PX)
    occupied = np.zeros((gh + 2, gw + 2), bool)
    if len(pts):
        u, w, ok = project(pts, R, t, c)
        occupied[(w[ok] // OCCUPANCY_CELL_PX).astype(np.int64) + 1, (u[ok] // OCCUPANCY_CELL_PX).astype(np.int64) + 1] = True
        occupied = occupied | np.roll(occupied, 1, 0) | np.roll(occupied, -1, 0)
        occupied = occupied | np.roll(occupied, 1, 1) | np.roll(occupied, -1, 1)
    return occupied


def open_mask(points: np.ndarray, camera) -> np.ndarray:
    """[H, W] bool: pixels of `camera` where it sees past the SfM points (no point within one dilated
    OCCUPANCY_CELL_PX cell): where the shell may show in training renders (`composite`)."""
    occ = _occupied_cells(np.asarray(points, np.float64), camera)[1:-1, 1:-1]
    rows = np.arange(camera.height) // OCCUPANCY_CELL_PX
    cols = np.arange(camera.width) // OCCUPANCY_CELL_PX
    return ~occ[rows[:, None], cols[None, :]]


def composite(render_fn, inputs, camera, far: torch.Tensor, open_px: torch.Tensor, background: torch.Tensor):
    """Training render with the shell behind the scene only where the view sees past the SfM points.

    Renders the scene's primitives (`far` False) over nothing and the far ones over `background`, then composites
    rgb = scene + T_scene x (far render where `open_px`, else `background`). Where `open_px` is True everywhere
    this is the single render of all primitives (the far ones lie behind the scene); elsewhere the far primitives
    cannot stand in for a transparent scene, so a random `background` still asks the scene to cover what SfM
    reconstructed. Returns (rgb [H, W, 3], [N] bool rasterized by either render or None).
    """
    near_in = replace(inputs, opacities=inputs.opacities * (~far).to(inputs.opacities.dtype))
    far_in = replace(inputs, opacities=inputs.opacities * far.to(inputs.opacities.dtype))
    a = render_fn(near_in, camera, background=torch.zeros_like(background))
    b = render_fn(far_in, camera, background=background)
    behind = torch.where(open_px[..., None], b.rgb, background.expand_as(b.rgb))
    rgb = a.rgb + (1 - a.alpha)[..., None] * behind
    ras = a.rasterized | b.rasterized if a.rasterized is not None and b.rasterized is not None else None
    return rgb, ras


def shell_points(points: np.ndarray, views: list, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [M, 3], rgb [M, 3] in [0, 1]) with M <= count: shell points that project into >= 1 training image at a
    pixel no SfM point reaches (OCCUPANCY_CELL_PX), coloured by the mean of those pixels."""
    if count <= 0 or not len(views):
        return np.zeros((0, 3)), np.zeros((0, 3))
    pts = np.asarray(points, np.float64)
    centre, reach = scene_sphere(pts, views)
    xyz = centre + SHELL_RADIUS_FACTOR * reach * fibonacci_sphere(count * CANDIDATES_PER_POINT)
    colour_sum, seen = np.zeros_like(xyz), np.zeros(len(xyz))
    for v in views:
        c = v.camera
        R, t = c.R.detach().double().cpu().numpy(), c.t.detach().double().cpu().numpy()
        occupied = _occupied_cells(pts, c)  # a shell point there would sit behind the SfM points
        u, w, inside = project(xyz, R, t, c)
        if not inside.any():
            continue
        open_ = inside.copy()
        open_[inside] = ~occupied[(w[inside] // OCCUPANCY_CELL_PX).astype(np.int64) + 1,
                                  (u[inside] // OCCUPANCY_CELL_PX).astype(np.int64) + 1]
        if not open_.any():
            continue
        img = v.image if isinstance(v.image, np.ndarray) else v.image.detach().cpu().numpy()
        colour_sum[open_] += img[w[open_].astype(np.int64), u[open_].astype(np.int64), :3]
        seen[open_] += 1
    keep = np.flatnonzero(seen > 0)
    if len(keep) > count:  # thin evenly along the Fibonacci order (which is spatially coherent)
        keep = keep[np.linspace(0, len(keep) - 1, count).round().astype(np.int64)]
    return xyz[keep], colour_sum[keep] / seen[keep, None]


class Shell(Component):
    """init_shell: the sphere that tells the far shell's primitives (initial points: start.init.scene_model) from the
    scene's; training renders composite the scene over them where the view sees past the SfM points (two renders:
    composite), and the content-aware routines never split or upscale them."""

    def __init__(self, scene, train_views, device):
        self.sphere = scene_sphere(scene.points, scene.train)
        # per training view, the pixels where the shell may show in training renders
        self.open_px = {v.name: torch.from_numpy(open_mask(scene.points, v.camera)).to(device) for v in train_views}

    def far(self, model) -> torch.Tensor:
        """[N] bool: model's primitives on the far shell."""
        return far_mask(model.means, *self.sphere)

    def render(self, st, inputs, view, bg):
        return composite(st.render_fn, inputs, view.camera, self.far(st.model), self.open_px[view.name],
                         st.background if bg is None else bg)
