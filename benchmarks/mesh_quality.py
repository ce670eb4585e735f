"""`ctgs mesh` on trained runs: time, CPU time and peak memory of the command, the mesh's size, its accuracy against
the exact surfaces on the demo scene, and a picture of each mesh beside a photo.

    .venv/bin/python benchmarks/mesh_quality.py --run ctgs=runs/demo --run 2dgs=runs/demo_2dgs --tag demo192 \\
        --resolution 256 512 1024

--resolution 0 (the default) meshes with `ctgs mesh`'s own default voxel (no --resolution).

Each run is meshed once per --resolution by `ctgs mesh` in its own process (its wall time, user + system CPU seconds
and peak resident memory from wait4). On a demo scene (demo_meta.json) every mesh is scored by
measures/mesh_accuracy.py (Chamfer distance, normal consistency, F-score against the true rectangles, seen from the
training cameras), and so is what the meshes are fused from: the points of each run's rendered depth maps (every
training view, as `ctgs mesh` renders them), by their distance to the true surfaces. --pictures N: the scene's N-th
test view, as photographed, as the model renders it, and each mesh (at the first resolution) shaded and in its
colours, drawn by the viewer (`ctgs view --mesh`) in headless Chromium.
Record: benchmarks/results/mesh_quality/<tag>_<commit>.{json,md} (and .png).
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from profile_train import machine  # noqa: E402
from record import stem, write_record  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CTGS = [sys.executable, "-m", "ctgs"]


def _run_child(cmd: list[str]) -> tuple[subprocess.CompletedProcess, object]:
    """Run cmd, returning its result and its own resource usage (wait4: this child, not the others)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return subprocess.CompletedProcess(cmd, proc.returncode, out.read(), err.read()), usage


def mesh_once(run_dir: str, out: str, extra: list[str]) -> dict:
    cmd = CTGS + ["mesh", run_dir, "-o", out, *extra]
    start = time.perf_counter()
    done, usage = _run_child(cmd)
    wall = time.perf_counter() - start
    if done.returncode:
        raise SystemExit(f"{shlex.join(cmd)} failed:\n{done.stderr[-2000:]}")
    return {"command": shlex.join(["ctgs", "mesh", run_dir, "-o", out, *extra]), "wall_s": round(wall, 1),
            "cpu_s": round(usage.ru_utime + usage.ru_stime, 1), "peak_rss_mb": round(usage.ru_maxrss / 1024),
            "line": done.stdout.strip().splitlines()[-1],
            "plan": next((ln for ln in done.stderr.splitlines() if ln.startswith("volume:")), "")}


def accuracy(mesh_path: str, scene_dir: str) -> dict:
    from ctgs.formats.mesh import read_mesh
    from ctgs.scene.loader import load_scene
    from measures.demo_surfaces import load_demo_meta
    from measures.mesh_accuracy import mesh_accuracy

    v, f, _ = read_mesh(mesh_path)
    cams = [view.camera for view in load_scene(scene_dir, load_images=False).train]
    return mesh_accuracy(v, f, load_demo_meta(scene_dir), cams)


def depth_accuracy(run_dir: str) -> dict:
    """The run's rendered depth (expected depth where alpha >= 0.5, as `ctgs mesh` fuses it) of every training view,
    unprojected: distances of its points to the demo scene's true surfaces (world units)."""
    import torch

    from ctgs.fusion.pipeline import view_maps
    from ctgs.runs import load_run
    from ctgs.scene.loader import load_scene
    from measures.demo_surfaces import load_demo_meta
    from measures.mesh_accuracy import distance_to_surfaces

    run = load_run(run_dir)
    views = load_scene(run.scene_dir, images=run.images, holdout=run.holdout, load_images=False).train
    points = []
    with torch.no_grad():
        inputs = run.model.render_inputs()
        for view in views:
            cam = view.camera
            depth, _ = view_maps(inputs, cam, "auto", run.model.sh_degree, float("inf"))
            v, u = torch.nonzero(depth > 0, as_tuple=True)
            z = depth[v, u].double()
            pc = torch.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], 1)
            vm = cam.viewmat.double()
            points.append(((pc - vm[:3, 3]) @ vm[:3, :3]).numpy())
    d, _ = distance_to_surfaces(np.concatenate(points), load_demo_meta(run.scene_dir))
    return {"views": len(views), "points": int(len(d)), "mean": float(d.mean()), "median": float(np.median(d)),
            "p90": float(np.percentile(d, 90)), "within": {str(t): float((d < t).mean()) for t in (0.01, 0.02, 0.05)}}


