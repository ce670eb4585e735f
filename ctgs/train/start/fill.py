"""Initial points where a training view sees no SfM point, at the depth of the SfM points nearby (`init_fill`).

SfM leaves regions without points (sky, distant trees, walls seen by one or two cameras), and the content-aware
method adds primitives only by splitting the ones it has (the paper's primitive management: no cloning), so a short
run can only cover such regions by growing the primitives at their edge. At 384x256 on herzjesu25 the `fast`
1500-iteration runs leave 5-12% of some training views open, 64-94% of it in cells no SfM point reaches, where 2DGS,
which clones, leaves 0-2.6% (docs/studies.md). `init_fill` adds, before training,
one point per FILL_CELL_PX cell of each training view whose centre no SfM point reaches
(ctgs.train.components.shell.open_mask: 8-px cells, dilated by one), on the centre pixel's ray at the median z-depth of the NEIGHBOURS SfM points that
project nearest to it in that view, coloured by the cell's mean pixel. Views are taken in order and each one's
occupancy counts the points the earlier views added, so a region seen by several views is filled once. The points
are ordinary primitives from then on (split, upscaled and pruned like the others).
"""

from __future__ import annotations

import numpy as np

from ctgs.train.components.shell import open_mask, project

FILL_CELL_PX = 16  # one candidate point per cell of this many pixels (of the training images)
NEIGHBOURS = 16  # SfM points whose median depth places a fill point


def _image(view) -> np.ndarray:
    img = view.image if isinstance(view.image, np.ndarray) else view.image.detach().cpu().numpy()
    return np.asarray(img, np.float64)[..., :3]


def fill_points(points: np.ndarray, views: list) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [M, 3], rgb [M, 3] in [0, 1]): the fill points of the training `views` (module docstring)."""
    # scikit-learn takes about a second to import: loaded only where it is used
    from sklearn.neighbors import NearestNeighbors

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out_xyz, out_rgb = [np.zeros((0, 3))], [np.zeros((0, 3))]
    for v in views:
        c = v.camera
        R, t = c.R.detach().double().cpu().numpy(), c.t.detach().double().cpu().numpy()
        u, w, inside = project(pts, R, t, c)
        if int(inside.sum()) < NEIGHBOURS:
            continue  # no depth to borrow
        occupied_by = np.concatenate([pts] + out_xyz)
        open_px = open_mask(occupied_by, c)
        cu = np.arange(FILL_CELL_PX // 2, c.width, FILL_CELL_PX)
        cv = np.arange(FILL_CELL_PX // 2, c.height, FILL_CELL_PX)
        gv, gu = np.meshgrid(cv, cu, indexing="ij")
        sel = open_px[gv, gu]
        if not sel.any():
            continue
        gu, gv = gu[sel], gv[sel]
        z = (pts[inside] @ R.T + t)[:, 2]
        nn = NearestNeighbors(n_neighbors=NEIGHBOURS).fit(np.stack([u[inside], w[inside]], 1))
        _, idx = nn.kneighbors(np.stack([gu + 0.5, gv + 0.5], 1).astype(np.float64))
        depth = np.median(z[idx], axis=1)
        cam_pts = np.stack([(gu + 0.5 - c.cx) / c.fx * depth, (gv + 0.5 - c.cy) / c.fy * depth, depth], 1)
        out_xyz.append((cam_pts - t) @ R)  # camera -> world: R^T (p - t), as row vectors
        img = _image(v)
        cells = [img[y - FILL_CELL_PX // 2: y + FILL_CELL_PX // 2, x - FILL_CELL_PX // 2: x + FILL_CELL_PX // 2]
                 .reshape(-1, 3).mean(0) for x, y in zip(gu, gv)]
        out_rgb.append(np.clip(np.stack(cells), 0.0, 1.0))
    return np.concatenate(out_xyz), np.concatenate(out_rgb)
