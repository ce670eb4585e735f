"""A surfel model that IS the demo scene's surfaces (opaque surfels tiling every rectangle, coloured by its texture):
what a perfect training would reach, so `ctgs mesh` can be checked against the exact geometry without training."""

from __future__ import annotations

import math
import os

import numpy as np
import torch

from ctgs.model.surfels import SurfelModel
from ctgs.render.geometry import rotmat_to_quat
from ctgs.scene.demo import demo_surfaces, make_demo_scene

SH_C0 = 0.28209479177387814
DEMO = {"num_views": 12, "width": 64, "height": 48, "points": 200, "supersample": 1}


def demo_scene(root: str) -> str:
    return make_demo_scene(os.path.join(root, "scene"), **DEMO)


def surface_model(spacing: float = 0.06, skip: tuple[str, ...] = ()) -> SurfelModel:
    """Surfels every `spacing` world units on each demo rectangle (not those named in `skip`), sigma = spacing / 2,
    opacity 0.99, the rectangle's colour at each surfel's centre, no textures."""
    means, rots, colours = [], [], []
    for rect in demo_surfaces():
        if rect.id in skip:
            continue
        nu, nv = (max(1, math.ceil(2 * h / spacing)) for h in rect.half)
        lx = (np.arange(nu) + 0.5) / nu * 2 * rect.half[0] - rect.half[0]
        ly = (np.arange(nv) + 0.5) / nv * 2 * rect.half[1] - rect.half[1]
        gx, gy = (a.reshape(-1) for a in np.meshgrid(lx, ly, indexing="ij"))
        means.append(rect.center[None] + gx[:, None] * rect.u[None] + gy[:, None] * rect.v[None])
        rots.append(np.repeat(np.stack([rect.u, rect.v, rect.normal], 1)[None], len(gx), 0))
        colours.append(rect.shade(gx, gy))
    m = torch.tensor(np.concatenate(means), dtype=torch.float32)
    n = len(m)
    sh = torch.tensor((np.concatenate(colours) - 0.5) / SH_C0, dtype=torch.float32)[:, None, :]
    return SurfelModel(means=m, log_scales=torch.full((n, 2), math.log(spacing / 2)),
                       quats=rotmat_to_quat(torch.tensor(np.concatenate(rots), dtype=torch.float32)),
                       opacity_logits=torch.full((n,), math.log(0.99 / 0.01)), sh=sh,
                       textures_raw=torch.zeros(0, 3), k_min=torch.full((n,), 1e-3),
                       t2p_exp=torch.ones(n, dtype=torch.int32), tex_res=torch.zeros(n, 2, dtype=torch.int32),
                       tex_offset=torch.zeros(n, dtype=torch.int64), sh_degree=0, texture_mode="none")


def write_run(run_dir: str, model: SurfelModel, scene_dir: str) -> str:
    os.makedirs(run_dir, exist_ok=True)
    torch.save({"model": model.state_dict(), "scene_dir": scene_dir, "images": "images", "holdout": 8,
                "iteration": 1, "config": {}}, os.path.join(run_dir, "model.pt"))
    return run_dir
