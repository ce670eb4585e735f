"""A new view's exposure predicted from its nearest training photos: validation PSNR with and without it.

For each validation run trained with `exposure_comp` (its held-out views are training-set views, never test views):
each validation view is drawn as the run draws it (no gain) and with the gain exp(sum_k w_k l_k) of its K nearest
training cameras by camera centre, w_k proportional to 1 / distance (normalised), l_k the run's learned centred
log-gains (the final `exposure` record of its log.jsonl). Reports both PSNRs per view and per run.

Usage: .venv/bin/python benchmarks/exposure_neighbours.py --work DIR --prefix exp --preset balanced \\
         --seeds 0 1 2 3 [--k 2] --out NAME [--note TEXT]
Writes benchmarks/results/exposure_neighbours_NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
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


def learned_gains(run_dir: str) -> dict[str, np.ndarray]:
    """{training image name: [3] gain} from the last `exposure` record of the run's log."""
    last = None
    with open(os.path.join(run_dir, "log.jsonl")) as fh:
        for line in fh:
            if '"exposure"' in line:
                rec = json.loads(line)
                if rec.get("type") == "exposure":
                    last = rec
    if last is None:
        raise SystemExit(f"{run_dir}: no exposure record in log.jsonl (train with --set exposure_comp=true)")
    return {k: np.asarray(v, dtype=np.float64) for k, v in last["gains"].items()}


def neighbour_gain(center: np.ndarray, centers: np.ndarray, log_gains: np.ndarray, k: int) -> np.ndarray:
    """[3] exp of the inverse-distance-weighted mean of the k nearest cameras' log-gains."""
    d = np.linalg.norm(centers - center[None], axis=1)
    idx = np.argsort(d)[:k]
    w = 1.0 / np.maximum(d[idx], 1e-9)
    w /= w.sum()
    return np.exp((w[:, None] * log_gains[idx]).sum(0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True)
    ap.add_argument("--prefix", required=True)
    ap.add_argument("--preset", required=True)
    ap.add_argument("--seeds", nargs="+", type=int, required=True)
    ap.add_argument("--k", type=int, default=2)
    ap.add_argument("--out", required=True)
    ap.add_argument("--note", default="")
    args = ap.parse_args()
    torch.set_num_threads(1)
    runs = []
    for seed in args.seeds:
        rd = os.path.join(args.work, f"{args.prefix}_{args.preset}_s{seed}")
        run, scene = load_validation_run(rd)
        gains = learned_gains(rd)
        centers = np.stack([v.camera.center.double().numpy() for v in scene.train])
        log_gains = np.log(np.stack([gains[v.name] for v in scene.train]))
        inputs = run.model.render_inputs()
        views = []
        for v in scene.test:
            with torch.no_grad():
                r = render(inputs, v.camera, sh_degree=run.model.sh_degree).rgb.clamp(0, 1).double().numpy()
            gt = np.asarray(v.image, dtype=np.float64)
            g = neighbour_gain(v.camera.center.double().numpy(), centers, log_gains, args.k)
            views.append({"view": v.name, "psnr": psnr(r, gt), "gain": [float(x) for x in g],
                          "psnr_neighbours": psnr(np.clip(r * g, 0, 1), gt)})
        runs.append({"seed": seed, "run": rd, "views": views,
                     "psnr": statistics.mean(x["psnr"] for x in views),
                     "psnr_neighbours": statistics.mean(x["psnr_neighbours"] for x in views)})
    diffs = [r["psnr_neighbours"] - r["psnr"] for r in runs]
    result = {"command": "benchmarks/exposure_neighbours.py " + " ".join(sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M"),
              "machine": f"{platform.node() or 'machine'} ({platform.machine()}, {os.cpu_count()} cpus)",
              "k": args.k, "note": args.note, "runs": runs, "mean_diff": statistics.mean(diffs),
              "ahead": sum(d > 0 for d in diffs)}

    def markdown(res: dict) -> str:
        lines = [f"# A new view's exposure from its {res['k']} nearest training photos ({args.out})", "",
                 f"Command: `{res['command']}` on {res['date']}, {res['machine']}. Validation views only.", ""]
        if res["note"]:
            lines += [res["note"], ""]
        lines += ["| seed | view | PSNR (no gain) | neighbours' gain R/G/B | PSNR x it |", "| ---: | --- | ---: | --- | ---: |"]
        for r in res["runs"]:
            for v in r["views"]:
                lines.append(f"| {r['seed']} | {v['view']} | {v['psnr']:.2f} | "
                             + "/".join(f"{x:.3f}" for x in v["gain"]) + f" | {v['psnr_neighbours']:.2f} |")
            lines.append(f"| {r['seed']} | mean | {r['psnr']:.2f} | | {r['psnr_neighbours']:.2f} |")
        lines += ["", f"Mean difference (neighbours' gain - none): **{res['mean_diff']:+.2f} dB** over {len(res['runs'])} "
                  f"seeds, ahead on {res['ahead']}."]
        return "\n".join(lines) + "\n"

    write_record(f"exposure_neighbours_{args.out}", result, markdown)


if __name__ == "__main__":
    main()
