"""Groups of finished validation runs (`--set validation_holdout=K`), side by side and paired by seed.

For tuning on validation views only: each run's validation views (the same split `ctgs train` made: every K-th
training view from the K//2-th) are rendered from its model, and per view the PSNR, the open pixels (rendered
alpha < 0.9: the black background shows) and the alpha of the scene's own primitives (the model with every
primitive farther than 2x the scene's reach dropped, ctgs.train.routines.far.far_mask: below 1 where the scene is
see-through and something far behind fills in) are reported, with the run's validation SSIM, primitives, params and
train time from its train_summary.json. Groups are compared with the first group (the reference) by seed.

With --train-views, also the fit of every training view (PSNR, SSIM, LPIPS; the same black background): how much of
a group's validation difference its training fit shows, i.e. whether it fits its own views better and does not
carry that to new ones.

Also the fit of the path's end cameras: PSNR and open pixels on the first and last training views (by name). On a
one-sided capture (herzjesu25) their outer edges are seen by one or two views, like the extrapolated test view the
validation views cannot stand in for; a run that leaves them open does not fit its own training data there.

Usage: .venv/bin/python benchmarks/validation_runs.py --group NAME=RUN_DIR[,RUN_DIR...] [--group ...] --out NAME
Writes benchmarks/results/validation_runs/<NAME>_<commit>.md. The first group is the reference; runs pair by their seed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
import tomllib
from dataclasses import replace
from types import SimpleNamespace

import torch

from ctgs.evaluation.report import OPEN_ALPHA  # rendered alpha below it: the background shows
from ctgs.metrics.lpips import load_lpips, lpips_hwc
from ctgs.metrics.ssim import ssim as ssim_of
from ctgs.render.api import render
from ctgs.runs import load_run, training_scene
from ctgs.train.components.shell import scene_sphere
from ctgs.train.routines.far import far_mask

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paired_stats import group_specs  # noqa: E402
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def psnr(se: torch.Tensor) -> float:
    return float(-10 * torch.log10(se.mean()))


def fit(inputs, view, sh_degree: int, net=None, with_ssim: bool = False) -> dict:
    """A view's PSNR and its open pixels (rendered alpha < OPEN_ALPHA); with an LPIPS net also its LPIPS; with_ssim
    its SSIM."""
    out = render(inputs, view.camera, sh_degree=sh_degree)
    rgb = out.rgb.clamp(0, 1)
    gt = torch.from_numpy(view.image)
    se = ((rgb - gt) ** 2).mean(-1)
    rec = {"name": view.name, "psnr": psnr(se), "open": float((out.alpha < OPEN_ALPHA).float().mean())}
    if net is not None:
        rec["lpips"] = lpips_hwc(net, rgb, view.image)
    if with_ssim:
        rec["ssim"] = float(ssim_of(rgb, gt))
    return rec


def by_view_table(title: str, groups: list, key: str, columns: list, extra=None) -> list[str]:
    """Markdown lines: one row per group, for each view of runs' `key` list the `columns` (header suffix, format of one
    view's record) joined over the group's runs in seed order; `extra` = (header, format of a run), a last column."""
    names = [v["name"] for v in groups[0][1][0][key]]
    head = [f"{n} {h}" for n in names for h, _ in columns] + ([extra[0]] if extra else [])
    lines = ["", title, "", "| group | " + " | ".join(head) + " |", "| --- | " + " | ".join("---:" for _ in head) + " |"]
    for name, runs in groups:
        runs = sorted(runs, key=lambda r: r["seed"])
        cells = [" / ".join(f(r[key][i]) for r in runs) for i in range(len(names)) for _, f in columns]
        if extra:
            cells.append(" / ".join(extra[1](r) for r in runs))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def load_validation_run(run_dir: str):
    """(RunModel, scene) of a tuning-mode run (`--set validation_holdout=K`): scene.test are its validation views,
    taken from the training set, never the protocol's test views. Exits with a message for any other run."""
    with open(os.path.join(run_dir, "config.toml"), "rb") as fh:
        holdout = int(tomllib.load(fh).get("validation_holdout", 0))
    if holdout <= 0:
        raise SystemExit(f"{run_dir}: not a validation run (validation_holdout = 0); train with "
                         "--set validation_holdout=8")
    run = load_run(run_dir)
    background = [float(c) for c in run.config.get("background") or (0.0, 0.0, 0.0)]  # the run's (ctgs train)
    scene = training_scene(SimpleNamespace(scene_dir=run.scene_dir, images=run.images, holdout=run.holdout,
                                           background=background, validation_holdout=holdout))
    return run, scene


