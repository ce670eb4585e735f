"""The paper's claims on the demo scene, checked by training (`make bench-claims`; too long for `make test`).

Trains the content-aware method (the `fast` preset, two seeds) and, on the same preset, the baselines and the
paper's two experiments (2dgs, fixed_texture, higher_tau_ds, lower_tau_tr) on a demo scene, then measures
per surface kind (benchmarks/measures/allocation.py): the world-space texel size (median over
primitives and over texels), parameters and texels per unit area. Claims (issue: evidence):
  1. content-aware allocation: flat texels >= MIN_TEXEL_SIZE_RATIO x larger than photo texels (median over
     primitives, mean of the two seeds), and photo surfaces hold >= MIN_PARAMS_RATIO x the parameters per unit
     area of flat ones; fixed_texture does not reach the texel-size ratio;
  2. the default beats fixed_texture and a 2dgs holding at least as many parameters, in test PSNR.
Writes results/claims_<host>.{json,md}; exits 1 if a claim fails (the table is written either way).

Usage: .venv/bin/python benchmarks/claims.py [--work /tmp/ctgs_claims] [--width 192 --height 144]
       [--only default 2dgs ...] [--table-only]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

from ctgs.scene.demo import make_demo_scene  # noqa: E402
from ctgs.stages.train import train_main  # noqa: E402

# name -> (preset, config overlay, extra --set values)
RUNS = {
    "default": ("fast", None, ()),
    "default_seed1": ("fast", None, ("seed=1",)),
    "2dgs": ("fast", "2dgs", ()),
    "2dgs_more_params": ("fast", "2dgs", ("densify_grad_threshold=3e-5",)),
    "fixed_texture": ("fast", "fixed_texture", ()),
    "higher_tau_ds": ("fast", "higher_tau_ds", ()),
    "lower_tau_tr": ("fast", "lower_tau_tr", ()),
}
MIN_TEXEL_SIZE_RATIO = 4.0  # flat : photo world-space texel size, median over primitives
MIN_PARAMS_RATIO = 10.0  # photo : flat parameters per unit area


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default="/tmp/ctgs_claims")
    ap.add_argument("--width", type=int, default=192)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--points", type=int, default=3000)
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--tag", default="demo192x144", help="names the record")
    args = ap.parse_args()
    scene = make_demo_scene(os.path.join(args.work, "scene"), num_views=args.views, width=args.width,
                            height=args.height, points=args.points)
    for name, (preset, config, sets) in RUNS.items():
        run = os.path.join(args.work, name)
        if args.table_only or (args.only and name not in args.only):
            continue
        if os.path.exists(os.path.join(run, "train_summary.json")):
            continue
        resume = os.path.exists(os.path.join(run, "checkpoints", "last.pt"))
        train_main(scene, run, preset=preset, config=config, sets=sets + ("threads=1", "backend='cpu'"),
                   resume=resume, quiet=True)
    rows = table_rows(args.work, scene)
    verdict = check(rows)
    write(rows, verdict, args)
    print(json.dumps(verdict, indent=1))
    return 0 if all(v["ok"] for v in verdict.values()) else 1


def table_rows(work: str, scene: str) -> dict:
    from ctgs.runs import load_run
    from measures.allocation import allocation_measures

    meta = json.load(open(os.path.join(scene, "demo_meta.json")))
    rows = {}
    for name in RUNS:
        path = os.path.join(work, name, "train_summary.json")
        if not os.path.exists(path):
            continue
        model = load_run(os.path.join(work, name)).model
        rows[name] = {"summary": json.load(open(path)), "allocation": allocation_measures(model, meta)}
    return rows


def check(rows: dict) -> dict:
    out = {}
    need = ("default", "default_seed1")
    if all(n in rows for n in need):
        r = [rows[n]["allocation"]["ratios"] for n in need]
        ts = sum(x["texel_size_prim_flat_over_photo"] for x in r) / 2
        pa = sum(x["params_per_area_photo_over_flat"] for x in r) / 2
        out["texel_size_ratio_default"] = {"value": ts, "goal": f">= {MIN_TEXEL_SIZE_RATIO}", "ok": ts >= MIN_TEXEL_SIZE_RATIO}
        out["params_per_area_ratio_default"] = {"value": pa, "goal": f">= {MIN_PARAMS_RATIO}", "ok": pa >= MIN_PARAMS_RATIO}
    if "fixed_texture" in rows:
        ft = rows["fixed_texture"]["allocation"]["ratios"]["texel_size_prim_flat_over_photo"]
        out["fixed_texture_below_texel_size_ratio"] = {"value": ft, "goal": f"< {MIN_TEXEL_SIZE_RATIO}",
                                                        "ok": not ft >= MIN_TEXEL_SIZE_RATIO}
    if "default" in rows:
        d = rows["default"]["summary"]
        for other in ("fixed_texture", "2dgs_more_params"):
            if other in rows:
                o = rows[other]["summary"]
                ok = d["final_test_psnr"] > o["final_test_psnr"]
                if other.startswith("2dgs"):
                    ok = ok and o["num_params"] >= d["num_params"]
                out[f"default_beats_{other}"] = {
                    "value": f"{d['final_test_psnr']:.2f} dB / {d['num_params']} params vs "
                             f"{o['final_test_psnr']:.2f} dB / {o['num_params']} params",
                    "goal": "higher test PSNR" + (" with no more params" if other.startswith("2dgs") else ""),
                    "ok": ok}
    return out


def write(rows: dict, verdict: dict, args) -> None:
    out = record.stem("claims", args.tag)
    meta = {"scene": f"demo {args.width}x{args.height}, {args.views} views (every 8th test), {args.points} points",
            "command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"),
            "machine": f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"}
    with open(out + ".json", "w") as fh:
        json.dump({"meta": meta, "rows": rows, "verdict": verdict}, fh, indent=1)
    lines = [f"# Claims on the demo scene ({meta['scene']})", "",
             f"`{meta['command']}` on {meta['machine']}, {meta['date']}; CPU backend, 1 thread per training. "
             "Every run uses the `fast` preset (3000 iterations) with the named overlay. Texel size = world-space "
             "texel size (k_min x 2^t2p_exp; fixed_texture: its grid spacing), median over primitives (prim) and "
             "over texels (texel), flat : photo. Params/area and texels/area: photo : flat (primitives counted on "
             "the surface of their centre; 59 params per primitive + 3 per texel).", "",
             "| config | test PSNR | SSIM | points | texels | params | train s | texel size flat:photo (prim) | "
             "(texel) | params/area photo:flat | texels/area photo:flat |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in rows.items():
        s, a = r["summary"], r["allocation"]["ratios"]
        lines.append(f"| {name} | {s['final_test_psnr']:.2f} | {s['final_test_ssim']:.4f} | {s['num_primitives']} | "
                     f"{s['num_texels']} | {s['num_params']} | {s['train_seconds']:.0f} | "
                     f"{a['texel_size_prim_flat_over_photo']:.2f} | {a['texel_size_texel_flat_over_photo']:.2f} | "
                     f"{a['params_per_area_photo_over_flat']:.2f} | {a['texels_per_area_photo_over_flat']:.2f} |")
    lines += ["", "| claim | measured | goal | holds |", "| --- | --- | --- | --- |"]
    for k, v in verdict.items():
        val = f"{v['value']:.2f}" if isinstance(v["value"], float) else v["value"]
        lines.append(f"| {k} | {val} | {v['goal']} | {'yes' if v['ok'] else 'NO'} |")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
