"""Which primitives does a test camera sit inside? The cause of one-view veils (benchmarks/per_view.py).

A 2D surfel is a disc in a plane. When a camera lies close to that plane and inside the disc's footprint,
the plane fills a large part of its image (a floor seen from a few centimetres above it), even though the
training cameras, further from the plane, see it as the surface it models. This lists, for every test
view of each run, the surfels whose +-3 sigma disc contains the camera's projection onto their plane while
the camera is within `--plane-distance` x the scene extent of that plane, and the share of the view's
blending weight (sum of alpha T, the renderer's statistics) they carry, with their opacities and sizes.

Usage: .venv/bin/python benchmarks/camera_in_surfel.py --out NAME [--plane-distance 0.2] LABEL=RUN_DIR ...
Writes benchmarks/results/camera_in_surfel_NAME.md (the command, machine and date in it).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from ctgs.io.run_model import load_run  # noqa: E402
from ctgs.model.geometry import quat_to_rotmat  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.scene.loader import load_scene  # noqa: E402

SIGMAS = 3.0  # the renderer's cutoff (CUTOFF_RHO = 9)


def camera_centre(cam) -> torch.Tensor:
    vm = cam.viewmat.double()
    return (-(vm[:3, :3].T @ vm[:3, 3])).float()


def scene_extent(views) -> float:
    """3DGS's camera extent: 1.1 x the largest distance of a camera centre from their mean."""
    cs = torch.stack([camera_centre(v.camera) for v in views])
    return 1.1 * float((cs - cs.mean(0)).norm(dim=1).max())


@torch.no_grad()
def inside(model, cam, max_plane_dist: float) -> torch.Tensor:
    """[N] bool: the camera is within max_plane_dist of the surfel's plane and inside its +-3 sigma disc."""
    rot = quat_to_rotmat(model.quats)  # columns u, v, n
    d = camera_centre(cam) - model.means
    dist = (d * rot[:, :, 2]).sum(1).abs()
    s = model.scales
    r = torch.sqrt(((d * rot[:, :, 0]).sum(1) / s[:, 0]) ** 2 + ((d * rot[:, :, 1]).sum(1) / s[:, 1]) ** 2)
    return (dist < max_plane_dist) & (r < SIGMAS)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--plane-distance", type=float, default=0.2, help="fraction of the scene extent")
    ap.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    args = ap.parse_args()
    torch.set_num_threads(1)
    lines = []
    for spec in args.runs:
        label, run = spec.split("=", 1)
        rm = load_run(run)
        scene = load_scene(rm.scene_dir, rm.images, rm.holdout, load_images=False)
        extent = scene_extent(scene.train)
        m = rm.model
        for v in scene.test:
            cam = v.camera
            out = render(m.render_inputs(), cam, backend="cpu", sh_degree=m.sh_degree,
                         error_image=torch.zeros(cam.height, cam.width))
            w = out.stats.contrib
            sel = inside(m, cam, args.plane_distance * extent)
            share = 100 * float(w[sel].sum() / w.sum().clamp_min(1e-12))
            o, sz = m.opacities[sel], m.scales[sel].max(1).values
            rng = (lambda t: f"{float(t.min()):.2f}-{float(t.max()):.2f}" if t.numel() else "-")
            lines.append(f"| {label} | {v.name} | {int(sel.sum())} | {share:.1f}% | {rng(o)} | {rng(sz)} | "
                         f"{m.num_primitives} | {extent:.2f} | `{run}` |")
    head = [f"# Surfels a test camera sits inside ({args.out})", "",
            f"Written by `benchmarks/camera_in_surfel.py {' '.join(sys.argv[1:])}` on "
            f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())} ({platform.node()}, {os.cpu_count()} cores, "
            f"torch {torch.__version__}). A surfel counts when the camera is within {args.plane_distance} x the "
            "scene extent (3DGS's camera extent) of its plane and inside its +-3 sigma disc; weight share = its "
            "part of the view's sum of alpha T over all blended pixels and primitives.", "",
            "| run | test view | surfels | weight share | their opacity | their larger scale (world) | primitives | "
            "extent | folder |",
            "| --- | --- | ---: | ---: | --- | --- | ---: | ---: | --- |"]
    path = os.path.join(ROOT, "benchmarks", "results", f"camera_in_surfel_{args.out}.md")
    with open(path, "w") as fh:
        fh.write("\n".join(head + lines) + "\n")
    print("\n".join(head + lines))


if __name__ == "__main__":
    main()
