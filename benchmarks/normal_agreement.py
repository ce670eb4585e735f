"""How well a finished run's surfels agree with the depth they draw: 2DGS's depth-normal consistency, measured.

For each run (a validation run: `--set validation_holdout=K`, so its held-out views are not test views), on its
training views and on its validation views: the mean of 2DGS's term (ctgs.train.normal.consistency, the value
`lambda_normal` weights), and the alpha-weighted mean angle between the surfels' blended normal and the normal of the
surface the expected depth describes (pixels with alpha >= 0.5 and a defined depth normal). Used to check that a run
trained with `lambda_normal > 0` did align its surfels with its depth, next to what that did to validation PSNR.

Usage: .venv/bin/python benchmarks/normal_agreement.py --work DIR --prefixes new old --presets balanced \\
         --seeds 0 1 2 3 --out NAME [--note TEXT]
Runs are DIR/{prefix}_{preset}_s{seed}. Writes benchmarks/results/normal_agreement_NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time

import torch

from ctgs.train.normal import blended_normal, consistency, depth_normals, render_normals

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from record import write_record  # noqa: E402
from validation_runs import load_validation_run  # noqa: E402


@torch.no_grad()
def agreement(inputs, views) -> dict:
    """{"term": mean consistency over the views, "angle_deg": alpha-weighted mean angle (alpha >= 0.5)}."""
    terms, num, den = [], 0.0, 0.0
    for v in views:
        out = render_normals(inputs, v.camera)
        terms.append(float(consistency(out, v.camera)))
        n_r = blended_normal(out)
        n_d = depth_normals(out.depth, out.alpha, v.camera)
        ok = (out.alpha >= 0.5) & (n_d.norm(dim=-1) > 0)
        cos = ((n_r / n_r.norm(dim=-1, keepdim=True).clamp_min(1e-12)) * n_d).sum(-1).clamp(-1, 1)
        w = out.alpha * ok
        num += float((torch.rad2deg(torch.acos(cos)) * w).sum())
        den += float(w.sum())
    return {"term": sum(terms) / len(terms), "angle_deg": num / den if den > 0 else math.nan}


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
    rows = []
    for preset in args.presets:
        for seed in args.seeds:
            for prefix in args.prefixes:
                rd = os.path.join(args.work, f"{prefix}_{preset}_s{seed}")
                if not os.path.isfile(os.path.join(rd, "model.pt")):
                    continue
                run, scene = load_validation_run(rd)
                cfg = run.config
                run.model.sh_degree = 0
                inputs = run.model.render_inputs()
                tr, va = agreement(inputs, scene.train), agreement(inputs, scene.test)
                rows.append({"preset": preset, "seed": seed, "run": prefix,
                             "lambda_normal": float(cfg.get("lambda_normal", 0.0)),
                             "val_psnr": (run.summary or {}).get("final_test_psnr"),
                             "train_term": tr["term"], "train_angle_deg": tr["angle_deg"],
                             "val_term": va["term"], "val_angle_deg": va["angle_deg"]})
    result = {"command": "benchmarks/normal_agreement.py " + " ".join(sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M"),
              "machine": f"{platform.node() or 'machine'} ({platform.machine()}, {os.cpu_count()} cpus)",
              "note": args.note, "rows": rows}
    lines = [f"# Depth-normal agreement of finished runs ({args.out})", "",
             f"Command: `{result['command']}` on {result['date']}, {result['machine']}. Per run, on its training "
             "views and on its validation views: 2DGS's depth-normal term (what `lambda_normal` weights: mean over "
             "pixels of 1 - alpha N_r . N_d; 1 where nothing is drawn) and the alpha-weighted mean angle between the "
             "blended surfel normal and the depth's normal (pixels with alpha >= 0.5). Validation PSNR: the run's own "
             "final evaluation (train_summary.json).", ""]
    if args.note:
        lines += [args.note, ""]
    lines += ["| preset | seed | run | lambda_normal | validation PSNR | train term | train angle | validation term | "
              "validation angle |", "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        vp = "-" if r["val_psnr"] is None else f"{r['val_psnr']:.2f}"
        lines.append(f"| {r['preset']} | {r['seed']} | {r['run']} | {r['lambda_normal']:g} | {vp} | "
                     f"{r['train_term']:.4f} | {r['train_angle_deg']:.1f} deg | {r['val_term']:.4f} | "
                     f"{r['val_angle_deg']:.1f} deg |")
    for prefix in args.prefixes:
        sel = [r for r in rows if r["run"] == prefix]
        if sel:
            lines.append(f"| mean | | {prefix} | | {sum(r['val_psnr'] or 0 for r in sel) / len(sel):.2f} | "
                         f"{sum(r['train_term'] for r in sel) / len(sel):.4f} | "
                         f"{sum(r['train_angle_deg'] for r in sel) / len(sel):.1f} deg | "
                         f"{sum(r['val_term'] for r in sel) / len(sel):.4f} | "
                         f"{sum(r['val_angle_deg'] for r in sel) / len(sel):.1f} deg |")
    write_record(f"normal_agreement_{args.out}", result, lambda _: "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
