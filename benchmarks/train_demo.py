"""Train default / 2dgs / fixed_texture / higher_tau_ds / lower_tau_tr on a small demo scene and record
the table of issue 4 in benchmarks/results/train_demo_<host>.{md,json}.

Usage: .venv/bin/python benchmarks/train_demo.py [--width 96 --height 72 --views 24 --points 1500]
(the demo-scene configs: configs/demo*.toml, 1000 iterations, CPU backend, 1 thread).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from pipeline.scene.demo import make_demo_scene  # noqa: E402
from pipeline.stages.train import train_main  # noqa: E402

RUNS = [("default", "configs/demo.toml"), ("2dgs", "configs/demo_2dgs.toml"),
        ("2dgs_equal_params", "configs/demo_2dgs.toml"),
        ("fixed_texture", "configs/demo_fixed_texture.toml"), ("higher_tau_ds", "configs/demo_higher_tau_ds.toml"),
        ("lower_tau_tr", "configs/demo_lower_tau_tr.toml")]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=72)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--points", type=int, default=1500)
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--work", default="/tmp/ctgs_bench")
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--table-only", action="store_true", help="only rebuild the table from the run folders")
    args = ap.parse_args()
    scene = make_demo_scene(os.path.join(args.work, "scene"), num_views=args.views, width=args.width,
                            height=args.height, points=args.points)
    host = platform.node()
    out_json = os.path.join("benchmarks", "results", f"train_demo_{host}.json")
    for name, cfg in RUNS:
        if args.table_only or (args.only and name not in args.only):
            continue
        run_dir = os.path.join(args.work, name)
        shutil.rmtree(run_dir, ignore_errors=True)
        sets = ()
        if name == "2dgs_equal_params":  # 2DGS capped at the default run's parameter count
            with open(os.path.join(args.work, "default", "train_summary.json")) as fh:
                sets = (f"max_primitives={json.load(fh)['num_params'] // 58}",)
        s = train_main(scene, run_dir, config=cfg, sets=sets, backend=args.backend, quiet=True)
        print(json.dumps({"config": name, **s}), flush=True)
    rows = []
    for name, cfg in RUNS:  # the table is rebuilt from the run folders (parallel invocations are fine)
        path = os.path.join(args.work, name, "train_summary.json")
        if os.path.exists(path):
            with open(path) as fh:
                row = {"config": name, "config_file": cfg, **json.load(fh)}
            row["texels_per_area"] = texel_density(os.path.join(args.work, name), scene)
            rows.append(row)
    write(rows, args, host, out_json)


NOTES = """Notes (recorded by hand from the runs of 2026-11-21, same scene and machine):
- Before configs/demo.toml raised lr_texture to 7e-3, the default reached 20.16 dB / SSIM 0.695 with
  2857 points, 29,944 texels, 258,395 params, and 2dgs capped to that budget (4375 points, 253,750
  params) reached 21.47 dB: at equal parameters on this tiny scene 2DGS won. With lr_texture 7e-3 the
  default wins in PSNR but spends more parameters than uncapped 2dgs (2.1M vs 0.9M).
- texels/area: allocated texels of primitives lying on photo-textured vs flat surfaces divided by those
  surfaces' area (pipeline/train/allocation.py); the issue asks for >= 10x, these runs reach 2.5-6.4x.
- fixed_texture edges out the default in PSNR (+0.09 dB) with 8.6x the parameters; the default has the
  higher SSIM."""


def texel_density(run_dir: str, scene: str) -> dict:
    """Texels per unit area on photo / flat / smooth demo surfaces (pipeline.train.allocation)."""
    from pipeline.train.allocation import texel_density_by_kind
    from pipeline.train.run import load_run

    model, _ = load_run(run_dir)
    with open(os.path.join(scene, "demo_meta.json")) as fh:
        return texel_density_by_kind(model, json.load(fh))


def write(rows, args, host, out_json) -> None:
    os.makedirs(os.path.dirname(out_json), exist_ok=True)
    meta = {"scene": f"demo scene {args.width}x{args.height}, {args.views} views (every 8th test), "
                     f"{args.points} SfM points", "host": host}
    with open(out_json, "w") as fh:
        json.dump({"meta": meta, "rows": rows}, fh, indent=1)
    lines = [f"# Training on the demo scene ({meta['scene']})", "",
             "Configs: configs/demo*.toml (1000 iterations, paper schedule x 0.04, tau_tr scaled to the image "
             "size). Params = 59/primitive (58 for 2dgs) + 3/texel. 2dgs_equal_params (when present): 2dgs "
             "with max_primitives = default params / 58. Training seconds on a 2-core machine shared with other jobs (noisy).", "",
             "| config | test PSNR | test SSIM | points | texels | params | train s | texels/area photo : flat | backend | machine |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['config']} | {r['final_test_psnr']:.2f} | {r['final_test_ssim']:.4f} | "
                     f"{r['num_primitives']} | {r['num_texels']} | {r['num_params']} | {r['train_seconds']:.0f} | "
                     f"{r['texels_per_area'].get('photo', 0):.0f} : {r['texels_per_area'].get('flat', 0):.0f} | "
                     f"{r['backend']} | {r['machine']} |")
    lines += ["", NOTES]
    with open(out_json[:-5] + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