def pictures(runs: dict[str, str], meshes: dict[str, str], view_index: int, path: str, width: int) -> dict:
    """photo | render | mesh shaded | mesh colours, one row per run, at the scene's test view `view_index`."""
    import cv2
    import torch

    from ctgs.formats.mesh import read_mesh, viewer_mesh
    from ctgs.formats.web_bundle import scene_cameras, write_web_bundle
    from ctgs.io.images import read_rgb
    from ctgs.render import render
    from ctgs.scene.loader import load_scene
    from ctgs.runs import load_run
    from ctgs.viewer.server import ViewerServer
    from headless import Browser
    from viewer_page import ViewerPage

    rows, info = [], {}
    for label, run_dir in runs.items():
        run = load_run(run_dir)
        scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout, load_images=False)
        view = scene.test[view_index]
        cams = scene_cameras(run.scene_dir, run.images, run.holdout)
        cam_index = next(i for i, c in enumerate(cams) if c["name"] == view.name)
        h = round(width * view.camera.height / view.camera.width)
        photo = cv2.resize(read_rgb(view.image_path), (width, h), interpolation=cv2.INTER_AREA)
        with torch.no_grad():
            rgb = render(run.model.render_inputs(), view.camera, sh_degree=run.model.sh_degree).rgb
        rendered = cv2.resize(rgb.clamp(0, 1).numpy(), (width, h), interpolation=cv2.INTER_AREA)
        with tempfile.TemporaryDirectory(prefix="mesh-quality-") as tmp:
            write_web_bundle(run.model, os.path.join(tmp, "web"), cams)
            mesh = viewer_mesh(*read_mesh(meshes[label]))
            with ViewerServer(os.path.join(tmp, "web"), mesh=mesh) as server, Browser() as browser:
                page = ViewerPage(browser, server.url, width=max(800, width), height=max(600, h))
                shaded = page.capture(cam_index, size=(width, h), mesh=True)
                coloured = page.capture(cam_index, size=(width, h), mesh=True, shade=False)
        rows.append(np.concatenate([photo, rendered, shaded, coloured], 1))
        info[label] = {"view": view.name, "triangles": mesh[0]["triangles"]}
    grid = (np.clip(np.concatenate(rows, 0), 0, 1) * 255).round().astype(np.uint8)
    cv2.imwrite(path, grid[..., ::-1])
    return {"file": os.path.relpath(path, ROOT), "layout": "rows: " + ", ".join(runs) +
            "; columns: photo, the model's render, mesh shaded, mesh colours", "views": info}


