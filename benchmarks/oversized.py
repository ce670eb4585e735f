"""Oversized primitives in finished runs: how many there are, and what they cost each view.

A surfel is blended in the order of its centre's camera depth (docs/renderer.md). A surfel many times larger
than the scene whose centre lies far to the side of a camera, at a small depth, is blended *before* the
surface it crosses in that camera's image: a semi-transparent veil over the whole view. Session 27 found one
(`benchmarks/results/blame_herzjesu25_192_fast_s2_view0008_vm27.md`: scale 100 in a scene of extent 6.6,
+5.6 dB on one test view when removed). This counts, for each run, the primitives whose largest scale exceeds
each of --factors x the scene extent (the trainer's, 3DGS's camera extent), and for those above the largest factor given
(--drop, default 1.0) reports the PSNR of every training view and every test view with them removed against the
run as it is, and their summed blending weight in both.

A diagnosis of finished runs: the test views are measured, nothing is chosen from them here.

Usage: .venv/bin/python benchmarks/oversized.py RUN [RUN ...] --out NAME [--factors 0.1 0.5 1 5] [--drop 1.0]
Writes benchmarks/results/oversized_NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def survey(run_dir: str, factors: list[float], drop: float) -> dict:
    import torch

    from ctgs.io.run_model import load_run
    from ctgs.metrics.evaluate import outside_share
    from ctgs.metrics.psnr import psnr
    from ctgs.render.api import render
    from ctgs.scene import load_scene

    run = load_run(run_dir)
    model = run.model
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    inp = model.render_inputs()  # the caller holds torch.no_grad(): no graph
    deg = model.sh_degree
    extent = scene.extent  # the trainer's: 1.1 x the largest distance of a camera centre from their mean
    max_scale = model.scales.max(1).values
    counts = {str(f): int((max_scale > f * extent).sum()) for f in factors}
    big = max_scale > drop * extent
    without = dataclasses.replace(inp, opacities=torch.where(big, torch.zeros_like(inp.opacities), inp.opacities))

    def per_view(views):
        rows = []
        for v in views:
            gt = torch.from_numpy(v.image)
            out = render(inp, v.camera, sh_degree=deg, error_image=torch.zeros(v.camera.height, v.camera.width))
            w = float(out.stats.contrib.float()[big].sum()) if bool(big.any()) else 0.0
            a = psnr(out.rgb.clamp(0, 1), gt)
            b = psnr(render(without, v.camera, sh_degree=deg).rgb.clamp(0, 1), gt) if bool(big.any()) else a
            rows.append({"view": v.name, "psnr": a, "psnr_without": b, "weight_px": w,
                         "pixels": v.camera.width * v.camera.height,
                         "veil": outside_share(out.stats.contrib, inp.means, v.camera)})
        return rows

    train, test = per_view(scene.train), per_view(scene.test)
    return {"run": os.path.abspath(run_dir), "primitives": model.num_primitives, "extent": extent,
            "counts": counts, "drop_factor": drop, "dropped": int(big.sum()),
            "dropped_scales": sorted((float(s) for s in max_scale[big]), reverse=True)[:10],
            "dropped_opacities": [float(o) for o in inp.opacities[big][:10]],
            "train": train, "test": test}


def _mean(rows, key):
    return sum(r[key] for r in rows) / max(1, len(rows))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("--factors", type=float, nargs="+", default=[0.1, 0.5, 1.0, 5.0])
    ap.add_argument("--drop", type=float, default=1.0, help="remove the primitives above this x extent")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    t0 = time.time()
    with torch.no_grad():
        res = [survey(r, args.factors, args.drop) for r in args.runs]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    machine = f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"
    meta = {"command": "benchmarks/oversized.py " + " ".join(sys.argv[1:]), "date": time.strftime("%Y-%m-%d %H:%M"),
            "commit": commit, "machine": machine, "seconds": time.time() - t0}
    out = os.path.join(ROOT, "benchmarks", "results", f"oversized_{args.out}")
    with open(out + ".json.tmp", "w") as fh:
        json.dump({**meta, "runs": res}, fh, indent=1)
    os.replace(out + ".json.tmp", out + ".json")
    fl = [str(f) for f in args.factors]
    lines = [f"# Oversized primitives ({machine})", "",
             f"Command: `{meta['command']}` on {meta['date']}, commit {commit}. Counts: primitives whose largest "
             f"scale exceeds the factor x the scene extent (the trainer's: 3DGS's camera extent over every camera). 'Removed': those above "
             f"{args.drop} x extent set to opacity 0; PSNR of the run as it is -> without them, mean over the "
             "views, and the worst single-view change; weight: their summed blending weight (sum of alpha T) as a "
             "share of the view's pixels, largest over the views. Veil: `ctgs eval`'s measure (the largest share of a "
             "view's blending weight that one primitive centred outside the view carries), largest over the training "
             "views, and per test view. A diagnosis: nothing is chosen from it.", "",
             "| run | primitives | extent | " + " | ".join(f"> {f}x" for f in fl) +
             " | removed | their scales | train PSNR -> without | largest train weight | test PSNR -> without | "
             "best test-view gain | largest test weight | veil, train max | veil per test view |",
             "| --- | ---: | ---: | " + " | ".join("---:" for _ in fl) + " | ---: | --- | --- | ---: | --- | --- | ---: | ---: | --- |"]
    for r in res:
        tr, te = r["train"], r["test"]
        gains = [(x["psnr_without"] - x["psnr"], x["view"]) for x in te]
        g, gv = max(gains)
        wtr = max(x["weight_px"] / x["pixels"] for x in tr)
        wte = max(x["weight_px"] / x["pixels"] for x in te)
        sc = ", ".join(f"{s:.1f}" for s in r["dropped_scales"][:4]) or "-"
        name = os.path.relpath(r["run"], os.path.dirname(os.path.dirname(r["run"])))
        lines.append(f"| `{name}` | {r['primitives']} | {r['extent']:.2f} | " +
                     " | ".join(str(r["counts"][f]) for f in fl) +
                     f" | {r['dropped']} | {sc} | {_mean(tr, 'psnr'):.2f} -> {_mean(tr, 'psnr_without'):.2f} | "
                     f"{100 * wtr:.1f}% | {_mean(te, 'psnr'):.2f} -> {_mean(te, 'psnr_without'):.2f} | "
                     f"{g:+.2f} dB ({gv}) | {100 * wte:.1f}% | {max(x['veil'] for x in tr):.3f} | "
                     + " / ".join(f"{x['veil']:.3f}" for x in te) + " |")
    lines.append("")
    with open(out + ".md.tmp", "w") as fh:
        fh.write("\n".join(lines))
    os.replace(out + ".md.tmp", out + ".md")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
