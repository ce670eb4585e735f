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


FRACTIONS = (0.1, 0.25, 0.5, 0.75)
RICH_WINDOW_S = 30.0  # rich.progress's speed_estimate_period: its ETA is the work left over the last 30 s's speed


def eta_checks(run: str, iterations: int, wall_s: float, est_at: list, est_s: list) -> dict:
    """At each fraction of the run, the predicted total wall time (command start to end) from the cost model's
    latest estimate, and from the recent speed as rich's ETA column computes it (iterations left / iterations per
    second over the last 30 s, from the log's step records), each over the wall time."""
    steps = [r for r in map(json.loads, open(os.path.join(run, "log.jsonl"))) if r.get("type") == "step"]
    out = {}
    for f in FRACTIONS:
        k = next((r for r in steps if r["it"] >= f * iterations), None)
        if k is None:
            continue
        past = [r for r in steps if r["wall"] <= k["wall"] - RICH_WINDOW_S] or steps[:1]
        ref = past[-1]
        speed = (k["it"] - ref["it"]) / max(k["wall"] - ref["wall"], 1e-9)
        naive = k["wall"] + (iterations - k["it"]) / max(speed, 1e-9)
        model = [s for i, s in zip(est_at, est_s) if i <= k["it"]]
        out[f] = {"it": k["it"], "model": model[-1] / wall_s if model else None, "recent_speed": naive / wall_s}
    return out


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
            "estimated_at_it": s["estimated_at_it"], "pixels": s["image_pixels"],
            "eta": eta_checks(run, s["iterations"], s["wall_seconds"], s["estimated_at_it"], s["estimated_wall_s"])}


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
    lines += ["", "Time left as the progress display shows it, read as the predicted total wall time over the actual one, at "
              "fractions of the run: the cost model's latest estimate (the display's ETA since this commit) against the "
              "recent speed's (rich's ETA column before it: iterations left / iterations per second over the last "
              f"{RICH_WINDOW_S:.0f} s, from the log's step records).", "",
              "| run | " + " | ".join(f"{f:.0%}: model | recent speed" for f in FRACTIONS) + " |",
              "| --- | " + " | ".join("---: | ---:" for _ in FRACTIONS) + " |"]
    for r in recs:
        cells = []
        for f in FRACTIONS:
            e = r["eta"].get(f) or r["eta"].get(str(f))
            cells.append("- | -" if e is None else
                         f"{'-' if e['model'] is None else format(e['model'], '.2f')} | {e['recent_speed']:.2f}")
        lines.append(f"| {r['run']} | " + " | ".join(cells) + " |")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
