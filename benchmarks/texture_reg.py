"""The texture regulariser's three forms on the demo scene -> benchmarks/results/texture_reg_<host>.{md,json}.

- centre: texels of primitives whose centre projects into the image (ctgs before issue 17; kept here only
  to measure it, by swapping ctgs.train.loss.rasterized_mask for it);
- rasterized: texels of the primitives the rasterizer keeps (the authors' release; ctgs' default);
- transmittance: rasterized, each primitive's L1 weighted by 1 - its mean transmittance in the view (the
  authors' README variant; config key texture_reg_transmittance).

Usage: .venv/bin/python benchmarks/texture_reg.py [--variants centre rasterized transmittance] [--seeds 0 1]
       [--width 192 --height 144 --views 24 --points 3000] [--work /tmp/ctgs_texreg] [--table-only]
Preset `fast` (the CPU recipe), CPU backend, 1 thread per training; invocations with disjoint --variants /
--seeds may run in parallel (the table is rebuilt from every run folder under --work).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

VARIANTS = ("centre", "rasterized", "transmittance")
PRESET = "fast"


def centre_mask(model, camera):
    """[N] bool: centre in front of the near plane and projecting inside the image (the replaced rule)."""
    import torch

    with torch.no_grad():
        vm = camera.viewmat.to(model.means.device, model.means.dtype)
        pc = model.means.detach() @ vm[:3, :3].T + vm[:3, 3]
        z = pc[:, 2]
        zs = z.clamp_min(1e-12)
        u = camera.fx * pc[:, 0] / zs + camera.cx
        v = camera.fy * pc[:, 1] / zs + camera.cy
        return (z > camera.near) & (u >= 0) & (u <= camera.width) & (v >= 0) & (v <= camera.height)


def run_one(scene: str, run_dir: str, variant: str, seed: int, backend: str, sets: tuple = ()) -> dict:
    import ctgs.train.loss as loss
    from ctgs.io.run_model import load_run
    from ctgs.stages.train import _load_scene, resolve_config
    from ctgs.train.allocation import texel_density_by_kind
    from ctgs.train.progress import run_with_progress
    from ctgs.train.run import write_config
    from ctgs.train.trainer import Trainer

    shutil.rmtree(run_dir, ignore_errors=True)
    tr = f"texture_reg_transmittance={'true' if variant == 'transmittance' else 'false'}"
    cfg = resolve_config(scene, run_dir, None, None, (f"seed={seed}", "threads=1", tr, *sets), None, False, backend,
                         None, preset=PRESET)
    trainer = Trainer(cfg, _load_scene(cfg), run_dir)
    write_config(run_dir, cfg.to_dict())
    kept = loss.rasterized_mask
    if variant == "centre":
        loss.rasterized_mask = centre_mask
    try:
        summary = run_with_progress(trainer, quiet=True)
    finally:
        loss.rasterized_mask = kept
    with open(os.path.join(scene, "demo_meta.json")) as fh:
        density = texel_density_by_kind(load_run(run_dir).model, json.load(fh))
    row = {"variant": variant, "seed": seed, **summary, "texels_per_area": density}
    with open(os.path.join(run_dir, "texture_reg_row.json"), "w") as fh:
        json.dump(row, fh, indent=1)
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--width", type=int, default=192)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--points", type=int, default=3000)
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--work", default="/tmp/ctgs_texreg")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="extra config override (smoke tests only: the recorded table uses none)")
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args()
    from ctgs.scene.demo import make_demo_scene

    scene = make_demo_scene(os.path.join(args.work, "scene"), num_views=args.views, width=args.width,
                            height=args.height, points=args.points)
    if not args.table_only:
        for seed in args.seeds:
            for variant in args.variants:
                row = run_one(scene, os.path.join(args.work, f"{variant}_s{seed}"), variant, seed, args.backend,
                              tuple(args.sets))
                print(json.dumps(row), flush=True)
    write_table(args)


def _commit() -> str:
    import subprocess

    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                       cwd=os.path.dirname(os.path.abspath(__file__)))
    return r.stdout.strip() or "unknown"


def write_table(args) -> None:
    rows = []
    for name in sorted(os.listdir(args.work)):
        path = os.path.join(args.work, name, "texture_reg_row.json")
        if os.path.isfile(path):
            with open(path) as fh:
                rows.append(json.load(fh))
    rows.sort(key=lambda r: (r["seed"], VARIANTS.index(r["variant"])))
    host = platform.node()
    meta = {"scene": f"demo scene {args.width}x{args.height}, {args.views} views (every 8th test), {args.points} "
                     "SfM points", "preset": PRESET, "commit": _commit(), "backend": args.backend, "threads": 1, "host": host,
            "machine": f"{platform.machine()}, {os.cpu_count()} cpus", "date": datetime.date.today().isoformat(), "extra_sets": args.sets,
            "command": "benchmarks/texture_reg.py " + " ".join(sys.argv[1:])}
    out = os.path.join("benchmarks", "results", f"texture_reg_{host}")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out + ".json", "w") as fh:
        json.dump({"meta": meta, "rows": rows}, fh, indent=1)
    lines = [f"# Texture regulariser forms ({meta['scene']})", "",
             f"Written by benchmarks/texture_reg.py on {meta['date']} ({host}, {meta['machine']}, commit {meta['commit']}); "
             f"preset {PRESET}, backend "
             f"{args.backend}, 1 thread per training (several in parallel on the 2 shared cores). centre = texels of primitives whose "
             "centre projects into the image (before issue 17); rasterized = primitives the rasterizer keeps (the "
             "authors' release, now the default); transmittance = rasterized, L1 weighted by 1 - mean transmittance "
             "(texture_reg_transmittance; one extra forward pass per iteration for the statistics, so its training "
             "time is not comparable). Test PSNR/SSIM: the run's final evaluation on the test views.", "",
             "| variant | seed | test PSNR | test SSIM | points | texels | params | texels/area photo : flat | train s |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        d = r["texels_per_area"]
        ratio = f"{d['photo'] / d['flat']:.1f}x" if d.get("flat") else "-"
        lines.append(f"| {r['variant']} | {r['seed']} | {r['final_test_psnr']:.2f} | {r['final_test_ssim']:.4f} | "
                     f"{r['num_primitives']} | {r['num_texels']} | {r['num_params']} | {ratio} | "
                     f"{r['train_seconds']:.0f} |")
    means = {}
    for r in rows:
        means.setdefault(r["variant"], []).append(r)
    if any(len(v) > 1 for v in means.values()):
        lines += ["", "Mean over seeds:", "", "| variant | seeds | test PSNR | params | texels |",
                  "| --- | --- | --- | --- | --- |"]
        for variant in VARIANTS:
            rs = means.get(variant, [])
            if rs:
                avg = lambda k: sum(r[k] for r in rs) / len(rs)  # noqa: E731
                lines.append(f"| {variant} | {len(rs)} | {avg('final_test_psnr'):.2f} | {avg('num_params'):.0f} | "
                             f"{avg('num_texels'):.0f} |")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
