"""Two SfM results of one capture, trained the same way side by side: does the faster scene train as well?

    .venv/bin/python benchmarks/sfm_train_check.py SCENE_A SCENE_B --scene NAME [--labels present,new]
        [--images images_4] [--preset fast] [--time-budget 10 | --iterations N] [--seed 0] [--photos-of-a]
        [--work DIR] [--note TEXT ...]

Both scenes get the same command, `ctgs train SCENE -o RUN --images IMAGES --preset PRESET --time-budget MIN
--seed S --set threads=1 -q`, started together (one thread each, so that both share the machine's load), then
`ctgs eval RUN` scores each on its scene's test views: a scene's `test_views.txt` when it has one (copy the same
file into both), else every 8th photo by name. The record gives each run's PSNR / SSIM / LPIPS, iterations,
primitives, and B minus A.

--photos-of-a trains B's cameras on A's photos. Where B was made by `ctgs sfm` from A's undistorted `images/`,
B's photos are A's resampled once more (undistortion to a pixel smaller, a centred crop, and a JPEG pass): its test
photos are smoother, and scores on them are not comparable with A's (bonsai252: +1.1 dB for the same training).
The scene WORK/<scene>_<B>_cameras_on_<A>_photos links A's image folders (and test_views.txt) and holds B's model
with each PINHOLE camera moved to A's image size about its centre (focal length kept, the principal point shifted by
half the size difference), so that both runs are scored on the same photos and differ only in the cameras (and the
points they start from).

Record: benchmarks/results/sfm_train_check/<scene>_<images>_<preset>_<minutes>min|<N>it[_photos_of_a]_<commit>.json
and .md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "benchmarks"))
import record  # noqa: E402
from sfm_accuracy import machine_info  # noqa: E402

CTGS = [sys.executable, "-m", "ctgs"]


def _train_command(scene: str, run: str, args) -> list[str]:
    length = ["--iterations", str(args.iterations)] if args.iterations else ["--time-budget", str(args.time_budget)]
    return ["train", scene, "-o", run, "--images", args.images, "--preset", args.preset, *length,
            "--seed", str(args.seed), "--set", "threads=1", "-q"]


def cameras_on_photos(scene_a: str, scene_b: str, out: str) -> str:
    """A scene of A's photos with B's cameras and points (--photos-of-a); returns its folder."""
    import pycolmap  # only this option reads COLMAP models here

    size = {(c.width, c.height) for c in pycolmap.Reconstruction(os.path.join(scene_a, "sparse", "0")).cameras.values()}
    if len(size) != 1:
        raise SystemExit(f"{scene_a}: --photos-of-a needs one image size, found {sorted(size)}")
    (width, height), = size
    rec = pycolmap.Reconstruction(os.path.join(scene_b, "sparse", "0"))
    for cam in rec.cameras.values():
        if cam.model_name != "PINHOLE":
            raise SystemExit(f"{scene_b}: --photos-of-a needs PINHOLE cameras, found {cam.model_name}")
        fx, fy, cx, cy = cam.params
        cam.params = [fx, fy, cx + (width - cam.width) / 2, cy + (height - cam.height) / 2]
        cam.width, cam.height = width, height
    if os.path.exists(out):
        shutil.rmtree(out)
    os.makedirs(os.path.join(out, "sparse", "0"))
    rec.write_binary(os.path.join(out, "sparse", "0"))
    for entry in sorted(os.listdir(scene_a)):
        if entry.startswith("images") or entry == "test_views.txt":
            os.symlink(os.path.join(scene_a, entry), os.path.join(out, entry))
    return out


def _summary(run: str, evaluation: str) -> dict:
    with open(os.path.join(evaluation, "metrics.json")) as f:
        m = json.load(f)
    with open(os.path.join(run, "train_summary.json")) as f:
        s = json.load(f)
    return {"iterations": s["iterations"], "train_seconds": round(s["train_seconds"], 1), "primitives": m["points"],
            "params": m["params"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
            "test_views": m["num_views"], "resolution": m["resolution"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene_a")
    ap.add_argument("scene_b")
    ap.add_argument("--scene", required=True, help="the capture's name in the record's name")
    ap.add_argument("--labels", default="present,new", help="names of the two scenes, A,B")
    ap.add_argument("--images", default="images_4")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--time-budget", type=float, default=10.0, help="minutes of each training")
    ap.add_argument("--iterations", type=int, default=0, help="a fixed length instead of --time-budget")
    ap.add_argument("--photos-of-a", action="store_true", help="train B's cameras on A's photos (see above)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default="/tmp/sfm_train_check")
    ap.add_argument("--note", action="append", default=[])
    args = ap.parse_args()
    labels = args.labels.split(",")
    scenes = [os.path.abspath(args.scene_a), os.path.abspath(args.scene_b)]
    os.makedirs(args.work, exist_ok=True)
    if args.photos_of_a:
        scenes[1] = cameras_on_photos(scenes[0], scenes[1],
                                      os.path.join(args.work, f"{args.scene}_{labels[1]}_cameras_on_{labels[0]}_photos"))
    commit = record.commit()
    runs = [os.path.join(args.work, f"{args.scene}_{label}") for label in labels]
    commands = [_train_command(scene, run, args) for scene, run in zip(scenes, runs)]
    load_start, date = list(os.getloadavg()), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    procs = [subprocess.Popen(CTGS + cmd, cwd=REPO) for cmd in commands]
    codes = [p.wait() for p in procs]
    if any(codes):
        print(f"a training failed: exit codes {codes}", file=sys.stderr)
        return 1
    results = {}
    for label, run, cmd in zip(labels, runs, commands):
        evaluation = run + "_eval"
        subprocess.run(CTGS + ["eval", run, "-o", evaluation], cwd=REPO, check=True)
        results[label] = {"train_command": "ctgs " + shlex.join(cmd), **_summary(run, evaluation)}
    a, b = (results[label] for label in labels)
    result = {"tool": "sfm_train_check", "commit": commit, "command": shlex.join([os.path.relpath(sys.executable, REPO),
                                                                                  *sys.argv]),
              "scene": args.scene, "scenes": dict(zip(labels, scenes)), "labels": labels, "date_utc": date,
              "load_average_start": load_start, "load_average_end": list(os.getloadavg()), "machine": machine_info(),
              "runs": results, "notes": args.note,
              "difference": {k: (b[k] - a[k]) if a[k] is not None and b[k] is not None else None
                             for k in ("psnr", "ssim", "lpips")}}
    length = f"{args.iterations}it" if args.iterations else f"{args.time_budget:g}min"
    name = f"{args.scene}_{args.images}_{args.preset}_{length}{'_photos_of_a' if args.photos_of_a else ''}"
    record.write_record(record.stem("sfm_train_check", f"{name}_{commit}"), result, markdown)
    return 0


def markdown(r: dict) -> str:
    m = r["machine"]
    la, lb = r["labels"]
    lines = [f"# {r['scene']}: the same training on two SfM results, side by side ({r['date_utc'][:10]})", "",
             f"`{r['command']}` at commit {r['commit']}; {m['cpu_model']} ({m['logical_cores']} logical cores), shared: "
             f"load average {r['load_average_start'][0]:.1f} at the start, {r['load_average_end'][0]:.1f} at the end.",
             ""] + [f"- `{label}`: {r['scenes'][label]}" for label in r["labels"]] + [""]
    lines += [f"Note: {n}" for n in r["notes"]] + ([""] if r["notes"] else [])
    lines += ["| scene | resolution | iterations | train s | primitives | test views | PSNR (dB) | SSIM | LPIPS |",
              "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for label in r["labels"]:
        run = r["runs"][label]
        lp = f"{run['lpips']:.3f}" if run["lpips"] is not None else "n/a"
        lines.append(f"| {label} | {run['resolution'][0]}x{run['resolution'][1]} | {run['iterations']} | "
                     f"{run['train_seconds']:.0f} | {run['primitives']} | {run['test_views']} | {run['psnr']:.2f} | "
                     f"{run['ssim']:.3f} | {lp} |")
    d = r["difference"]
    lp = f"{d['lpips']:+.3f}" if d["lpips"] is not None else "n/a"
    lines += ["", f"{lb} minus {la}: PSNR {d['psnr']:+.2f} dB, SSIM {d['ssim']:+.3f}, LPIPS {lp}.", "",
              "Commands:", ""] + [f"- {label}: `{r['runs'][label]['train_command']}`" for label in r["labels"]]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
