"""`--max-params`: which textures to coarsen first, compared post hoc on a trained model's TRAINING views.

texels.fit_texels coarsens textures (x2, the paper's bicubic round trip, no threshold) in increasing order of
E_d x (image area per texel) until a texel budget fits. This takes a trained run, cuts copies of its model to the
same texel count with three orders, and scores each on the run's training views (never the test views: the order is
a setting of `--max-params` and is chosen here):
- support: E_d x blend weight summed over the pixels of the training view where the surfel weighs most / its texels
  (what the full routine uses);
- E_d alone;
- E_d x 4**t2p_exp (a texel's area in pixels of the closest camera: what the steps without renders use).
Post hoc, with no training after the cut, so every order loses more than a budgeted training run does.

Usage: .venv/bin/python benchmarks/budget_ranking.py RUN_DIR --tag NAME [--fraction 0.333]
(writes benchmarks/results/budget_ranking_<tag>.{json,md})
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from ctgs.io.run_model import load_run  # noqa: E402
from ctgs.metrics.psnr import psnr  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.scene import load_scene  # noqa: E402
from ctgs.train import texels  # noqa: E402
from ctgs.train.adam import SurfelAdam  # noqa: E402
from record import write_record  # noqa: E402 (benchmarks/record.py)


def render_views(model, views):
    inputs = model.render_inputs()
    outs = []
    with torch.no_grad():
        for v in views:
            err = torch.zeros(v.image.shape[:2], dtype=inputs.means.dtype)  # asks for per-primitive stats
            outs.append(render(inputs, v.camera.to("cpu", inputs.means.dtype), backend="cpu",
                               sh_degree=model.sh_degree, error_image=err))
    return outs


def mean_psnr(outs, views) -> float:
    vals = [psnr(o.rgb.clamp(0, 1).float(), torch.as_tensor(v.image, dtype=torch.float32)) for o, v in zip(outs, views)]
    return sum(vals) / len(vals)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--tag", required=True)
    ap.add_argument("--fraction", type=float, default=1 / 3, help="texel budget as a fraction of the model's texels")
    a = ap.parse_args()
    run = load_run(a.run_dir)
    cfg = run.config
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    views = scene.train
    outs = render_views(run.model, views)
    support = torch.stack([o.stats.contrib.double() for o in outs]).amax(0)
    full = {"texels": run.model.num_texels, "train_psnr": mean_psnr(outs, views)}
    # Where the texels are: share by texels per weighted pixel of the surfel's best training view
    n0 = run.model.tex_res.long().prod(1).double()
    ratio = n0 / support.clamp_min(1e-9)
    edges = [0, 0.5, 1, 2, 4, 16, float("inf")]
    full["texel_share_by_texels_per_pixel"] = {f"[{lo}, {hi})": float(n0[(ratio >= lo) & (ratio < hi)].sum() / n0.sum())
                                              for lo, hi in zip(edges[:-1], edges[1:])}
    budget = int(a.fraction * run.model.num_texels)
    rows = []
    for name in ("support", "E_d alone", "closest-camera pixels"):
        m = load_run(a.run_dir).model
        n_tex = m.tex_res.long().prod(1).double()
        # fit_texels ranks by E_d x support / texels; these supports give the other two orders
        sup = {"support": support, "E_d alone": n_tex,
               "closest-camera pixels": n_tex * torch.pow(4.0, m.t2p_exp.double())}[name]
        stats = texels.fit_texels(m, SurfelAdam(m), budget, cfg["max_texture_res"], cfg["texture_alloc"],
                                  cfg["texture_sigma"], support=sup)
        rows.append({"order": name, "texels": stats["budget_texels"], "downscaled": stats["budget_downscaled"],
                     "train_psnr": mean_psnr(render_views(m, views), views)})
    commit = subprocess.run(["git", "-C", os.path.dirname(HERE), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    result = {"command": "benchmarks/budget_ranking.py " + " ".join(sys.argv[1:]), "commit": commit,
              "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
              "machine": f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)",
              "run_dir": os.path.abspath(a.run_dir), "train_views": len(views), "budget_texels": budget,
              "full": full, "rows": rows}
    write_record(f"budget_ranking_{a.tag}", result, markdown)


def markdown(r: dict) -> str:
    lines = [f"# `--max-params`: coarsening order, post hoc on training views ({os.path.basename(r['run_dir'])})", "",
             f"Written by `{r['command']}` on {r['date']}, {r['machine']}, commit {r['commit']}. The model cut to "
             f"{r['budget_texels']} texels by texels.fit_texels with three orders, no training after the cut; mean PSNR "
             f"over the run's {r['train_views']} training views (the test views are not rendered).", "",
             "| order | texels | textures coarsened | training-view PSNR |", "| --- | ---: | ---: | ---: |",
             f"| (the model as trained) | {r['full']['texels']} | 0 | {r['full']['train_psnr']:.2f} |"]
    for row in r["rows"]:
        lines.append(f"| {row['order']} | {row['texels']} | {row['downscaled']} | {row['train_psnr']:.2f} |")
    lines += ["", "Where the model's texels are, by the surfel's texels per pixel of blend weight in the training view "
              "where it weighs most (above 1: more texels than weighted pixels ever show them):", "",
              "| texels per weighted pixel | share of the texels |", "| --- | ---: |"]
    lines += [f"| {k} | {100 * v:.1f}% |" for k, v in r["full"]["texel_share_by_texels_per_pixel"].items()]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
