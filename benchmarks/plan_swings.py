"""How much a `--time-budget` run's plan moved: every schedule is a fraction of the planned run, so each
re-plan moves every event. Reads the runs' log.jsonl ("plan" records) and train_summary.json.

Usage: .venv/bin/python benchmarks/plan_swings.py --out NAME LABEL=RUN_DIR [LABEL=RUN_DIR ...]
Writes benchmarks/results/plan_swings_NAME.md. After the first 10% of the run (the initial calibration's
corrections are expected), it sums |log(new plan / old plan)| over the re-plans and reports the largest one.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def swings(run: str) -> dict:
    plans = []
    with open(os.path.join(run, "log.jsonl")) as fh:
        for line in fh:
            e = json.loads(line)
            if e.get("type") == "plan":
                plans.append((int(e["it"]), int(e["iterations"])))
    summary = json.load(open(os.path.join(run, "train_summary.json")))
    final = plans[-1][1] if plans else int(summary.get("iterations", 0))
    late = [(a, b) for (ia, a), (_, b) in zip(plans, plans[1:]) if ia > 0.1 * final]
    logs = [abs(math.log(b / a)) for a, b in late if a > 0 and b > 0]
    return {"plans": plans, "final": final, "replans_late": len(logs), "sum": sum(logs),
            "largest_pct": 100 * (math.exp(max(logs)) - 1) if logs else 0.0,
            "first": plans[:4], "budget_min": summary.get("time_budget_s", 0) / 60,
            "wall_min": summary.get("wall_seconds", 0) / 60}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    args = ap.parse_args()
    lines = [f"# Plan swings of --time-budget runs ({args.out})", "",
             f"Written by `benchmarks/plan_swings.py {' '.join(sys.argv[1:])}` on "
             f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())} ({platform.node()}). After the first 10% of "
             "each run: the number of logged re-plans, the sum of |log(new / old)| over them and the largest "
             "single change.", "",
             "| run | budget min | wall min | final iterations | first plans (it, planned) | re-plans after 10% | "
             "summed abs log change | largest change | folder |",
             "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | --- |"]
    for spec in args.runs:
        label, run = spec.split("=", 1)
        s = swings(run)
        first = ", ".join(f"({i}, {n})" for i, n in s["first"])
        lines.append(f"| {label} | {s['budget_min']:.1f} | {s['wall_min']:.2f} | {s['final']} | {first} | "
                     f"{s['replans_late']} | {s['sum']:.2f} | {s['largest_pct']:.0f}% | `{run}` |")
    path = os.path.join(ROOT, "benchmarks", "results", f"plan_swings_{args.out}.md")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
