"""How much of a run's held-out error is exposure: PSNR before and after one oracle gain per view.

For each validation run (`--set validation_holdout=K`: its held-out views are training-set views, never test views),
on its validation views: PSNR of the render as it is, the least-squares gain g = <render, photo> / <render, render>
over the view (one for all channels, and one per channel), and PSNR of g x render (clipped to [0, 1]). The oracle
gain is not available to any method (a new view's exposure is unknown): it bounds what exposure mismatch costs, and
shows whether the photos of a capture share an exposure. On the training views only the range of g is reported
(how far the model drew each training photo's own brightness).

Usage: .venv/bin/python benchmarks/exposure_gap.py --work DIR --prefixes old exp --presets balanced \\
         --seeds 0 1 2 3 --out NAME [--note TEXT]
Runs are DIR/{prefix}_{preset}_s{seed}. Writes benchmarks/results/exposure_gap_NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np
import torch

from ctgs.render.api import render

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from record import write_record  # noqa: E402
from validation_runs import load_validation_run  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(max(float(((a - b) ** 2).mean()), 1e-12)))


@torch.no_grad()
def view_gap(inputs, view, sh_degree: int) -> dict:
    r = render(inputs, view.camera, sh_degree=sh_degree).rgb.clamp(0, 1).numpy().reshape(-1, 3).astype(np.float64)
    g = np.asarray(view.image, dtype=np.float64).reshape(-1, 3)
    one = float((r * g).sum() / max((r * r).sum(), 1e-12))
    per = (r * g).sum(0) / np.maximum((r * r).sum(0), 1e-12)
    return {"view": view.name, "psnr": psnr(r, g), "gain": one, "gain_rgb": [float(x) for x in per],
            "psnr_gain": psnr(np.clip(r * one, 0, 1), g), "psnr_gain_rgb": psnr(np.clip(r * per, 0, 1), g)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True)
    ap.add_argument("--prefixes", nargs="+", required=True)
    ap.add_argument("--presets", nargs="+", required=True)
    ap.add_argument("--seeds", nargs="+", type=int, required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--note", default="")
    args = ap.parse_args()
    torch.set_num_threads(1)
    runs = []
    for preset in args.presets:
        for seed in args.seeds:
            for prefix in args.prefixes:
                rd = os.path.join(args.work, f"{prefix}_{preset}_s{seed}")
                if not os.path.isfile(os.path.join(rd, "model.pt")):
                    continue
                run, scene = load_validation_run(rd)
                cfg = run.config
                inputs = run.model.render_inputs()
                deg = run.model.sh_degree
                val = [view_gap(inputs, v, deg) for v in scene.test]
                train_gains = [view_gap(inputs, v, deg)["gain"] for v in scene.train]
                runs.append({"preset": preset, "seed": seed, "run": prefix,
                             "exposure_comp": bool(cfg.get("exposure_comp", False)), "validation": val,
                             "train_gain_min": min(train_gains), "train_gain_max": max(train_gains)})
    result = {"command": "benchmarks/exposure_gap.py " + " ".join(sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M"),
              "machine": f"{platform.node() or 'machine'} ({platform.machine()}, {os.cpu_count()} cpus)",
              "note": args.note, "runs": runs}

    def markdown(res: dict) -> str:
        lines = [f"# Exposure gap on validation views ({args.out})", "",
                 f"Command: `{res['command']}` on {res['date']}, {res['machine']}. Per validation view: PSNR of the "
                 "render, the least-squares gain g (photo ~ g x render; one for all channels, and the per-channel "
                 "gains), and PSNR after it (an oracle: no method knows a new view's exposure). Training views: the "
                 "range of the same gain. The test views are not rendered.", ""]
        if res["note"]:
            lines += [res["note"], ""]
        lines += ["| run | seed | view | PSNR | gain | gains R/G/B | PSNR x gain | PSNR x gains | training-view gains |",
                  "| --- | ---: | --- | ---: | ---: | --- | ---: | ---: | --- |"]
        for r in res["runs"]:
            for i, v in enumerate(r["validation"]):
                tg = f"{r['train_gain_min']:.3f}-{r['train_gain_max']:.3f}" if i == 0 else ""
                lines.append(f"| {r['run']} | {r['seed']} | {v['view']} | {v['psnr']:.2f} | {v['gain']:.3f} | "
                             + "/".join(f"{x:.3f}" for x in v["gain_rgb"])
                             + f" | {v['psnr_gain']:.2f} | {v['psnr_gain_rgb']:.2f} | {tg} |")
        lines += ["", "| run | seeds | validation PSNR (mean) | x one oracle gain | x per-channel gains | "
                  "training-view gains |", "| --- | ---: | ---: | ---: | ---: | --- |"]
        for prefix in args.prefixes:
            sel = [r for r in res["runs"] if r["run"] == prefix]
            if not sel:
                continue

            def mean(key, rows=sel):
                return float(np.mean([np.mean([v[key] for v in r["validation"]]) for r in rows]))

            lines.append(f"| {prefix} | {len(sel)} | {mean('psnr'):.2f} | {mean('psnr_gain'):.2f} | "
                         f"{mean('psnr_gain_rgb'):.2f} | {min(r['train_gain_min'] for r in sel):.3f}-"
                         f"{max(r['train_gain_max'] for r in sel):.3f} |")
        return "\n".join(lines) + "\n"

    write_record(f"exposure_gap_{args.out}", result, markdown)


if __name__ == "__main__":
    main()
