"""Pool benchmarks/equal_time.py results over seeds: per-seed test rows, the paired PSNR difference
(content-aware - 2dgs), its mean, standard deviation and a paired t statistic.

Usage: .venv/bin/python benchmarks/equal_time_summary.py RESULT.json [RESULT.json ...] --out NAME
(writes benchmarks/results/NAME.md; reads only the JSON files equal_time.py wrote).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("results", nargs="+")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    rows, diffs = [], []
    for path in args.results:
        with open(path) as fh:
            d = json.load(fh)
        seed = d["command"].split("--seed ")[1].split()[0] if "--seed " in d["command"] else "?"
        by = {r["method"]: r for r in d["test"]}
        ca, g = by.get("content-aware", by.get("ca")), by["2dgs"]
        diffs.append(ca["psnr"] - g["psnr"])
        rows.append((seed, d["commit"], os.path.basename(path), ca, g))
    n = len(diffs)
    mean = statistics.mean(diffs)
    sd = statistics.stdev(diffs) if n > 1 else float("nan")
    t = mean / (sd / math.sqrt(n)) if n > 1 and sd > 0 else float("nan")

    def mean_of(method: str, key: str) -> float:
        return statistics.mean(r[3 if method == "ca" else 4][key] for r in rows)

    lines = ["# Content-aware vs 2dgs at equal wall time, pooled over seeds (herzjesu25 images_8, preset fast)", "",
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
              f"Paired PSNR difference (content-aware - 2dgs): mean {mean:+.2f} dB, standard deviation {sd:.2f} dB, "
              f"content-aware ahead on {sum(x > 0 for x in diffs)} of {n} seeds, paired t = {t:.2f} with {n - 1} degrees "
              "of freedom (|t| > 3.18 would be needed for 5% two-sided at 3 degrees of freedom)."]
    out = os.path.join(ROOT, "benchmarks", "results", args.out + ".md")
    with open(out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
