"""Which primitives of a finished run sit far from the rest, and what they are doing there.

For each run: the primitives whose centre is more than --factor times the median (Chebyshev) distance from the
median centre, listed farthest first with their opacity, scales, texture size, the number of training cameras whose
image their centre projects into, the median depth there, and how many training-view pixels they cover (a pixel
counts when the primitive's blending weight there is >= 1/255 in a render of that view).

Why: a few primitives of some runs end up hundreds to thousands of scene units out (session 10's `make demo` model:
2400 units, which broke single-range q16 positions in `ctgs compress`). Are they stray, invisible leftovers (then a
prune is free) or do they draw something (then they are part of the model)?

Usage: .venv/bin/python benchmarks/far_primitives.py RUN [RUN ...] [--factor 20] [--out NAME]
Writes benchmarks/results/far_primitives_<NAME>.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import subprocess
import time

import numpy as np
import torch

from ctgs.io.run_model import load_run
from ctgs.render.api import render
from ctgs.scene import load_scene
from ctgs.train.shell import project  # the same in-image test as the far shell's

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def effects(model, views, rows: list[int]) -> tuple[list[float], list[float]]:
    """Per primitive in `rows`: its blending contribution summed over the training views (the renderer's per-primitive
    `contrib` statistic, in pixels) and the change of the mean training-view PSNR when it alone is removed."""
    from ctgs.metrics.psnr import psnr

    inp = model.render_inputs()
    inp = type(inp)(**{k: (v.detach() if torch.is_tensor(v) else v) for k, v in vars(inp).items()})
    deg = model.sh_degree
    gts = [torch.from_numpy(v.image) for v in views]

    def mean_psnr(inputs) -> float:
        return float(np.mean([float(psnr(render(inputs, v.camera, sh_degree=deg).rgb.clamp(0, 1), g))
                              for v, g in zip(views, gts)]))

    with torch.no_grad():
        contrib = sum(render(inp, v.camera, sh_degree=deg, error_image=torch.zeros(v.camera.height, v.camera.width))
                      .stats.contrib.float() for v in views)
        base = mean_psnr(inp)
        loss = []
        for i in rows:
            op = inp.opacities.clone()
            op[i] = 0.0
            loss.append(base - mean_psnr(dataclasses.replace(inp, opacities=op)))
    return [float(contrib[i]) for i in rows], loss


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--factor", type=float, default=20.0)
    ap.add_argument("--top", type=int, default=8)
    ap.add_argument("--out", default=platform.node())
    args = ap.parse_args()
    torch.set_num_threads(1)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    lines = [f"# Far primitives of finished runs ({args.out})", "",
             f"Written by `benchmarks/far_primitives.py {' '.join(os.path.relpath(r) if r.startswith(ROOT) else r for r in args.runs)} "
             f"--factor {args.factor:g}` on {time.strftime('%Y-%m-%d')}, {platform.node()} ({platform.machine()}, "
             f"{os.cpu_count()} cpus), commit {commit}. Far = centre more than {args.factor:g}x the median distance "
             "from the median centre (Chebyshev). frusta = training cameras whose image the centre projects into; "
             "contrib = the renderer's per-primitive contribution summed over the training views (it can cover views its "
             "centre is outside of); train dB lost = mean training-view PSNR with it minus without it (> 0: it draws "
             "something the training views want).", ""]
    for rd in args.runs:
        run = load_run(rd)
        m = run.model
        sc = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
        x = m.means.detach().double()
        d = (x - x.median(0).values).abs().amax(1)
        med = float(d.median())
        far = torch.nonzero(d > args.factor * med).flatten()
        far = far[torch.argsort(-d[far])][: args.top].tolist()
        op = torch.sigmoid(m.opacity_logits.detach()).double()
        scales = m.log_scales.detach().double().exp()
        pix, drop = effects(m, sc.train, far)
        lines += [f"## `{rd}`", "",
                  f"{m.num_primitives:,} primitives; median distance {med:.3g}; {int((d > args.factor * med).sum())} "
                  f"beyond {args.factor:g}x (farthest {float(d.max()):.4g}, {float(d.max()) / med:.0f}x).", "",
                  "| primitive | distance (x median) | opacity | scales | texture | frusta | median depth | contrib | train dB lost without it |",
                  "| ---: | --- | ---: | --- | --- | ---: | ---: | ---: | ---: |"]
        xs = x[far].numpy()
        depth = np.full((len(sc.train), len(far)), np.nan)  # depth in each training camera whose image holds the centre
        for j, v in enumerate(sc.train):
            c = v.camera
            R, t = c.R.double().numpy(), c.t.double().numpy()
            inside = project(xs, R, t, c)[2]
            depth[j, inside] = (xs @ R.T + t)[inside, 2]
        for k, (i, p, dl) in enumerate(zip(far, pix, drop)):
            seen = depth[~np.isnan(depth[:, k]), k]
            tex = tuple(m.tex_res[i].tolist())
            lines.append(f"| {i} | {float(d[i]):.4g} ({float(d[i]) / med:.0f}x) | {float(op[i]):.3f} | "
                         f"{float(scales[i, 0]):.3g} x {float(scales[i, 1]):.3g} | "
                         f"{'none' if tex == (0, 0) else f'{tex[0]}x{tex[1]}'} | {len(seen)} | "
                         f"{f'{np.median(seen):.3g}' if len(seen) else '-'} | {p:,.0f} | {dl:+.3f} |")
        lines.append("")
    out = os.path.join(ROOT, "benchmarks", "results", f"far_primitives_{args.out}.md")
    with open(out, "w") as fh:
        fh.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
