"""How evenly a run's full routines are spaced: reads finished runs' log.jsonl, trains nothing.

For each run: the iterations of its full routines, and each gap in units of the routine period of the plan in force
at the later routine (routine_every x iterations / 30000, from the run's config.toml and its logged plans). A fixed
run's gaps are all 1 by construction; a `--time-budget` run's show whether re-plans moved the calendar.
Writes benchmarks/results/routine_spacing_<tag>.md.

    .venv/bin/python benchmarks/routine_spacing.py --tag vm20 "before=out/demo/run" "after=/work/runs/x/run"
"""

from __future__ import annotations

import argparse
import bisect
import datetime
import json
import os
import statistics
import sys
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from ctgs.train.run import machine_name  # noqa: E402


def spacing(run: str) -> dict:
    with open(os.path.join(run, "config.toml"), "rb") as fh:
        cfg = tomllib.load(fh)
    rows = [json.loads(line) for line in open(os.path.join(run, "log.jsonl"))]
    plans = {0: int(cfg["iterations"])}
    for r in rows:
        if r["type"] == "plan":
            plans[int(r["it"])] = int(r["iterations"])
    keys = sorted(plans)
    its = [r["it"] for r in rows if r["type"] == "routine" and r.get("kind") == "full"]

    def period(it: int) -> float:
        n = plans[keys[bisect.bisect_right(keys, it) - 1]]
        return float(cfg["routine_every"]) * n / 30000.0

    gaps = [(b - a) / period(b) for a, b in zip(its, its[1:])]
    return {"routines": len(its), "plans": len(plans) - 1, "gaps": gaps,
            "iterations": plans[keys[-1]]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tag", required=True)
    ap.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    args = ap.parse_args()
    lines = [f"# Full-routine spacing ({args.tag})", "",
             f"Written by `benchmarks/routine_spacing.py {' '.join(sys.argv[1:])}` on "
             f"{datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')} ({machine_name()}); "
             "gaps in periods of the plan in force (1 = on schedule).", "",
             "| run | plans | iterations | full routines | gap min | gap median | gap max | gaps < 0.5 | gaps > 1.5 |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for spec in args.runs:
        label, run = spec.split("=", 1)
        s = spacing(run)
        g = s["gaps"]
        lines.append(f"| {label} (`{run}`) | {s['plans']} | {s['iterations']:,} | {s['routines']} | {min(g):.2f} | "
                     f"{statistics.median(g):.2f} | {max(g):.2f} | {sum(x < 0.5 for x in g)} | "
                     f"{sum(x > 1.5 for x in g)} |")
    out = os.path.join(ROOT, "benchmarks", "results", f"routine_spacing_{args.tag}.md")
    with open(out + ".tmp", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    os.replace(out + ".tmp", out)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