def measure(run_dir: str, net=None, train_views: bool = False) -> dict:
    run, scene = load_validation_run(run_dir)
    cfg = run.config
    with open(os.path.join(run_dir, "train_summary.json")) as fh:
        summary = json.load(fh)
    model = run.model
    centre, reach = scene_sphere(scene.points, scene.train)
    far = far_mask(model.means, centre, reach)
    inputs = model.render_inputs()
    opac = inputs.opacities.detach().clone()
    opac[far] = 0
    scene_only = replace(inputs, opacities=opac)
    views = []
    with torch.no_grad():
        for v in scene.test:
            a = render(scene_only, v.camera, sh_degree=model.sh_degree).alpha
            views.append({**fit(inputs, v, model.sh_degree, net), "scene_alpha": float(a.mean()),
                          "scene_below": float((a < OPEN_ALPHA).float().mean())})
        ends = [fit(inputs, v, model.sh_degree) for v in (scene.train[0], scene.train[-1])]
        train = [fit(inputs, v, model.sh_degree, net, with_ssim=True) for v in scene.train] if train_views else None
    return {"run": run_dir, "train": train, "seed": int(cfg.get("seed", 0)), "views": views, "ends": ends,
            "psnr": statistics.fmean(v["psnr"] for v in views), "ssim": summary["final_test_ssim"],
            "lpips": statistics.fmean(v["lpips"] for v in views) if net is not None else None,
            "summary_psnr": summary["final_test_psnr"], "primitives": summary["num_primitives"],
            "params": summary["num_params"], "far": int(far.sum()), "train_s": summary["train_seconds"],
            "iterations": summary["iterations"]}


