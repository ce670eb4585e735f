"""How close a fixed-length run's wall-time estimates come to its wall time (`ctgs train` without --time-budget).

Trains each RUN (PRESET[:IMAGES[:CONFIG]]) through the `ctgs` CLI, two at a time by default (one thread each, as a
user on a shared 2-core machine would), and reads from each train_summary.json the estimates the run made (at the
start, from the calibration; after ten measured steps past the texture start) and its wall seconds. Writes
benchmarks/results/estimate_accuracy_<tag>.{md,json}. Finished runs in --work are reused.

    .venv/bin/python benchmarks/estimate_accuracy.py --scene /work/data/herzjesu25 --work /work/runs/est \
        --runs fast:images_4 fast:images_8 balanced:images_8 fast:images_4:2dgs --tag vm19
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from trade import ctgs, git_commit  # noqa: E402

from ctgs.train.run import machine_name  # noqa: E402


def parse_run(spec: str) -> tuple[str, str, str | None]:
    parts = spec.split(":")
    if not 1 <= len(parts) <= 3 or not parts[0]:
        raise SystemExit(f"estimate_accuracy.py: write a run as PRESET[:IMAGES[:CONFIG]], got {spec!r}")
    return parts[0], parts[1] if len(parts) > 1 and parts[1] else "images", parts[2] if len(parts) > 2 else None


def run_one(args, spec: str) -> dict:
    preset, images, config = parse_run(spec)
    label = "_".join([preset, images] + ([config] if config else []))
    run = os.path.join(args.work, label)
    summary_path = os.path.join(run, "train_summary.json")
    commit = git_commit()
    if not os.path.exists(summary_path):
        os.makedirs(args.work, exist_ok=True)
        ctgs("train", args.scene, "-o", run, "--images", images, "--preset", preset, "-q",
             *(["--config", config] if config else []), "--set", f"threads={args.threads}",
             "--set", f"seed={args.seed}", log=run + ".log")
    with open(summary_path) as fh:
        s = json.load(fh)
    if "estimated_wall_s" not in s:
        raise SystemExit(f"{summary_path}: no estimates (a --time-budget run, or trained before they existed)")
    return {"run": label, "preset": preset, "images": images, "config": config, "commit": commit,
            "iterations": s["iterations"], "wall_s": s["wall_seconds"], "estimated_wall_s": s["estimated_wall_s"],
            "estimated_at_it": s["estimated_at_it"], "pixels": s["image_pixels"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--work", required=True)
    ap.add_argument("--runs", nargs="+", required=True, help="PRESET[:IMAGES[:CONFIG]] each")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", required=True)
    args = ap.parse_args()
    commit = git_commit()
    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        recs = list(pool.map(lambda spec: run_one(args, spec), args.runs))
    out = os.path.join(ROOT, "benchmarks", "results", f"estimate_accuracy_{args.tag}")
    with open(out + ".json", "w") as fh:
        json.dump({"command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit,
                   "machine": machine_name(), "runs": recs}, fh, indent=1)
    lines = [f"# Wall-time estimates of fixed-length runs against their wall time ({os.path.basename(args.scene)})", "",
             f"Written by `benchmarks/estimate_accuracy.py {' '.join(sys.argv[1:])}` on {time.strftime('%Y-%m-%d %H:%M')}, "
             f"{machine_name()}, commit {commit} at the start, {args.threads} thread per training, {args.parallel} "
             "trainings at a time. Estimate / wall: 1.00 is exact; the first is made before the first step from the "
             "calibration, the second from ten steps measured after the texture start (the baselines: the first ten).",
             "", "| run | pixels per view | iterations | wall min | estimate at start, min | / wall | re-estimate at it. "
             "| min | / wall |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in recs:
        est, at, wall = r["estimated_wall_s"], r["estimated_at_it"], r["wall_s"]
        second = (f"{at[1]} | {est[1] / 60:.2f} | {est[1] / wall:.2f}" if len(est) > 1 else "- | - | -")
        lines.append(f"| {r['run']} | {r['pixels']:.0f} | {r['iterations']} | {wall / 60:.2f} | {est[0] / 60:.2f} | "
                     f"{est[0] / wall:.2f} | {second} |")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
