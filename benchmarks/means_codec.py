"""How trained models' positions fare under the compressed format's three position encodings.

For each run folder (a `ctgs train` output with model.pt): the positions' coded bytes (xz, as `ctgs compress`
writes them, Morton-sorted) and the worst shift in pixels of each primitive's closest training camera, for
- f32: float32 positions (exact);
- q16 one range: fixed point over the bounding box of every centre (what `ctgs compress` stored before session 11,
  and what it then had to abandon for f32 whenever the shift passed MEANS_MAX_SHIFT_PX);
- q16 + outliers: the current encoding (ctgs.io.compress._encode_means): the range leaves out the primitives it
  would move too far, which are stored apart as float32.

Usage: .venv/bin/python benchmarks/means_codec.py RUN [RUN ...] [--out NAME]
Writes benchmarks/results/means_codec_<NAME>.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time

import numpy as np
from ctgs.io import quantize
from ctgs.io.compress import MEANS_MAX_SHIFT_PX, _encode_means, morton_order
from ctgs.io.packed import Section, encode_section
from ctgs.io.run_model import load_run

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def coded(*arrays: np.ndarray) -> int:
    return sum(len(encode_section(Section("s", a, {}), "xz", 0)[0]) for a in arrays if len(a))


def measure(run: str) -> dict:
    model = load_run(run).model
    means = model.means.detach().double().numpy()
    k_min = np.maximum(model.k_min.detach().double().numpy(), 1e-12)
    order = morton_order(means)
    means, k_min = means[order], k_min[order]
    one_stored, one_enc = quantize.encode(means, "q16")
    one_shift = float((np.abs(quantize.decode(one_stored, one_enc) - means).max(1) / k_min).max())
    stored, enc, out, st = _encode_means(means, k_min, "q16")
    new_shift = np.abs(quantize.decode(stored, enc) - means).max(1) / k_min
    new_shift[out] = 0.0
    return {"run": run, "primitives": len(means),
            "extent": float(np.abs(means - np.median(means, 0)).max()),
            "median_extent": float(np.median(np.abs(means - np.median(means, 0)).max(1))),
            "f32_bytes": coded(means.astype("<f4")),
            "q16_bytes": coded(one_stored), "q16_shift_px": one_shift,
            "outlier_bytes": coded(stored, out.astype("<u4"), means[out].astype("<f4")) if len(out) < len(means)
            else coded(means.astype("<f4")),
            "outliers": int(len(out)), "outlier_shift_px": float(new_shift.max())}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--out", default=platform.node())
    args = ap.parse_args()
    rows = [measure(r) for r in args.runs]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    machine = f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"
    out = os.path.join(ROOT, "benchmarks", "results", f"means_codec_{args.out}")
    with open(out + ".json", "w") as fh:
        json.dump({"command": "benchmarks/means_codec.py " + " ".join(args.runs), "machine": machine,
                   "commit": commit, "limit_px": MEANS_MAX_SHIFT_PX, "rows": rows}, fh, indent=1)
    lines = [f"# Position encodings of trained models ({args.out})", "",
             f"Written by `benchmarks/means_codec.py` on {time.strftime('%Y-%m-%d')}, {machine}, commit {commit}. "
             f"Bytes = xz-coded positions as `ctgs compress` writes them (Morton order); shift = the largest move "
             f"of a centre in pixels of its closest training camera (limit {MEANS_MAX_SHIFT_PX} px). "
             "q16 one range is what `ctgs compress` had to replace by f32 when its shift passed the limit.", "",
             "| run | primitives | farthest / median distance from the median centre | f32 bytes | q16 one range: bytes, "
             "shift px | q16 + outliers: bytes, outliers, shift px | stored before -> now |",
             "| --- | ---: | ---: | ---: | --- | --- | --- |"]
    for r in rows:
        before = r["q16_bytes"] if r["q16_shift_px"] <= MEANS_MAX_SHIFT_PX else r["f32_bytes"]
        lines.append(f"| `{r['run']}` | {r['primitives']:,} | {r['extent'] / r['median_extent']:.0f}x | "
                     f"{r['f32_bytes']:,} | {r['q16_bytes']:,}, {r['q16_shift_px']:.3f} | "
                     f"{r['outlier_bytes']:,}, {r['outliers']}, {r['outlier_shift_px']:.3f} | "
                     f"{before:,} -> {r['outlier_bytes']:,} |")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
