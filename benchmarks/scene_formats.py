"""A real capture trained from another scene layout: `ctgs convert` writes a COLMAP scene as nerfstudio's
transforms.json, then the same short training runs from the transforms.json and from the COLMAP scene, and
`ctgs eval` scores both on the same test views.

    .venv/bin/python benchmarks/scene_formats.py SCENE_DIR [--images images_8] [--preset preview] [--iterations N]
        [--work DIR] [--no-lpips] [--name NAME]

What it reports (benchmarks/results/scene_formats/<name>_<commit>.{json,md}): the conversion (views, points, seconds,
bytes written), and for each layout the training's iterations, seconds, primitives, parameters and the test PSNR /
SSIM / LPIPS of `ctgs eval`, with the machine, the command and the date. The two trainings run one after the other
with one thread each (`--set threads=1`), the same seed and settings: the layouts should give the same model within
the noise of a training run.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

import record
from sfm_accuracy import machine_info

CTGS = [sys.executable, "-m", "ctgs"]


def _run(args: list[str]) -> float:
    """Run a ctgs command; its wall seconds. Its output is passed through."""
    start = time.perf_counter()
    subprocess.run(CTGS + args, check=True)
    return time.perf_counter() - start


def _bytes(folder: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(folder) for f in files)


def _layout_run(scene: str, work: str, label: str, args) -> dict:
    run = os.path.join(work, f"run_{label}")
    train = ["train", scene, "-o", run, "--images", args.images, "--preset", args.preset, "--seed", "0",
             "--set", "threads=1", "-q"] + (["--iterations", str(args.iterations)] if args.iterations else [])
    wall = _run(train)
    evaluate = ["eval", run, "-o", os.path.join(work, f"eval_{label}")] + (["--no-lpips"] if args.no_lpips else [])
    _run(evaluate)
    with open(os.path.join(work, f"eval_{label}", "metrics.json")) as f:
        m = json.load(f)
    with open(os.path.join(run, "train_summary.json")) as f:
        s = json.load(f)
    return {"scene_dir": scene, "train_command": "ctgs " + shlex.join(train), "train_wall_s": round(wall, 1),
            "iterations": s["iterations"], "train_seconds": round(s["train_seconds"], 1),
            "primitives": m["points"], "texels": m["texels"], "params": m["params"], "psnr": m["psnr"],
            "ssim": m["ssim"], "lpips": m["lpips"], "test_views": m["num_views"], "resolution": m["resolution"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", help="a COLMAP scene folder (sparse/0, images/)")
    ap.add_argument("--images", default="images_8", help="image level both trainings read (default images_8)")
    ap.add_argument("--preset", default="preview")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--work", default=None, help="folder for the converted scene, runs and evals (default: a "
                                                 "temporary folder, removed)")
    ap.add_argument("--no-lpips", action="store_true")
    ap.add_argument("--name", default=None, help="record name (default <scene>_<images>_<preset>)")
    args = ap.parse_args()

    scene = os.path.abspath(args.scene)
    commit = record.commit()  # the code that runs: the record is named by it, whatever is committed meanwhile
    work = args.work or tempfile.mkdtemp(prefix="scene_formats-")
    os.makedirs(work, exist_ok=True)
    converted = os.path.join(work, "nerfstudio")
    convert = ["convert", scene, "--to", "nerfstudio", "-o", converted]
    convert_s = _run(convert)
    with open(os.path.join(converted, "transforms.json")) as f:
        doc = json.load(f)
    result = {
        "tool": "scene_formats", "commit": commit, "command": " ".join(sys.argv),
        "scene": os.path.basename(scene), "images": args.images, "preset": args.preset,
        "conversion": {"command": "ctgs " + shlex.join(convert), "seconds": round(convert_s, 1),
                       "views": len(doc["frames"]), "bytes": _bytes(converted),
                       "points_file": doc.get("ply_file_path"), "camera_model": doc.get("camera_model"),
                       "levels": sorted(d for d in os.listdir(converted) if d.startswith("images_"))},
        "runs": {"transforms.json": _layout_run(converted, work, "nerfstudio", args),
                 "colmap": _layout_run(scene, work, "colmap", args)},
        "machine": machine_info(),
    }
    name = args.name or f"{os.path.basename(scene)}_{args.images}_{args.preset}"
    record.write_record(record.stem("scene_formats", f"{name}_{commit}"), result, markdown)
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def markdown(r: dict) -> str:
    c, m = r["conversion"], r["machine"]
    lines = [f"# {r['scene']} trained from a transforms.json and from its COLMAP scene ({m['date_utc'][:10]})", "",
             f"`{r['command']}` at commit {r['commit']}, {m['cpu_model']} ({m['logical_cores']} logical cores), "
             f"load average {m['load_average']} at the end, {m['date_utc']}.", "",
             f"Conversion: `{c['command']}`: {c['views']} views, points in {c['points_file']}, levels "
             f"{', '.join(c['levels']) or 'none'}, {c['bytes'] / 1e6:.1f} MB written in {c['seconds']:.1f} s.", "",
             "| layout | resolution | iterations | train s | primitives | params | test views | PSNR (dB) | SSIM "
             "| LPIPS |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, run in r["runs"].items():
        lp = f"{run['lpips']:.3f}" if run["lpips"] is not None else "n/a"
        lines.append(f"| {label} | {run['resolution'][0]}x{run['resolution'][1]} | {run['iterations']} | "
                     f"{run['train_seconds']:.0f} | {run['primitives']} | {run['params']} | {run['test_views']} | "
                     f"{run['psnr']:.2f} | {run['ssim']:.3f} | {lp} |")
    lines += ["", "Training commands:", ""]
    lines += [f"- {label}: `{run['train_command']}`" for label, run in r["runs"].items()]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
