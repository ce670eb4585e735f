"""Does a scene train the same in any unit and anywhere? The demo scene scaled, or moved far from the origin.

Makes the `make demo` scene (192x144, 24 views, 3000 points), writes copies with camera centres and points
multiplied by each --factors value, and copies moved by each --moves value M (the translation M x (1, -0.7, 0.1),
as a georeferenced model's coordinates; pycolmap Sim3d, the images shared), trains each through the `ctgs` CLI
(`--preset fast --iterations N`, two at a time, one thread each) and compares test PSNR, primitives, texels, the
near plane and the working frame's origin the loader gave the scene with the unchanged run. Writes
benchmarks/results/scene_scale_<tag>.md. A run that fails is reported with its error line, not dropped.

    .venv/bin/python benchmarks/scene_scale.py --work /work/runs/scale --tag vm20
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from trade import ctgs, git_commit  # noqa: E402

from ctgs.train.run import machine_name  # noqa: E402


MOVE_DIRECTION = (1.0, -0.7, 0.1)


def scaled_copy(scene_dir: str, out_dir: str, factor: float, move: float = 0.0) -> str:
    import numpy as np
    import pycolmap

    if os.path.isdir(out_dir):
        return out_dir
    rec = pycolmap.Reconstruction(os.path.join(scene_dir, "sparse", "0"))
    rec.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), move * np.array(MOVE_DIRECTION)))
    tmp = out_dir + ".tmp"
    os.makedirs(os.path.join(tmp, "sparse", "0"), exist_ok=True)
    rec.write(os.path.join(tmp, "sparse", "0"))
    os.symlink(os.path.abspath(os.path.join(scene_dir, "images")), os.path.join(tmp, "images"))
    os.rename(tmp, out_dir)
    return out_dir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--tag", required=True)
    ap.add_argument("--factors", type=float, nargs="+", default=[1e-5, 1e-3, 1.0, 1e3, 1e5])
    ap.add_argument("--moves", type=float, nargs="*", default=[1e3, 1e5])
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--parallel", type=int, default=2)
    args = ap.parse_args()
    if 1.0 not in args.factors:
        raise SystemExit("scene_scale.py: --factors must include 1 (the reference)")
    commit = git_commit()
    started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    os.makedirs(args.work, exist_ok=True)
    base = os.path.join(args.work, "scene_x1")
    if not os.path.isdir(base):
        from ctgs.scene.demo import make_demo_scene

        make_demo_scene(base, num_views=24, width=192, height=144, points=3000)
    scenes = {f"x{f:g}": base if f == 1.0 else scaled_copy(base, os.path.join(args.work, f"scene_x{f:g}"), f)
              for f in args.factors}
    scenes.update({f"moved {m:g}": scaled_copy(base, os.path.join(args.work, f"scene_moved{m:g}"), 1.0, m)
                   for m in args.moves})

    def train(label: str) -> tuple[str, dict | str]:
        run = os.path.join(args.work, "run_" + label.replace(" ", ""))
        log = run + ".log"
        if not os.path.exists(os.path.join(run, "train_summary.json")):
            try:
                ctgs("train", scenes[label], "-o", run, "--preset", "fast", "--iterations", str(args.iterations),
                     "--set", "threads=1", "-q", log=log)
            except RuntimeError:
                lines = [ln.strip() for ln in open(log) if ln.strip()]
                return label, next((ln for ln in reversed(lines) if ln.startswith("error")), lines[-1])
        with open(os.path.join(run, "train_summary.json")) as fh:
            return label, json.load(fh)

    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        results = dict(pool.map(train, scenes))

    from ctgs.scene.loader import load_scene

    ref = results["x1"]
    rows = ["| scene | extent | camera near | working frame origin | test PSNR (dB) | vs x1 | primitives | texels | "
            "train s |", "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for label, path in scenes.items():
        s = load_scene(path, load_images=False)
        origin = getattr(s, "origin", None)  # absent before recentring existed
        where = "-" if origin is None else ("0" if not origin.any() else ", ".join(f"{x:.1f}" for x in origin))
        r = results[label]
        head = f"| {label} | {s.extent:.3g} | {s.train[0].camera.near:.3g} | {where} |"
        if isinstance(r, str):
            rows.append(f"{head} failed: {r} | | | | |")
            continue
        d = (f"{r['final_test_psnr'] - ref['final_test_psnr']:+.2f}" if isinstance(ref, dict) else "-")
        rows.append(f"{head} {r['final_test_psnr']:.2f} | {d} | {r['num_primitives']:,} | {r['num_texels']:,} | "
                    f"{r['train_seconds']:.0f} |")
    cmd = " ".join(["benchmarks/scene_scale.py", *sys.argv[1:]])
    text = "\n".join([
        f"# The demo scene in other units ({args.tag})", "",
        f"Written by `{cmd}` at commit {commit}, started {started} ({machine_name()}; {args.parallel} trainings side "
        f"by side, one thread each). The `make demo` scene (192x144, 24 views, 3000 points, extent 2.78) with every "
        f"world coordinate multiplied by the factor (xF) or moved by M x {MOVE_DIRECTION} (moved M: 1.22 M units "
        f"from the origin), `ctgs train --preset fast --iterations {args.iterations}` on each.",
        "", *rows, ""])
    out = os.path.join(ROOT, "benchmarks", "results", f"scene_scale_{args.tag}.md")
    with open(out + ".tmp", "w") as fh:
        fh.write(text)
    os.replace(out + ".tmp", out)
    print(text)


if __name__ == "__main__":
    main()
