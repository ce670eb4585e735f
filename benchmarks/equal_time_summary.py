"""Pool benchmarks/equal_time.py results over seeds: per-seed test rows, the paired PSNR difference
(content-aware - 2dgs), its mean, standard deviation and a paired t statistic.

Usage: .venv/bin/python benchmarks/equal_time_summary.py RESULT.json [RESULT.json ...] --out NAME
(writes benchmarks/results/equal_time/NAME_<commit>.md; reads only the JSON files equal_time.py wrote).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)
from paired_stats import paired, sentence  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("results", nargs="+")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    rows, diffs, setups = [], [], set()
    for path in args.results:
        with open(path) as fh:
            d = json.load(fh)
        seed = d["command"].split("--seed ")[1].split()[0] if "--seed " in d["command"] else "?"
        opt = lambda k, default: d["command"].split(f"--{k} ")[1].split()[0] if f"--{k} " in d["command"] else default  # noqa: E731
        setups.add(f"{os.path.basename(opt('scene', '?').rstrip('/'))} {opt('images', 'images_8')}, preset {opt('preset', 'fast')}")
        by = {r["method"]: r for r in d["test"]}
        ca, g = by.get("content-aware", by.get("ca")), by["2dgs"]
        diffs.append(ca["psnr"] - g["psnr"])
        rows.append((seed, d["commit"], os.path.basename(path), ca, g))
    n = len(diffs)
    st = paired(diffs)

    def mean_of(method: str, key: str) -> float:
        return statistics.mean(r[3 if method == "ca" else 4][key] for r in rows)

    lines = [f"# Content-aware vs 2dgs at equal wall time, pooled over seeds ({'; '.join(sorted(setups))})", "",
             f"Written by `benchmarks/equal_time_summary.py {' '.join(sys.argv[1:])}`. Each seed: benchmarks/"
             "equal_time.py (lengths chosen on validation views, test views left out of the choice; both chosen runs "
             "trained side by side, 1 thread each, on the dev VM); its own file has the validation table.", "",
             "| seed | file | commit | content-aware it | CA PSNR | CA SSIM | CA LPIPS | CA prims | CA params | 2dgs it "
             "| 2dgs PSNR | 2dgs SSIM | 2dgs LPIPS | 2dgs prims | 2dgs params | PSNR CA - 2dgs |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for (seed, commit, name, ca, g), dlt in zip(rows, diffs):
        lines.append(f"| {seed} | {name} | {commit} | {ca['iterations']} | {ca['psnr']:.2f} | {ca['ssim']:.3f} | "
                     f"{ca['lpips']:.3f} | {ca['primitives']} | {ca['params']} | {g['iterations']} | {g['psnr']:.2f} | "
                     f"{g['ssim']:.3f} | {g['lpips']:.3f} | {g['primitives']} | {g['params']} | {dlt:+.2f} |")
    lines += ["", f"Mean over {n} seeds: content-aware {mean_of('ca', 'psnr'):.2f} dB / SSIM {mean_of('ca', 'ssim'):.3f} / "
              f"LPIPS {mean_of('ca', 'lpips'):.3f}, {mean_of('ca', 'primitives'):.0f} primitives, "
              f"{mean_of('ca', 'params') / 1e6:.2f}M params; 2dgs {mean_of('g', 'psnr'):.2f} dB / SSIM "
              f"{mean_of('g', 'ssim'):.3f} / LPIPS {mean_of('g', 'lpips'):.3f}, {mean_of('g', 'primitives'):.0f} primitives, "
              f"{mean_of('g', 'params') / 1e6:.2f}M params.",
              sentence("Paired PSNR difference (content-aware - 2dgs)", st)]
    for key, note in (("ssim", ""), ("lpips", "; lower is better")):
        sk = paired([r[3][key] - r[4][key] for r in rows])
        lines.append(f"Paired {key.upper()} difference: mean {sk['mean']:+.4f}, p = {sk['p']:.3f}{note}.")
    # Per-view differences, for the seeds whose records kept each view's PSNR (equal_time.py keeps them).
    views = [(ca["per_view_psnr"], g["per_view_psnr"]) for _, _, _, ca, g in rows
             if ca.get("per_view_psnr") and g.get("per_view_psnr")]
    if views:
        lines += ["", f"Per test view, over the {len(views)} seed(s) whose records keep each view's PSNR "
                  "(the first view of herzjesu25's one-sided trajectory is an extrapolation; "
                  "docs/studies.md):", "",
                  "| view | content-aware mean | 2dgs mean | paired difference |", "| --- | ---: | ---: | --- |"]
        for name in sorted(views[0][0]):
            d = [a[name] - b[name] for a, b in views]
            s_v = paired(d)
            extra = f", t = {s_v['t']:.2f}, p = {s_v['p']:.3f}" if s_v["n"] > 1 else ""
            lines.append(f"| {name} | {statistics.mean(a[name] for a, _ in views):.2f} | "
                         f"{statistics.mean(b[name] for _, b in views):.2f} | {s_v['mean']:+.2f} dB{extra} |")
        first = sorted(views[0][0])[0]
        rest = [statistics.mean(a[k] - b[k] for k in a if k != first) for a, b in views]
        lines += ["", sentence(f"Breakdown, not the measure: the paired difference of the mean over the views other "
                               f"than {first} (content-aware - 2dgs)", paired(rest))]
    out = record.stem("equal_time", args.out) + ".md"
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
