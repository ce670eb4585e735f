"""What a `--time-budget` run planned first against what it ran, from finished runs' logs.

The first plan is the line a user reads when the run starts ("planned N iterations"), and every schedule is a
fraction of the plan: an event that fires early in the run (the texture start, at 500/30000 = 1.7% of it)
happens at its fraction of the plan in force at that time and cannot be moved afterwards. For each run:
budget and wall time, the first plan and the iterations run (ratio), the texture start's iteration and what
fraction of the run it came at, the calibration's step against the median of the first 10 measured steps,
and the calibrated texture-start jump against the measured one (median seconds per step over the 60 steps
after the texture start / over the steps before it, windows with a routine or an evaluation left out).
With `--set validation_holdout=K` runs, the final PSNR is on validation views (labelled so); otherwise none is
shown (test views are not used to choose anything here).

Usage: .venv/bin/python benchmarks/budget_first_plan.py --out NAME LABEL=RUN_DIR [LABEL=RUN_DIR ...]
Writes benchmarks/results/budget_first_plan_NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TEXTURE_START_FRACTION = 500 / 30000


def _windows(log: list[dict]) -> list[tuple[int, float]]:
    """(iteration, seconds per step) over consecutive logged steps with no routine, evaluation or checkpoint in
    between (a re-plan costs milliseconds: windows with one count)."""
    steps = [e for e in log if e.get("type") == "step"]
    events = {e["it"] for e in log if e.get("type") in ("routine", "test", "checkpoint")}
    out = []
    for a, b in zip(steps, steps[1:]):
        if b["it"] > a["it"] and not any(a["it"] < k <= b["it"] for k in events):
            out.append((b["it"], (b["seconds"] - a["seconds"]) / (b["it"] - a["it"])))
    return out


def measure(run: str) -> dict:
    with open(os.path.join(run, "log.jsonl")) as fh:
        log = [json.loads(line) for line in fh if line.strip()]
    summary = json.load(open(os.path.join(run, "train_summary.json")))
    with open(os.path.join(run, "config.toml"), "rb") as fh:
        cfg = tomllib.load(fh)
    plans = [e for e in log if e.get("type") == "plan"]
    first = plans[0]
    ran = int(summary["iterations"])
    tex = [e["it"] for e in log if e.get("type") == "routine" and e.get("kind") == "texture_start"]
    win = _windows(log)
    steps = [e for e in log if e.get("type") == "step"]
    first10 = [s for i, s in win if i <= 11] or [steps[1]["seconds"] / max(steps[1]["it"], 1)]
    out = {"run": run, "preset": summary.get("preset"), "method": summary.get("method"),
           "pixels": summary.get("image_pixels"), "budget_min": summary["time_budget_s"] / 60,
           "wall_s": summary["wall_seconds"], "budget_s": summary["time_budget_s"],
           "first_plan": int(first["iterations"]), "ran": ran, "first_over_ran": int(first["iterations"]) / ran,
           "calib_step_s": first.get("calibration_step_s"), "first_steps_s": statistics.median(first10),
           "calib_textured_step_s": first.get("calibration_textured_step_s")}
    if tex:
        t = tex[0]
        before = [s for i, s in win if 10 < i <= t]
        after = [s for i, s in win if t < i <= t + 60]
        out.update(texture_start_it=t, texture_start_fraction=t / ran,
                   jump_measured=statistics.median(after) / statistics.median(before) if before and after else None)
        if out["calib_textured_step_s"] and out["calib_step_s"]:
            out["jump_calibrated"] = out["calib_textured_step_s"] / out["calib_step_s"]
    if int(cfg.get("validation_holdout", 0)) > 0:
        out["validation_psnr"] = summary.get("final_test_psnr")
    return out


def _f(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    args = ap.parse_args()
    rows = []
    for spec in args.runs:
        label, run = spec.split("=", 1)
        rows.append({"label": label, **measure(run)})
    lines = [f"# First plan against the run, `--time-budget` ({args.out})", "",
             f"Written by `benchmarks/budget_first_plan.py {' '.join(sys.argv[1:])}` on "
             f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())} ({platform.node()}, {platform.machine()}, "
             f"{os.cpu_count()} CPUs). Texture start: the schedule puts it at {100 * TEXTURE_START_FRACTION:.2f}% "
             "of the run. Step seconds: the calibration's (a training step of the initial model) against the median "
             "of the first 10 measured steps; jump: textured step / untextured step, calibrated (on a copy of the "
             "model, before the run) and measured (60 steps after the texture start / the steps before it). "
             "`val PSNR`: validation views (`--set validation_holdout=8`), shown for runs trained so.", "",
             "| run | preset | px/view | budget min | wall s | first plan | ran | first / ran | texture start (it, % of run) "
             "| calib step s | first 10 steps s | jump calibrated | jump measured | val PSNR |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        ts = (f"{r['texture_start_it']} ({100 * r['texture_start_fraction']:.2f}%)"
              if r.get("texture_start_it") is not None else "-")
        lines.append(f"| {r['label']} | {r['preset']} | {r['pixels']:.0f} | {r['budget_min']:.1f} | {r['wall_s']:.1f} | "
                     f"{r['first_plan']} | {r['ran']} | {r['first_over_ran']:.2f} | {ts} | "
                     f"{_f(r['calib_step_s'], '.3f')} | {r['first_steps_s']:.3f} | {_f(r.get('jump_calibrated'), '.2f')} | "
                     f"{_f(r.get('jump_measured'), '.2f')} | {_f(r.get('validation_psnr'), '.2f')} |")
    lines += ["", "Folders: " + "; ".join(f"{r['label']}: `{r['run']}`" for r in rows)]
    base = os.path.join(ROOT, "benchmarks", "results", f"budget_first_plan_{args.out}")
    with open(base + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    with open(base + ".json", "w") as fh:
        json.dump({"argv": sys.argv[1:], "rows": rows}, fh, indent=1)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
