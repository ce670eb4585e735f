"""Surfaces without ground truth: does a model's depth agree between neighbouring views, and is its mesh seen where
the views put it?

    .venv/bin/python benchmarks/depth_consistency.py --run content-aware=runs/bonsai --mesh content-aware=bonsai.ply \\
        --run 2dgs=runs/bonsai_2dgs --mesh 2dgs=bonsai_2dgs.ply --tag bonsai252_images_4_15min

1. Depth agreement: each training view's depth map (median and expected depth, where alpha >= 0.5, as `ctgs mesh`
   fuses them) unprojected and projected into its nearest training camera (by centre), compared with that camera's
   own depth at the pixel it lands on (nearest pixel): the relative difference |z_i->j - z_j| / z_j. A surface both
   views see agrees to within the depth's noise; a floater one view draws lands in front of what the other sees.
   Reported: the median relative difference and the fraction of pixels within 1% and 5%, over the pixels that land
   inside the other view on a drawn pixel.
2. Support of a mesh: area-uniform samples of the mesh, each counted in the training cameras where it lies in the
   image, in front of the camera and within 1% (relative) of that camera's median depth there (on the surface it
   draws, not hidden behind it); reported: the fraction of the mesh's area with at least 1, 3 and 10 such views.
Record: benchmarks/results/depth_consistency/<tag>_<commit>.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from profile_train import machine  # noqa: E402
from record import stem, write_record  # noqa: E402

AGREE = (0.01, 0.05)  # relative depth differences reported
SUPPORT_TOL = 0.01  # a mesh sample lies on a view's surface within this relative depth
MESH_SAMPLES = 200_000
MIN_ALPHA = 0.5


def view_depths(run, cams) -> list[dict]:
    """{median, mean} [H, W] depth maps (0 where alpha < MIN_ALPHA) of each camera."""
    from ctgs.render import render  # the renderer's extension is built on first use, after the arguments are read

    out = []
    with torch.no_grad():
        inputs = run.model.render_inputs()
        for cam in cams:
            r = render(inputs, cam, backend="cpu", sh_degree=run.model.sh_degree)
            covered = r.alpha >= MIN_ALPHA
            zero = torch.zeros_like(r.alpha)
            out.append({"median": torch.where(covered, r.median_depth, zero).double().numpy(),
                        "mean": torch.where(covered, r.depth / r.alpha.clamp_min(1e-6), zero).double().numpy()})
    return out


def _world_points(depth: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    pc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], 1)
    vm = cam.viewmat.double().numpy()
    return (pc - vm[:3, 3]) @ vm[:3, :3], z


def _project(points: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pixel column, pixel row, depth) of world points in cam (nearest pixel; -1 off the image or behind)."""
    vm = cam.viewmat.double().numpy()
    pc = points @ vm[:3, :3].T + vm[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(cam.fx * pc[:, 0] / z + cam.cx)
        v = np.floor(cam.fy * pc[:, 1] / z + cam.cy)
    ok = (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return np.where(ok, u, -1).astype(np.int64), np.where(ok, v, -1).astype(np.int64), z


def agreement(depths: list[dict], cams, which: str) -> dict:
    centres = np.stack([c.center.double().numpy() for c in cams])
    rel = []
    for i, cam in enumerate(cams):
        d = np.linalg.norm(centres - centres[i], axis=1)
        d[i] = np.inf
        j = int(np.argmin(d))
        pts, _ = _world_points(depths[i][which], cam)
        u, v, z = _project(pts, cams[j])
        ok = u >= 0
        zj = depths[j][which][v[ok], u[ok]]
        drawn = zj > 0
        rel.append(np.abs(z[ok][drawn] - zj[drawn]) / zj[drawn])
    r = np.concatenate(rel)
    return {"pixels": int(len(r)), "median_relative": float(np.median(r)),
            **{f"within_{t:g}": float((r < t).mean()) for t in AGREE}}


def support(mesh_path: str, depths: list[dict], cams) -> dict:
    # loaded only for a run given a mesh (--mesh)
    from ctgs.formats.mesh import read_mesh
    from measures.mesh_accuracy import sample_mesh

    v, f, _ = read_mesh(mesh_path)
    pts, _ = sample_mesh(v, f, MESH_SAMPLES, seed=0)
    count = np.zeros(len(pts), np.int64)
    for cam, d in zip(cams, depths):
        u, vv, z = _project(pts, cam)
        ok = u >= 0
        zd = np.zeros(len(pts))
        zd[ok] = d["median"][vv[ok], u[ok]]
        count += ok & (zd > 0) & (np.abs(z - zd) <= SUPPORT_TOL * np.maximum(zd, 1e-9))
    return {"vertices": int(len(v)), "triangles": int(len(f)), "samples": int(len(pts)),
            "seen_by_1": float((count >= 1).mean()), "seen_by_3": float((count >= 3).mean()),
            "seen_by_10": float((count >= 10).mean()), "median_views": float(np.median(count))}


def markdown(r: dict) -> str:
    lines = [f"# Depth consistency: {r['tag']}", "", f"{r['date']}, commit {r['commit']}, {r['machine']['cpu']} "
             f"({r['machine']['cores']} cores), load average {r.get('loadavg_start')} at the start, "
             f"{r.get('loadavg_end')} at the end.", "", f"Command: `{r['command']}`", "",
             *([r["note"], ""] if r.get("note") else []),
             "Each training view's depth projected into its nearest training camera: relative difference from that "
             "camera's own depth (pixels with alpha >= 0.5 in both):", "",
             "| run | depth | pixels compared | median relative difference | within 1% | within 5% |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    for label, d in r["runs"].items():
        for which, a in d["agreement"].items():
            lines.append(f"| {label} | {which} | {a['pixels']:,} | {a['median_relative']:.4f} | "
                         f"{a['within_0.01']:.3f} | {a['within_0.05']:.3f} |")
    if any("support" in d for d in r["runs"].values()):
        lines += ["", f"Mesh support: the share of the mesh's area lying within {100 * SUPPORT_TOL:g}% of the median "
                  "depth of at least N training views (in their image, in front of them):", "",
                  "| run | mesh | vertices | N >= 1 | N >= 3 | N >= 10 | median N |", "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
        for label, d in r["runs"].items():
            if "support" in d:
                s = d["support"]
                lines.append(f"| {label} | `{d['mesh']}` | {s['vertices']:,} | {s['seen_by_1']:.3f} | "
                             f"{s['seen_by_3']:.3f} | {s['seen_by_10']:.3f} | {s['median_views']:g} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="LABEL=RUN_DIR")
    ap.add_argument("--mesh", action="append", default=[], metavar="LABEL=MESH_FILE")
    ap.add_argument("--tag", required=True, help="record name (scene, resolution, variant)")
    ap.add_argument("--note", default="", help="a line for the record (how the runs were trained and meshed)")
    args = ap.parse_args()
    # loaded after the arguments are read (--help stays quick)
    from ctgs.runs import load_run
    from ctgs.scene.loader import load_scene

    torch.set_num_threads(1)
    meshes = dict(item.split("=", 1) for item in args.mesh)
    path_stem = stem("depth_consistency", args.tag)
    result = {"tag": args.tag, "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "commit": os.path.basename(path_stem).rsplit("_", 1)[1], "machine": machine(),
              "loadavg_start": [round(x, 2) for x in os.getloadavg()],
              "command": shlex.join(["benchmarks/depth_consistency.py", *sys.argv[1:]]), "note": args.note, "runs": {}}
    for item in args.run:
        label, run_dir = item.split("=", 1)
        run = load_run(run_dir)
        cams = [v.camera for v in load_scene(run.scene_dir, images=run.images, holdout=run.holdout,
                                             load_images=False).train]
        depths = view_depths(run, cams)
        entry = {"run": run_dir, "primitives": run.model.num_primitives,
                 "agreement": {w: agreement(depths, cams, w) for w in ("median", "mean")}}
        if label in meshes:
            entry["mesh"] = meshes[label]
            entry["support"] = support(meshes[label], depths, cams)
        result["runs"][label] = entry
        print(label, entry["agreement"], entry.get("support"), flush=True)
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    write_record(path_stem, result, markdown)


if __name__ == "__main__":
    main()
