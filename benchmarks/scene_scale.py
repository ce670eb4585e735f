"""Does a scene train the same in any unit? The demo scene with every world coordinate multiplied by a factor.

Makes the `make demo` scene (192x144, 24 views, 3000 points), writes copies with camera centres and points
multiplied by each --factors value (pycolmap Sim3d; the images are shared), trains each through the `ctgs` CLI
(`--preset fast --iterations N`, two at a time, one thread each) and compares test PSNR, primitives, texels and the
near plane the loader gave the cameras with the unscaled run. Writes benchmarks/results/scene_scale_<tag>.md.
A run that fails is reported with its error line, not dropped.

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


def scaled_copy(scene_dir: str, out_dir: str, factor: float) -> str:
    import numpy as np
    import pycolmap

    if os.path.isdir(out_dir):
        return out_dir
    rec = pycolmap.Reconstruction(os.path.join(scene_dir, "sparse", "0"))
    rec.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.zeros(3)))
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
    scenes = {f: base if f == 1.0 else scaled_copy(base, os.path.join(args.work, f"scene_x{f:g}"), f)
              for f in args.factors}

    def train(factor: float) -> tuple[float, dict | str]:
        run = os.path.join(args.work, f"run_x{factor:g}")
        log = run + ".log"
        if not os.path.exists(os.path.join(run, "train_summary.json")):
            try:
                ctgs("train", scenes[factor], "-o", run, "--preset", "fast", "--iterations", str(args.iterations),
                     "--set", "threads=1", "-q", log=log)
            except RuntimeError:
                lines = [ln.strip() for ln in open(log) if ln.strip()]
                return factor, next((ln for ln in reversed(lines) if ln.startswith("error")), lines[-1])
        with open(os.path.join(run, "train_summary.json")) as fh:
            return factor, json.load(fh)

    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        results = dict(pool.map(train, args.factors))

    from ctgs.scene.loader import load_scene

    ref = results[1.0]
    rows = ["| factor | scene extent | camera near | test PSNR (dB) | vs x1 | primitives | texels | train s |",
            "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for f in args.factors:
        s = load_scene(scenes[f], load_images=False)
        r = results[f]
        if isinstance(r, str):
            rows.append(f"| {f:g} | {s.extent:.3g} | {s.train[0].camera.near:.3g} | failed: {r} | | | | |")
            continue
        d = (f"{r['final_test_psnr'] - ref['final_test_psnr']:+.2f}" if isinstance(ref, dict) else "-")
        rows.append(f"| {f:g} | {s.extent:.3g} | {s.train[0].camera.near:.3g} | {r['final_test_psnr']:.2f} | {d} | "
                    f"{r['num_primitives']:,} | {r['num_texels']:,} | {r['train_seconds']:.0f} |")
    cmd = " ".join(["benchmarks/scene_scale.py", *sys.argv[1:]])
    text = "\n".join([
        f"# The demo scene in other units ({args.tag})", "",
        f"Written by `{cmd}` at commit {commit}, started {started} ({machine_name()}; {args.parallel} trainings side "
        f"by side, one thread each). The `make demo` scene (192x144, 24 views, 3000 points) with every world "
        f"coordinate multiplied by the factor, `ctgs train --preset fast --iterations {args.iterations}` on each.",
        "", *rows, ""])
    out = os.path.join(ROOT, "benchmarks", "results", f"scene_scale_{args.tag}.md")
    with open(out + ".tmp", "w") as fh:
        fh.write(text)
    os.replace(out + ".tmp", out)
    print(text)


if __name__ == "__main__":
    main()
