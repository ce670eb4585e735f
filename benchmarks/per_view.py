"""Per-view test PSNR of finished runs: is a mean carried by one view?

A mean over 3 test views (the 192x144 demo: views 000, 008, 016) can move by several dB when one view goes
wrong, e.g. a semi-transparent primitive in front of that camera only. This tabulates each run's per-view
PSNR (`ctgs eval RUN -o RUN/eval` is run first where RUN/eval/per_image.csv is missing), the mean, and the
mean without the worst view.

Usage: .venv/bin/python benchmarks/per_view.py --out NAME LABEL=RUN_DIR [LABEL=RUN_DIR ...]
Writes benchmarks/results/per_view_NAME.md.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def per_image(run: str) -> list[dict]:
    path = os.path.join(run, "eval", "per_image.csv")
    if not os.path.exists(path):
        subprocess.run([sys.executable, "-m", "ctgs", "eval", run, "-o", os.path.join(run, "eval")], check=True,
                       cwd=ROOT, capture_output=True)
    with open(path) as fh:
        return list(csv.DictReader(fh))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    args = ap.parse_args()
    rows = []
    for spec in args.runs:
        label, run = spec.rsplit("=", 1)
        rows.append((label, run, per_image(run)))
    names = sorted({r["name"] for _, _, pi in rows for r in pi})
    lines = [f"# Per-view test PSNR ({args.out})", "",
             f"Written by `benchmarks/per_view.py {' '.join(sys.argv[1:])}` on {time.strftime('%Y-%m-%d')} "
             f"({platform.node()}, {platform.machine()}, {os.cpu_count()} cpus). PSNR from `ctgs eval` of each run "
             "(CPU backend); mean = the eval's mean over views; w/o worst = the mean of the other views.", "",
             "| run | " + " | ".join(names) + " | mean | w/o worst | folder |",
             "| --- | " + " | ".join("---:" for _ in names) + " | ---: | ---: | --- |"]
    for label, run, pi in rows:
        by = {r["name"]: float(r["psnr"]) for r in pi}
        vals = sorted(by.values())
        rest = vals[1:] if len(vals) > 1 else vals
        lines.append(f"| {label} | " + " | ".join(f"{by[n]:.2f}" if n in by else "-" for n in names) +
                     f" | {sum(vals) / len(vals):.2f} | {sum(rest) / len(rest):.2f} | `{run}` |")
    out = os.path.join(ROOT, "benchmarks", "results", f"per_view_{args.out}.md")
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
