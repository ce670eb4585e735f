"""Surface accuracy of trained runs on the demo scene, grouped over seeds: each run meshed by `ctgs mesh`'s pipeline
with the median and the expected (mean) depth, scored against the exact surfaces, beside its novel-view scores and size.

    .venv/bin/python benchmarks/surface_accuracy.py --group content-aware=runs/ca_s0,runs/ca_s1,runs/ca_s2 \\
        --group 2dgs=runs/2dgs_s0,runs/2dgs_s1,runs/2dgs_s2 --tag demo192x144_3000it_3seeds --resolution 256

Per run: Chamfer distance, accuracy / completeness, normal consistency and F-score at 1, 2 and 5 cm
(measures/mesh_accuracy.py) of the mesh fused from each depth (--depths), at --resolution voxels across the scene
extent; the run's final PSNR / SSIM on its held-out views (test views, or validation views for a run trained with
validation_holdout), primitives and parameters (train_summary.json); and what the depth maps are made of
(surface_diagnosis.py: the median and expected depths' errors, the spread of the blended depths). Per group: the mean
and standard deviation over its runs.
Record: benchmarks/results/surface_accuracy/<tag>_<commit>.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from profile_train import machine  # noqa: E402
from record import stem, write_record  # noqa: E402

FIGURES = ("chamfer", "accuracy", "completeness", "normal_consistency", "f1", "f2", "f5")


def mesh_scores(run, cameras, depth: str, resolution: int) -> dict:
    # loaded when a run is scored (--help and a cached rerun need neither ctgs's renderer nor the measures)
    from ctgs.fusion.pipeline import MeshOptions, extract, fuse, plan_volume
    from measures.demo_surfaces import load_demo_meta
    from measures.mesh_accuracy import mesh_accuracy

    start = time.perf_counter()
    opts = MeshOptions(resolution=resolution, depth=depth)
    plan = plan_volume(run.model, cameras, None, opts, "cpu")
    mesh, _ = extract(fuse(run.model, cameras, plan, "cpu"), opts.pieces)
    a = mesh_accuracy(mesh.vertices, mesh.faces, load_demo_meta(run.scene_dir), cameras)
    return {"voxel": plan.domain.voxel, "triangles": mesh.num_faces, "seconds": round(time.perf_counter() - start, 1),
            "chamfer": a["chamfer"], "accuracy": a["accuracy"], "completeness": a["completeness"],
            "normal_consistency": a["normal_consistency"], "f1": a["fscore"]["0.01"]["f"],
            "f2": a["fscore"]["0.02"]["f"], "f5": a["fscore"]["0.05"]["f"]}


def score_run(run_dir: str, depths: list[str], resolution: int) -> dict:
    # loaded when a run is scored (--help and a cached rerun need neither ctgs's renderer nor the measures)
    from ctgs.runs import load_run
    from ctgs.scene.loader import load_scene
    from surface_diagnosis import diagnose

    run = load_run(run_dir)
    cameras = [v.camera for v in load_scene(run.scene_dir, images=run.images, holdout=run.holdout,
                                            load_images=False).train]
    summary = run.summary or {}
    cfg = run.config or {}
    out = {"run": run_dir, "psnr": summary.get("final_test_psnr"), "ssim": summary.get("final_test_ssim"),
           "views": (summary.get("eval_peak") or {}).get("views", "test"),
           "primitives": run.model.num_primitives, "params": run.model.num_params(),
           "train_seconds": summary.get("train_seconds"), "method": cfg.get("method"),
           "lambda_normal": cfg.get("lambda_normal"), "lambda_dist": cfg.get("lambda_dist"), "mesh": {}}
    for depth in depths:
        out["mesh"][depth] = mesh_scores(run, cameras, depth, resolution)
    d = diagnose(run_dir)
    out["depth_maps"] = {k: d["pixels"]["all"][k] for k in ("expected_depth_error_median_cm",
                                                             "median_depth_error_median_cm", "spread_median_cm",
                                                             "weight_near")}
    return out


def stats(values: list) -> dict:
    v = np.array([x for x in values if x is not None], float)
    return {"mean": float(v.mean()) if len(v) else None, "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "n": int(len(v))}


def aggregate(runs: list[dict], depths: list[str]) -> dict:
    agg = {k: stats([r[k] for r in runs]) for k in ("psnr", "ssim", "primitives", "params", "train_seconds")}
    for depth in depths:
        agg[depth] = {k: stats([r["mesh"][depth][k] for r in runs]) for k in FIGURES}
    agg["depth_maps"] = {k: stats([r["depth_maps"][k] for r in runs]) for k in runs[0]["depth_maps"]}
    return agg


def _ms(s: dict, scale: float = 1.0, digits: int = 2) -> str:
    if s["mean"] is None:
        return "-"
    return f"{scale * s['mean']:.{digits}f} ± {scale * s['sd']:.{digits}f}"


def markdown(r: dict) -> str:
    lines = [f"# Surface accuracy: {r['tag']}", "", f"{r['date']}, commit {r['commit']}, {r['machine']['cpu']} "
             f"({r['machine']['cores']} cores), load average {r.get('loadavg_start')} at the start, "
             f"{r.get('loadavg_end')} at the end.", "", f"Command: `{r['command']}`", "",
             *([r["note"], ""] if r.get("note") else []),
             f"Meshes: `ctgs mesh`'s pipeline at --resolution {r['resolution']} (voxels of "
             f"{100 * r['voxel']:.2f} cm), every training view fused; mean ± sd over each group's runs (n).", ""]
    for depth in r["depths"]:
        lines += [f"Fused depth: **{depth}**", "",
                  "| group | n | Chamfer (cm) | accuracy / completeness (cm) | normal consistency | F@1cm | F@2cm | "
                  "F@5cm | PSNR (dB) | SSIM | primitives | parameters |",
                  "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for label, g in r["groups"].items():
            a = g["aggregate"]
            m = a[depth]
            lines.append(f"| {label} | {a['psnr']['n']} | {_ms(m['chamfer'], 100)} | "
                         f"{_ms(m['accuracy'], 100)} / {_ms(m['completeness'], 100)} | "
                         f"{_ms(m['normal_consistency'], 1, 3)} | {_ms(m['f1'], 1, 3)} | {_ms(m['f2'], 1, 3)} | "
                         f"{_ms(m['f5'], 1, 3)} | {_ms(a['psnr'])} | {_ms(a['ssim'], 1, 3)} | "
                         f"{_ms(a['primitives'], 1, 0)} | {_ms(a['params'], 1, 0)} |")
        lines.append("")
    lines += ["What the depth maps are made of (every training view; surface_diagnosis.py), cm:", "",
              "| group | expected depth error, median | median depth error, median | spread of the blended depths, "
              "median | weight within 2 cm of the surface | training s |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for label, g in r["groups"].items():
        d = g["aggregate"]["depth_maps"]
        lines.append(f"| {label} | {_ms(d['expected_depth_error_median_cm'])} | "
                     f"{_ms(d['median_depth_error_median_cm'])} | {_ms(d['spread_median_cm'], 1, 1)} | "
                     f"{_ms(d['weight_near'], 1, 3)} | {_ms(g['aggregate']['train_seconds'], 1, 0)} |")
    lines += ["", "PSNR / SSIM: each run's final scores on its held-out views ("
              + ", ".join(sorted({run['views'] for g in r['groups'].values() for run in g['runs']})) + ")."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--group", action="append", required=True, metavar="LABEL=RUN[,RUN...]")
    ap.add_argument("--tag", required=True, help="record name (scene, resolution, variant)")
    ap.add_argument("--resolution", type=int, default=256, help="voxels across the scene extent")
    ap.add_argument("--depths", nargs="+", default=["median", "mean"], choices=["median", "mean"])
    ap.add_argument("--note", default="", help="a line for the record (how the runs were trained)")
    ap.add_argument("--cache", default=None, help="folder keeping each run's scores (a rerun reads them back)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    path_stem = stem("surface_accuracy", args.tag)
    result = {"tag": args.tag, "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "commit": os.path.basename(path_stem).rsplit("_", 1)[1], "machine": machine(),
              "loadavg_start": [round(x, 2) for x in os.getloadavg()],
              "command": shlex.join(["benchmarks/surface_accuracy.py", *sys.argv[1:]]), "note": args.note,
              "resolution": args.resolution, "depths": args.depths, "groups": {}}
    for item in args.group:
        label, runs = item.split("=", 1)
        scored = []
        for run_dir in runs.split(","):
            key = f"{os.path.abspath(run_dir).strip('/').replace('/', '_')}_{args.resolution}_{'_'.join(args.depths)}"
            cached = os.path.join(args.cache, key + ".json") if args.cache else None
            if cached and os.path.isfile(cached):
                with open(cached) as f:
                    scored.append(json.load(f))
            else:
                scored.append(score_run(run_dir, args.depths, args.resolution))
                if cached:
                    os.makedirs(args.cache, exist_ok=True)
                    with open(cached, "w") as f:
                        json.dump(scored[-1], f)
            print(json.dumps({"group": label, "run": run_dir, **{d: scored[-1]["mesh"][d]["chamfer"]
                                                                   for d in args.depths}}), flush=True)
        result["groups"][label] = {"runs": scored, "aggregate": aggregate(scored, args.depths)}
    result["voxel"] = next(iter(result["groups"].values()))["runs"][0]["mesh"][args.depths[0]]["voxel"]
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    write_record(path_stem, result, markdown)


if __name__ == "__main__":
    main()
