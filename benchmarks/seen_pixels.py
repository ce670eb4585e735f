"""Test-view pixels by how many training cameras saw them, and how each run does on each kind.

On a one-sided camera path the protocol's first test view is an extrapolation: part of it may lie outside every
training camera's frustum, and more of it inside only one or two (benchmarks/results/train_findings.md).
This splits every test pixel by a rule that depends only on the cameras and the SfM points, not on any model
(ctgs.scene.coverage):

- the pixel's ray is sampled at DEPTHS z-depths between the 5th and 95th percentile depth of the SfM points that
  project into the test view (uniform in inverse depth) and at infinity (its direction);
- **seen**: at every sample the point lies inside (in front of) at least FEW + 1 = 3 training images;
- **few**: at every sample inside at least one training image, at some inside only one or two;
- **partly**: inside some training image at some samples, at others inside none;
- **unseen**: at no sample inside any training image.
Occlusion is ignored, so the classes are upper bounds on what the training images show.

For each run and test view: the share of pixels in each class, the open pixels (rendered alpha < 0.9: the
protocol's black background shows) in each, the share of the view's squared error in each, and PSNR over all
pixels, over the seen and few pixels together, and over the seen pixels alone. Groups of runs
(one per seed, in the same seed order in every group) are compared with the first group, paired by seed. A
breakdown of finished runs on test views, not a measure to choose settings by.

Usage: .venv/bin/python benchmarks/seen_pixels.py --group NAME=RUN[,RUN...] [--group ...] --out NAME
Writes benchmarks/results/seen_pixels_<NAME>.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import numpy as np
import torch

from ctgs.io.run_model import load_run
from ctgs.metrics.report import OPEN_ALPHA  # rendered alpha below it: the background shows
from ctgs.render.api import render
from ctgs.scene import load_scene
from ctgs.scene.coverage import CLASSES, DEPTHS, FEW, FEW_CLASS, seen_classes

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paired_stats import group_specs  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def psnr_of(se: torch.Tensor) -> float:
    return float(-10 * torch.log10(se.mean())) if se.numel() else float("nan")


def fmt_pct(x: float) -> str:
    return "" if np.isnan(x) else f"{100 * x:.1f}%"


def paired(diffs: list[float]) -> str:
    d = np.asarray(diffs, np.float64)
    if len(d) < 2:
        return f"{d.mean():+.2f}"
    return f"{d.mean():+.2f} ({' / '.join(f'{x:+.2f}' for x in d)})"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--group", action="append", required=True, help="NAME=RUN[,RUN...] (one run per seed)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    groups = group_specs(args.group, "seen_pixels.py")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()

    classes_cache: dict = {}
    records = {}  # group -> list (per run) of {view: {...}}
    scene_key = None
    for name, runs in groups:
        records[name] = []
        for rd in runs:
            run = load_run(rd)
            scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
            key = (os.path.realpath(run.scene_dir), run.images, run.holdout)
            if scene_key is None:
                scene_key = key
            elif key != scene_key:
                raise SystemExit(f"error: {rd} was trained on {key}, the first run on {scene_key}: compare runs of "
                                 "one scene, image folder and split")
            inputs = run.model.render_inputs()
            per_view = {}
            for view in scene.test:
                if view.name not in classes_cache:
                    classes_cache[view.name] = seen_classes(view.camera, [tv.camera for tv in scene.train],
                                                            scene.points)
                cls = classes_cache[view.name]
                with torch.no_grad():
                    out = render(inputs, view.camera, sh_degree=run.model.sh_degree)
                gt = torch.from_numpy(view.image)
                se = ((out.rgb.clamp(0, 1) - gt) ** 2).mean(-1)
                opened = out.alpha < OPEN_ALPHA
                rec = {"psnr": psnr_of(se), "seen_or_few_psnr": psnr_of(se[cls <= FEW_CLASS]), "share_of_error": {}}
                for i, c in enumerate(CLASSES):
                    m = cls == i
                    rec[f"{c}_pixels"] = float(m.float().mean())
                    rec[f"{c}_open"] = float(opened[m].float().mean()) if bool(m.any()) else float("nan")
                    rec[f"{c}_psnr"] = psnr_of(se[m])
                    rec["share_of_error"][c] = float(se[m].sum() / se.sum())
                per_view[view.name] = rec
            records[name].append({"run": rd, "views": per_view})

    views = sorted(classes_cache)
    ref_name = groups[0][0]
    lines = [f"# Seen and unseen test pixels ({args.out})", "",
             f"Written by `benchmarks/seen_pixels.py {' '.join('--group ' + g for g in args.group)} --out "
             f"{args.out}` on {time.strftime('%Y-%m-%d')}, {platform.node()} ({platform.machine()}, "
             f"{os.cpu_count()} cpus), commit {commit}. Renders: CPU backend, black background.",
             "",
             f"Each test pixel's ray is sampled at {DEPTHS} depths between the 5th and 95th percentile depth of the "
             "SfM points in that view (uniform in inverse depth) and at infinity. **seen**: every sample lies inside "
             f"at least {FEW + 1} training images; **few**: every sample inside at least one, some inside only "
             f"1-{FEW}; **partly**: some samples inside none; **unseen**: no sample inside any (cameras and SfM "
             f"points only, no model; occlusion ignored). open = rendered alpha < {OPEN_ALPHA}. Reference group: "
             f"**{ref_name}**; differences pair runs by seed. A breakdown of finished runs on test views: nothing is "
             "chosen from it.",
             "", "## Pixel classes per test view", "", "| view | " + " | ".join(CLASSES) + " |",
             "| --- |" + " ---: |" * len(CLASSES)]
    first = records[ref_name][0]["views"]
    for vname in views:
        r = first[vname]
        lines.append(f"| {vname} | " + " | ".join(f"{100 * r[f'{c}_pixels']:.1f}%" for c in CLASSES) + " |")

    lines += ["", "## Per group and view (mean over runs; PSNR on seen + few by run in seed order)", "",
              "| group | view | PSNR | PSNR on seen + few (by run) | " + " | ".join(f"open in {c}" for c in CLASSES)
              + " | error share " + " / ".join(CLASSES) + " |", "| --- | --- | ---: | --- |" + " ---: |" * len(CLASSES)
              + " --- |"]
    for name, _ in groups:
        for vname in views:
            recs = [r["views"][vname] for r in records[name]]
            mean = lambda key: float(np.mean([x[key] for x in recs]))  # noqa: E731 (nan: class absent)
            seen_by_run = " / ".join(f"{x['seen_or_few_psnr']:.2f}" for x in recs)
            share = " / ".join(f"{100 * np.mean([x['share_of_error'][c] for x in recs]):.0f}%" for c in CLASSES)
            opens = " | ".join(fmt_pct(mean(f"{c}_open")) for c in CLASSES)
            lines.append(f"| {name} | {vname} | {mean('psnr'):.2f} | {seen_by_run} | {opens} | {share} |")

    lines += ["", "## Paired against the reference (mean over test views of each run, then by seed)", "",
              "| group | test PSNR | vs reference | PSNR on seen + few | vs reference | PSNR on seen | vs reference |",
              "| --- | ---: | --- | ---: | --- | ---: | --- |"]
    summary = {}
    for name, _ in groups:
        allp = [float(np.mean([r["views"][v]["psnr"] for v in views])) for r in records[name]]
        summary[name] = {"test_psnr": allp}
        for key in ("seen_or_few_psnr", "seen_psnr"):
            summary[name][key] = [float(np.mean([r["views"][v][key] for v in views])) for r in records[name]]
    for name, _ in groups:
        s, ref = summary[name], summary[ref_name]
        n = min(len(s["test_psnr"]), len(ref["test_psnr"]))
        cells = []
        for key in ("test_psnr", "seen_or_few_psnr", "seen_psnr"):
            diff = "" if name == ref_name else paired([s[key][i] - ref[key][i] for i in range(n)])
            cells.append(f"{np.mean(s[key]):.2f} | {diff}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Runs: " + "; ".join(f"{name}: {', '.join(runs)}" for name, runs in groups), ""]

    out = os.path.join(ROOT, "benchmarks", "results", f"seen_pixels_{args.out}")
    with open(out + ".md.tmp", "w") as f:
        f.write("\n".join(lines))
    os.replace(out + ".md.tmp", out + ".md")
    with open(out + ".json.tmp", "w") as f:
        json.dump({"commit": commit, "groups": {n: records[n] for n, _ in groups}, "summary": summary}, f, indent=1)
    os.replace(out + ".json.tmp", out + ".json")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
