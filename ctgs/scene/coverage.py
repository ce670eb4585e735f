"""Which pixels of a camera the training cameras hold, from cameras and SfM points alone (no model).

A pixel's ray is sampled at `depths` z-depths between the 5th and 95th percentile depth of the SfM points that
project into the camera (uniform in inverse depth) and at infinity (its direction). Classes:

- SEEN: every sample lies inside (in front of) more than FEW training images;
- FEW: every sample inside at least one training image, some inside only 1..FEW;
- PARTLY: some samples inside none;
- UNSEEN: no sample inside any.

Occlusion is ignored, so the classes are upper bounds on what the training images show. Used by
a study of test pixels (benchmarks/results/archive/seen_pixels/herzjesu25_384_4f6edb4.md) and by the virtual-view
coverage term (ctgs.train.components.virtual).
"""

from __future__ import annotations

import numpy as np
import torch

DEPTHS = 16
FEW = 2
SEEN, FEW_CLASS, PARTLY, UNSEEN = 0, 1, 2, 3
CLASSES = ("seen", "few", "partly", "unseen")
MIN_POINTS = 10


@torch.no_grad()
def seen_classes(cam, train_cams, points: np.ndarray, depths: int = DEPTHS) -> torch.Tensor:
    """[H, W] int8 class of every pixel of `cam` (module docstring); ValueError when fewer than MIN_POINTS SfM
    points project into it (no depth range to sample)."""
    h, w = cam.height, cam.width
    vm = cam.viewmat.detach().cpu().double()
    r, t = vm[:3, :3], vm[:3, 3]
    _, _, z, inside = cam.project(torch.from_numpy(np.asarray(points, np.float64)))
    if int(inside.sum()) < MIN_POINTS:
        raise ValueError(f"fewer than {MIN_POINTS} SfM points project into the view: no depth range to sample")
    zs = z[inside]
    lo, hi = float(torch.quantile(zs, 0.05)), float(torch.quantile(zs, 0.95))
    inv = torch.linspace(1.0 / lo, 1.0 / hi, depths, dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                            indexing="ij")
    ray = torch.stack([(xs - cam.cx) / cam.fx, (ys - cam.cy) / cam.fy, torch.ones_like(xs)], -1)
    ray_w = ray.reshape(-1, 3) @ r  # camera -> world directions (R^T d, as row vectors)
    centre = -r.T @ t
    lowest = torch.full((h * w,), len(train_cams), dtype=torch.int32)  # fewest images holding a sample
    highest = torch.zeros(h * w, dtype=torch.int32)
    for k in range(depths + 1):
        hit = torch.zeros(h * w, dtype=torch.int32)
        for tc in train_cams:
            tv = tc.viewmat.detach().cpu().double()
            tr, tt = tv[:3, :3], tv[:3, 3]
            if k < depths:
                q = (centre + ray_w / inv[k]) @ tr.T + tt  # z-depth 1/inv[k] along this camera's axis
            else:
                q = ray_w @ tr.T  # the direction: a point at infinity
            qz = q[:, 2]
            near = tc.near if k < depths else 0.0
            qu = tc.fx * q[:, 0] / qz.clamp_min(1e-12) + tc.cx
            qv = tc.fy * q[:, 1] / qz.clamp_min(1e-12) + tc.cy
            hit += ((qz > near) & (qu >= 0) & (qu < tc.width) & (qv >= 0) & (qv < tc.height)).int()
        lowest = torch.minimum(lowest, hit)
        highest = torch.maximum(highest, hit)
    cls = torch.full((h * w,), PARTLY, dtype=torch.int8)
    cls[lowest > FEW] = SEEN
    cls[(lowest >= 1) & (lowest <= FEW)] = FEW_CLASS
    cls[highest == 0] = UNSEEN
    return cls.reshape(h, w)
