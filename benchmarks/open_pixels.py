"""Where a finished run leaves the background showing, per test view, and how much of the error that is.

For each run and each test view: the fraction of pixels no primitive covers (rendered alpha < 0.9, so the
protocol's black background shows through), the share of the view's squared error in those pixels, the view's PSNR
and its PSNR over the covered pixels only. With --masks DIR, one PNG per run and view: ground truth | render | open
pixels in white.

Why: at 384x256 the content-aware runs lose to 2dgs at equal time on herzjesu25 (equal_time_384_3seeds.md) while
matching it between cameras on covered pixels; this measures whether open pixels (sky the model never covered,
parts of the scene no training view saw) are the difference. Diagnosis on test views: nothing is chosen from it.

Usage: .venv/bin/python benchmarks/open_pixels.py LABEL=RUN [LABEL=RUN ...] --out NAME [--masks DIR]
Writes benchmarks/results/open_pixels_<NAME>.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import time

import numpy as np
import torch

from ctgs.io.run_model import load_run
from ctgs.metrics.report import OPEN_ALPHA  # rendered alpha below it: the background shows
from ctgs.render.api import render
from ctgs.scene import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def psnr_of(se: torch.Tensor) -> float:
    return float(-10 * torch.log10(se.mean())) if se.numel() else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--out", required=True)
    ap.add_argument("--masks", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    lines = [f"# Open pixels per test view ({args.out})", "",
             f"Written by `benchmarks/open_pixels.py {' '.join(args.runs)} --out {args.out}` on "
             f"{time.strftime('%Y-%m-%d')}, {platform.node()} ({platform.machine()}, {os.cpu_count()} cpus), commit "
             f"{commit}. open = rendered alpha < {OPEN_ALPHA} (the black background shows); share = that part of the "
             "view's squared error; covered PSNR = PSNR over the other pixels. Renders: CPU backend, black background.",
             "", "| run | view | PSNR | open pixels | share of the error | covered PSNR |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    for spec in args.runs:
        label, rd = spec.split("=", 1)
        run = load_run(rd)
        model = run.model
        scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
        inputs = model.render_inputs()
        for v in scene.test:
            with torch.no_grad():
                out = render(inputs, v.camera, sh_degree=model.sh_degree)
            gt = torch.from_numpy(v.image)
            rgb = out.rgb.clamp(0, 1)
            se = ((rgb - gt) ** 2).mean(-1)
            open_px = out.alpha < OPEN_ALPHA
            share = float(se[open_px].sum() / se.sum().clamp_min(1e-20))
            lines.append(f"| {label} | {v.name} | {psnr_of(se):.2f} | {100 * float(open_px.float().mean()):.1f}% | "
                         f"{100 * share:.0f}% | {psnr_of(se[~open_px]):.2f} |")
            if args.masks:
                import cv2

                os.makedirs(args.masks, exist_ok=True)
                to8 = lambda a: (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
                mask = np.repeat(open_px.numpy()[..., None].astype(np.float32), 3, 2)
                strip = np.concatenate([to8(v.image), to8(rgb.numpy()), to8(mask)], 1)
                name = f"{label}_{os.path.splitext(v.name)[0]}.png"
                cv2.imwrite(os.path.join(args.masks, name), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    out = os.path.join(ROOT, "benchmarks", "results", f"open_pixels_{args.out}.md")
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
