"""A tiny finished run folder for eval tests: a small demo scene + a model built from its SfM points."""

from __future__ import annotations

import json
import os

import numpy as np
import torch

from ctgs.model.surfels import SurfelModel, jagged_offsets

SH_C0 = 0.28209479177387814


def point_model(points: np.ndarray, colors: np.ndarray, n: int = 150, tex: int = 4, seed: int = 0) -> SurfelModel:
    """Surfels on SfM points coloured by them (DC), with small random textures: a crude 'fitted' model."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(len(points), generator=g)[:n]
    means = torch.as_tensor(points, dtype=torch.float32)[idx]
    n = len(means)
    dc = (torch.as_tensor(colors, dtype=torch.float32)[idx] - 0.5) / SH_C0
    sh = torch.zeros(n, 16, 3)
    sh[:, 0] = dc
    res = torch.full((n, 2), tex, dtype=torch.int32)
    return SurfelModel(
        means=means, log_scales=torch.full((n, 2), float(np.log(0.08))),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        opacity_logits=torch.full((n,), 2.0), sh=sh,
        textures_raw=torch.randn(n * tex * tex, 3, generator=g) * 0.5,
        k_min=torch.full((n,), 0.01), t2p_exp=torch.full((n,), 2, dtype=torch.int32),
        tex_res=res, tex_offset=jagged_offsets(res), sh_degree=0,
    )


def make_run(tmp: str, *, views: int = 9, width: int = 40, height: int = 32, n: int = 150) -> str:
    """tmp/scene (demo scene) + tmp/run (model.pt, train_summary.json); returns the run folder."""
    from ctgs.scene import load_scene
    from ctgs.scene.demo import make_demo_scene

    scene_dir = make_demo_scene(os.path.join(tmp, "demo", "scene"), num_views=views, width=width, height=height,
                                points=500, supersample=1)
    scene = load_scene(scene_dir, holdout=8, load_images=False)
    model = point_model(scene.points, scene.point_colors, n=n)
    run = os.path.join(tmp, "run")
    os.makedirs(run, exist_ok=True)
    torch.save({"model": model.state_dict(), "scene_dir": scene_dir, "images": "images", "holdout": 8,
                "iteration": 10, "config": {"backend": "reference"}}, os.path.join(run, "model.pt"))
    with open(os.path.join(run, "train_summary.json"), "w") as f:
        json.dump({"iterations": 10, "train_seconds": 1.5, "backend": "reference", "device": "cpu",
                   "machine": {}, "num_primitives": n, "num_texels": model.num_texels,
                   "num_params": model.num_params(), "final_test_psnr": None}, f)
    return run
