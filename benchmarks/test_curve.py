"""Test PSNR / SSIM over a run's length, from the periodic test evaluations in each RUN/log.jsonl.

    .venv/bin/python benchmarks/test_curve.py RUN [RUN ...] --name NAME
writes benchmarks/results/test_curve_NAME.md: one column per run, one row per evaluated iteration. A reading aid
(does a recipe overfit with length?), never a way to choose a setting: these are the protocol's test views.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def curve(run: str) -> dict[int, tuple[float, float]]:
    out = {}
    with open(os.path.join(run, "log.jsonl")) as fh:
        for line in fh:
            d = json.loads(line)
            if d.get("type") == "test":
                out[int(d["it"])] = (d["psnr"], d["ssim"])
    if not out:
        raise SystemExit(f"test_curve.py: {run}/log.jsonl has no test evaluations (test_every)")
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--name", required=True)
    args = ap.parse_args()
    curves = {os.path.basename(os.path.normpath(r)): curve(r) for r in args.runs}
    its = sorted({i for c in curves.values() for i in c})
    lines = [f"# Test PSNR / SSIM over the run ({platform.node()}, {platform.machine()}, {os.cpu_count()} cpus)", "",
             f"Command: `{' '.join(sys.argv)}`. From each run's log.jsonl (its test evaluations, every `test_every` "
             "iterations, on the protocol's test views: read, not used to choose anything).", "",
             "| iteration | " + " | ".join(curves) + " |", "| ---: |" + " ---: |" * len(curves)]
    for i in its:
        cells = [f"{c[i][0]:.2f} / {c[i][1]:.3f}" if i in c else "-" for c in curves.values()]
        lines.append(f"| {i} | " + " | ".join(cells) + " |")
    out = os.path.join(ROOT, "benchmarks", "results", f"test_curve_{args.name}.md")
    with open(out + ".tmp", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    os.replace(out + ".tmp", out)
    print(out)


if __name__ == "__main__":
    main()
