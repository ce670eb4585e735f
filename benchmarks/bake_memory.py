"""Peak memory of `ctgs export --bake-textures` per splat written, this checkout against another, side by side.

A baked export holds one splat per texel: a paper-scale model (Mip-NeRF 360: 46.6M texels) bakes to tens of
millions, so what counts is the memory per splat. Each measurement is a fresh Python process that builds a
synthetic textured model (surfels with 8x8 textures, SH degree 3: the paper's degree, the heaviest per splat),
bakes it (ctgs.io.bake.bake_texels) and writes it in one format through `ctgs export`'s writer, and reports its
peak resident memory (ru_maxrss) over what it held before baking. The floor is the baked model's own tensors
(bytes per splat of the float32 fields), which any in-memory writer holds. Both checkouts run the same child
code, alternating, so the machine's load falls on both.

Usage: .venv/bin/python benchmarks/bake_memory.py --other /path/to/old/checkout [--surfels 10000 20000] [--tag T]
(writes benchmarks/results/bake_memory_<tag>.{json,md})
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

from record import write_record

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FORMATS = ("ply", "splat", "spz")

CHILD = r"""
import json, math, os, resource, sys, time
import torch
from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.io.bake import bake_texels
from ctgs.stages.export import FORMATS, Export
n, fmt, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
res, degree = 8, 3
g = torch.Generator().manual_seed(0)
tex_res = torch.full((n, 2), res, dtype=torch.int32)
m = SurfelModel(means=torch.randn(n, 3, generator=g), log_scales=torch.full((n, 2), math.log(0.02)),
                quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
                opacity_logits=torch.full((n,), 3.0), sh=torch.randn(n, 16, 3, generator=g) * 0.1,
                textures_raw=torch.randn(n * res * res, 3, generator=g), k_min=torch.full((n,), 0.02 * 4 / res),
                t2p_exp=torch.zeros(n, dtype=torch.int32), tex_res=tex_res, tex_offset=jagged_offsets(tex_res),
                sh_degree=degree, texture_mode="content_aware")
rss = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
m.textures  # loads (first time: builds) the fused CPU kernels before anything is measured
r0, t0 = rss(), time.perf_counter()
baked = bake_texels(m)
r1, t1 = rss(), time.perf_counter()
FORMATS[fmt].write(Export(model=baked, out=out, source={}, plain_ply=False, baked=True))
r2, t2 = rss(), time.perf_counter()
floor = sum(t.numel() * t.element_size() for t in (baked.means, baked.log_scales, baked.quats, baked.opacity_logits,
                                                     baked.sh, baked.k_min, baked.t2p_exp, baked.tex_res,
                                                     baked.tex_offset))
print(json.dumps({"splats": baked.num_primitives, "bake_peak": r1 - r0, "peak": r2 - r0, "floor": floor,
                  "bake_s": t1 - t0, "write_s": t2 - t1, "file_bytes": os.path.getsize(out)}))
os.remove(out)
"""


def measure(checkout: str, name: str, surfels: int, fmt: str, tmp: str) -> dict:
    # Each checkout its own extension build folder: sharing one, they would rebuild it in turn.
    env = {**os.environ, "PYTHONPATH": checkout, "OMP_NUM_THREADS": "1",
           "TORCH_EXTENSIONS_DIR": os.path.join(tmp, f"bake_memory_ext_{name}")}
    out = os.path.join(tmp, f"bake_memory.{fmt}")
    proc = subprocess.run([sys.executable, "-c", CHILD, str(surfels), fmt, out], env=env, capture_output=True,
                          text=True, cwd=tmp)
    if proc.returncode:
        raise SystemExit(f"{checkout}: child failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def commit_of(path: str) -> str:
    try:
        return subprocess.run(["git", "-C", path, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def markdown(r: dict) -> str:
    lines = [f"# Peak memory of a baked export, per splat: {r['this']['commit']} against {r['other']['commit']}", "",
             f"Written by `{r['command']}` on {r['date']}, {r['machine']}. Each row: a fresh process builds a synthetic "
             "model (surfels with 8x8 textures, SH degree 3), bakes it and writes it with `ctgs export`'s writer; "
             "peak resident memory over what the process held before baking, per splat written. Floor: the baked "
             "model's own float32 tensors per splat. The two checkouts alternate, one process at a time.", "",
             "| format | surfels | splats | checkout | bake peak B/splat | bake + write peak B/splat | x floor | bake s "
             "| write s |", "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for row in r["rows"]:
        s = row["splats"]
        lines.append(f"| {row['format']} | {row['surfels']} | {s} | {row['checkout']} | {row['bake_peak'] / s:.0f} | "
                     f"{row['peak'] / s:.0f} | {row['peak'] / row['floor']:.2f} | {row['bake_s']:.1f} | "
                     f"{row['write_s']:.1f} |")
    lines += ["", "Ratios (other / this, bake + write peak per splat, mean over the model sizes):", ""]
    for fmt in FORMATS:
        ratios = [o["peak"] / t["peak"] for t in r["rows"] for o in r["rows"]
                  if t["format"] == o["format"] == fmt and t["surfels"] == o["surfels"]
                  and t["checkout"] == "this" and o["checkout"] == "other"]
        if ratios:
            lines.append(f"- {fmt}: {sum(ratios) / len(ratios):.2f}x")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", required=True, help="another checkout of ctgs (e.g. a git worktree of an older commit)")
    ap.add_argument("--surfels", type=int, nargs="+", default=[10000, 20000])
    ap.add_argument("--tmp", default="/tmp")
    ap.add_argument("--tag", default="vm")
    a = ap.parse_args()
    rows = []
    for surfels in a.surfels:
        for fmt in FORMATS:
            for name, path in (("other", a.other), ("this", ROOT)):
                row = measure(os.path.abspath(path), name, surfels, fmt, a.tmp)
                rows.append({"format": fmt, "surfels": surfels, "checkout": name, **row})
                print(json.dumps(rows[-1]), flush=True)
    result = {"command": "benchmarks/bake_memory.py " + " ".join(sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.node()} ({platform.machine()}, "
              f"{os.cpu_count()} cpus)", "this": {"path": ROOT, "commit": commit_of(ROOT)},
              "other": {"path": os.path.abspath(a.other), "commit": commit_of(a.other)}, "rows": rows}
    write_record(f"bake_memory_{a.tag}", result, markdown)


if __name__ == "__main__":
    main()