def markdown(r: dict) -> str:
    lines = [f"# `ctgs mesh`: {r['tag']}", "", f"{r['date']}, commit {r['commit']}, {r['machine']['cpu']} "
             f"({r['machine']['cores']} cores), load average {r['loadavg_start']} at the start.", "",
             f"Command: `{r['command']}`", ""]
    demo = any("accuracy" in m for m in r["meshes"])
    head = "| run | resolution | voxel | vertices | triangles | MB | wall s | CPU s | peak RSS MB |"
    if demo:
        head += " Chamfer (cm) | accuracy / completeness (cm) | normal consistency | F@1cm | F@2cm | F@5cm |"
    lines += [head, "|" + " --- |" * (head.count("|") - 1)]
    for m in r["meshes"]:
        row = (f"| {m['run']} | {m['resolution']} | {m['voxel']} | {m.get('vertices', 0):,} | {m['triangles']:,} | "
               f"{m['mb']:.1f} | "
               f"{m['wall_s']} | {m['cpu_s']} | {m['peak_rss_mb']} |")
        if demo:
            a = m["accuracy"]
            row += (f" {100 * a['chamfer']:.2f} | {100 * a['accuracy']:.2f} / {100 * a['completeness']:.2f} | "
                    f"{a['normal_consistency']:.3f} | " + " | ".join(f"{a['fscore'][t]['f']:.3f}"
                                                              for t in ("0.01", "0.02", "0.05")) + " |")
        lines.append(row)
    lines += ["", "Wall time depends on the machine's load (CPU seconds less so). "]
    if demo:
        lines += ["Accuracy: benchmarks/measures/mesh_accuracy.py (world units ~ metres; the true surfaces seen from "
                  "the training cameras; completeness to mesh samples spaced as `mesh_sample_spacing` in the JSON)."]
    if r.get("depth"):
        lines += ["", "What the meshes are fused from: each run's rendered depth over its training views, the distance "
                  "of its points to the true surfaces:", "",
                  "| run | points | mean (cm) | median (cm) | 90th percentile (cm) | within 1 / 2 / 5 cm |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for label, d in r["depth"].items():
            lines.append(f"| {label} | {d['points']:,} | {100 * d['mean']:.2f} | {100 * d['median']:.2f} | "
                         f"{100 * d['p90']:.2f} | "
                         + " / ".join(f"{d['within'][t]:.3f}" for t in ("0.01", "0.02", "0.05")) + " |")
    if r.get("pictures"):
        lines += ["", f"Picture: `{r['pictures']['file']}` ({r['pictures']['layout']})."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="LABEL=RUN_DIR")
    ap.add_argument("--tag", required=True, help="record name (scene, resolution, variant)")
    ap.add_argument("--resolution", type=int, nargs="+", default=[0], help="voxels across the extent (0: the default)")
    ap.add_argument("--mesh-args", default="", help="more `ctgs mesh` options, one string (e.g. '--bound contract')")
    ap.add_argument("--pictures", type=int, default=None, metavar="N", help="picture of the scene's N-th test view")
    ap.add_argument("--picture-width", type=int, default=400)
    ap.add_argument("--work", default=None, help="folder for the meshes (default: a temporary folder)")
    args = ap.parse_args()
    runs = dict(item.split("=", 1) for item in args.run)
    from ctgs.runs import load_run

    path_stem = stem("mesh_quality", args.tag)
    work = args.work or tempfile.mkdtemp(prefix="mesh-quality-")
    result = {"tag": args.tag, "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "commit": os.path.basename(path_stem).rsplit("_", 1)[1], "machine": machine(),
              "loadavg_start": [round(x, 2) for x in os.getloadavg()], "command": shlex.join(sys.argv),
              "meshes": []}
    first = {}
    for label, run_dir in runs.items():
        scene_dir = load_run(run_dir).scene_dir
        for res in args.resolution:
            out = os.path.join(work, f"{label}_{res}.ply")
            m = mesh_once(run_dir, out, [*(["--resolution", str(res)] if res else []), *shlex.split(args.mesh_args)])
            words = m["line"].split()
            m.update(run=label, resolution=res or "default", vertices=int(words[1]), triangles=int(words[3]), mb=os.path.getsize(out) / 1e6,
                     voxel=m["plan"].split(" voxels of ")[1].split()[0] if " voxels of " in m["plan"] else "")
            if os.path.isfile(os.path.join(scene_dir, "demo_meta.json")):
                m["accuracy"] = accuracy(out, scene_dir)
                if res == args.resolution[0]:
                    result.setdefault("depth", {})[label] = depth_accuracy(run_dir)
            result["meshes"].append(m)
            first.setdefault(label, out)
            print(m["line"], flush=True)
    if args.pictures is not None:
        result["pictures"] = pictures(runs, first, args.pictures, path_stem + ".png", args.picture_width)
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    write_record(path_stem, result, markdown)


if __name__ == "__main__":
    main()