def train_fit_table(groups: list, ref_name: str, ref_by_seed: dict, with_lpips: bool) -> list[str]:
    """Markdown lines: each group's mean fit of its training views next to its validation figures, and the
    differences to the reference by seed (train against validation)."""
    def mean(r, key, which):
        return statistics.fmean(v[key] for v in r[which]) if which == "train" else r[key]

    lines = ["", "## Training views (fit) against validation views (means over the views, then over seeds)", "",
             f"{len(groups[0][1][0]['train'])} training views. Differences pair runs by seed with **{ref_name}**.", "",
             "| group | train PSNR | val PSNR | train PSNR vs ref | val PSNR vs ref | train SSIM | train LPIPS | "
             "val LPIPS | train LPIPS vs ref | val LPIPS vs ref |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, runs in groups:
        def avg(key, which):
            return statistics.fmean(mean(r, key, which) for r in runs)

        def diff(key, which):
            d = [mean(r, key, which) - mean(ref_by_seed[r["seed"]], key, which) for r in runs
                 if r["seed"] in ref_by_seed]
            return "" if name == ref_name or not d else f"{statistics.fmean(d):+.3f}"
        lp = (f"{avg('lpips', 'train'):.4f} | {avg('lpips', 'val'):.4f} | {diff('lpips', 'train')} | "
              f"{diff('lpips', 'val')}" if with_lpips else "n/a | n/a | | ")
        lines.append(f"| {name} | {avg('psnr', 'train'):.2f} | {avg('psnr', 'val'):.2f} | {diff('psnr', 'train')} | "
                     f"{diff('psnr', 'val')} | {avg('ssim', 'train'):.4f} | {lp} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--group", action="append", required=True, help="NAME=RUN_DIR[,RUN_DIR...]")
    ap.add_argument("--out", required=True)
    ap.add_argument("--train-views", action="store_true", help="also PSNR / SSIM / LPIPS on every training view")
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, status = load_lpips()  # LPIPS of the validation views where the VGG weights are present (make lpips-weights)
    groups = [(name, [measure(d, net, args.train_views) for d in dirs]) for name, dirs in group_specs(args.group, "validation_runs.py")]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    ref_name, ref = groups[0]
    ref_by_seed = {r["seed"]: r for r in ref}
    lines = [f"# Validation runs side by side ({args.out})", "",
             f"Written by `benchmarks/validation_runs.py {' '.join(sys.argv[1:])}` on {time.strftime('%Y-%m-%d')}, "
             f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus), commit {commit}. Validation views "
             "only (the protocol's test views were never trained on or rendered). PSNR = mean over the validation "
             f"views of each view's PSNR (CPU backend, black background); open = rendered alpha < {OPEN_ALPHA}; scene "
             "alpha = alpha without the primitives beyond 2x the scene's reach (`far`); LPIPS (VGG, [0, 1] inputs) "
             f"{'from ' + status.detail if net is not None else status.detail}. Reference group: "
             f"**{ref_name}**; differences pair runs by seed.", "",
             "## Groups", "",
             "| group | runs | val PSNR (by seed) | mean | vs reference | val SSIM | val LPIPS | primitives | params | train s |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: |"]
    for name, runs in groups:
        runs = sorted(runs, key=lambda r: r["seed"])
        mean = statistics.fmean(r["psnr"] for r in runs)
        diffs = [r["psnr"] - ref_by_seed[r["seed"]]["psnr"] for r in runs if r["seed"] in ref_by_seed]
        vs = "" if name == ref_name or not diffs else f"{statistics.fmean(diffs):+.2f} ({', '.join(f'{d:+.2f}' for d in diffs)})"
        by_seed = " / ".join("%.2f" % r["psnr"] for r in runs)
        params = " / ".join("%.2fM" % (r["params"] / 1e6) for r in runs)
        lines.append(f"| {name} | {len(runs)} | {by_seed} | {mean:.2f} | {vs} | "
                     f"{statistics.fmean(r['ssim'] for r in runs):.4f} | "
                     + (f"{statistics.fmean(r['lpips'] for r in runs):.4f} | " if net is not None else "n/a | ") +
                     f"{statistics.fmean(r['primitives'] for r in runs) / 1e3:.1f}k | "
                     f"{params} | "
                     f"{statistics.fmean(r['train_s'] for r in runs):.0f} |")
    psnr_open = [("PSNR", lambda v: f"{v['psnr']:.2f}"), ("open", lambda v: f"{100 * v['open']:.2f}%")]
    lines += by_view_table("## Per view (seed order)", groups, "views",
                           psnr_open + [("scene alpha (< 0.9)",
                                         lambda v: f"{v['scene_alpha']:.3f} ({100 * v['scene_below']:.1f}%)")],
                           ("far", lambda r: str(r["far"])))
    lines += by_view_table("## Path-end training views (training fit where the fewest views overlap; seed order)",
                           groups, "ends", psnr_open)
    if args.train_views:
        lines += train_fit_table(groups, ref_name, ref_by_seed, net is not None)
    worst = max(abs(r["psnr"] - r["summary_psnr"]) for _, runs in groups for r in runs)
    lines += ["", f"Check: these PSNR means differ from the runs' own validation PSNR (train_summary.json) by at most "
              f"{worst:.3f} dB.", "", "Runs: " + "; ".join(f"{name}: " + ", ".join(r["run"] for r in runs)
                                                          for name, runs in groups)]
    out = record.stem("validation_runs", args.out) + ".md"
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
