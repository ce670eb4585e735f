"""SOG's SH palette: PlayCanvas's size rule (K-means into 1024 entries per 1-2k splats, doubling with the count)
against ctgs's (every distinct SH row while they fit the 65,536 entries), on a trained run: export seconds, bytes,
test PSNR and PSNR against the exact model, each file read back and drawn by our CPU renderer.

Usage: .venv/bin/python benchmarks/sog_palette.py RUN_DIR [--tag NAME]
Writes benchmarks/results/sog_palette_<tag>.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import sys
import tempfile
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import ctgs.io.playcanvas as pc  # noqa: E402
from ctgs.io.run_model import load_run  # noqa: E402
from ctgs.scene import load_scene  # noqa: E402
from export_formats import render_views, scores  # noqa: E402
from record import write_record  # noqa: E402 (benchmarks/record.py)


def playcanvas_rule(n: int) -> int:
    """splat-transform 3.7.0's palette size (write-sog): min(64, 2^floor(log2(n / 1024))) * 1024."""
    return int(min(64, 2.0 ** math.floor(math.log2(n / 1024))) * 1024)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--tag", required=True)
    args = ap.parse_args()
    t0 = time.time()
    run = load_run(args.run_dir)
    model = run.model
    views = load_scene(run.scene_dir, images=run.images, holdout=run.holdout).test
    exact = render_views(model, views)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, rule in (("PlayCanvas's rule (K-means)", playcanvas_rule), ("ctgs: every distinct row", None)):
            original = pc.palette_size
            if rule is not None:
                pc.palette_size = rule
            try:
                t = time.time()
                info = pc.write_sog(model, os.path.join(tmp, "m.sog"))
                seconds = time.time() - t
            finally:
                pc.palette_size = original
            back = pc.read_sog(os.path.join(tmp, "m.sog"))
            rows.append({"palette_rule": name, "palette": info["palette"], "bytes": info["bytes"],
                         "export_seconds": seconds, **scores(render_views(back, views), views, exact)})
    result = {"benchmark": "sog_palette", "date": datetime.date.today().isoformat(),
              "command": " ".join([os.path.relpath(sys.executable), *sys.argv]),
              "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__},
              "run_dir": os.path.abspath(args.run_dir), "splats": model.num_primitives,
              "sh_degree": int(model.sh_degree), "test_views": [v.name for v in views], "rows": rows,
              "seconds": time.time() - t0}
    write_record(f"sog_palette_{args.tag}", result, markdown)


def markdown(r: dict) -> str:
    lines = [f"# SOG's SH palette: PlayCanvas's size rule vs every distinct row ({r['date']})", "",
             f"Run `{r['run_dir']}` ({r['splats']} surfels, SH degree {r['sh_degree']}), test views "
             f"{', '.join(r['test_views'])}. Machine: {r['machine']['platform']}, {r['machine']['cpu_count']} CPUs.",
             f"Command: `{r['command']}` ({r['seconds']:.0f} s). Each .sog read back by ctgs.io.playcanvas.read_sog "
             "and drawn by our CPU renderer.", "",
             "| palette | entries | bytes | export s | test PSNR (dB) | PSNR vs exact (dB) |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for row in r["rows"]:
        lines.append(f"| {row['palette_rule']} | {row['palette']} | {row['bytes']} | {row['export_seconds']:.1f} | "
                     f"{row['psnr']:.2f} | {row['psnr_vs_exact']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
