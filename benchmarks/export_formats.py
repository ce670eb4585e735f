"""What each export format keeps: bytes on disk and test-view PSNR of a trained run, rendered from the file.

Exports RUN_DIR with `ctgs export --format ctgs|ply|splat|spz|compressed-ply|sog|glb-splats|glb` (and `ctgs compress` of the
ctgs folder),
reads every file back and renders the run's test views from it:
- ctgs, ctgs K-means: ctgs.formats.model_format.read_model, our CPU renderer (exact model);
- ply (3DGS PLY), splat, spz, compressed-ply, sog, glb-splats (KHR_gaussian_splatting), and ply / spz / sog with
  --bake-textures (a splat per texel: ctgs.formats.bake): read back as untextured surfels (ctgs.formats.plain_ply / splat /
  spz / playcanvas / gltf_splats), our CPU renderer
  (so the figure is what the file holds, not what some viewer's EWA splatting makes of it);
- glb: read with pygltflib (ctgs.formats.gltf.read_glb), drawn by a headless OpenGL renderer
  (benchmarks/glb_render.py: moderngl + EGL, Mesa llvmpipe here), quads sorted back to front per view,
  in two colour pipelines (blending in image space as our renderer does, and sRGB-correct linear blending
  as three.js/Blender do). Without moderngl/EGL the glb row says so and carries no PSNR.
The .glb is also checked with the Khronos glTF validator (npm gltf-validator, installed into the ctgs
cache as tests/formats/test_export_cli.py does) when node/npm are present.
A diagnostic row renders the exact model with its SH cut to the DC band: the part of the ply/splat/glb
loss that comes from dropping view dependence rather than from the format itself.

Usage: .venv/bin/python benchmarks/export_formats.py RUN_DIR [--work DIR] [--tag NAME]
Writes benchmarks/results/export_formats/<tag>_<commit>.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tests", "io"))

from ctgs.formats.model_format import read_model  # noqa: E402
from ctgs.runs import load_run  # noqa: E402
import record  # noqa: E402 (benchmarks/record.py)
from record import write_record  # noqa: E402
from ctgs.metrics.psnr import psnr  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.scene import load_scene  # noqa: E402

CODEBOOK = 256  # the K-means size `make demo` uses


def ctgs_cli(*args: str) -> None:
    exe = os.path.join(os.path.dirname(sys.executable), "ctgs")
    subprocess.run([exe, *args], check=True)


def folder_bytes(path: str) -> int:
    """Bytes a model folder needs to load (manifest + primitives + blob; not the optional plain PLY)."""
    return read_model(path)[1].bytes_on_disk


def render_views(model, views) -> list[torch.Tensor]:
    """[H, W, 3] float32 renders in [0, 1] of `model` from every view (CPU backend)."""
    inputs = model.render_inputs()
    out = []
    with torch.no_grad():
        for v in views:
            cam = v.camera.to("cpu", inputs.means.dtype)
            out.append(render(inputs, cam, backend="cpu", sh_degree=model.sh_degree).rgb.clamp(0, 1).float())
    return out


def scores(images: list[torch.Tensor], views, exact: list[torch.Tensor]) -> dict:
    """Mean PSNR against the test photos, per view, and against the exact model's renders (what the file
    keeps of the model, whatever the model's own quality)."""
    gt = [psnr(im.float(), torch.as_tensor(v.image, dtype=torch.float32)) for im, v in zip(images, views)]
    vs = [psnr(im.float(), ex) for im, ex in zip(images, exact)]
    return {"psnr": sum(gt) / len(gt), "per_view": gt, "psnr_vs_exact": sum(vs) / len(vs)}


def validate_glb(path: str) -> dict:
    """The Khronos validator's issue counts, or {"status": why not}."""
    if not (shutil.which("node") and shutil.which("npm")):
        return {"status": "not run: node/npm not found"}
    import pytest  # noqa: F401  (the fixture module imports it)
    from test_export_cli import VALIDATE_JS, VALIDATOR

    from ctgs.resources import cache_dir

    package = cache_dir() / "node" / VALIDATOR.replace("@", "-") / "node_modules" / "gltf-validator"
    if not (package / "package.json").is_file():
        subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--prefix", str(package.parents[1]), VALIDATOR],
                       check=True, capture_output=True)
    p = subprocess.run(["node", "-e", VALIDATE_JS, str(package), path], capture_output=True, text=True, check=True)
    issues = json.loads(p.stdout)["issues"]
    return {"status": "ok", "validator": VALIDATOR, "errors": issues["numErrors"], "warnings": issues["numWarnings"],
            "infos": issues["numInfos"], "hints": issues["numHints"]}


def glb_rows(path: str, views, exact: list[torch.Tensor], nbytes: int, validation: dict) -> list[dict]:
    from ctgs.formats.gltf import read_glb

    glb = read_glb(path)
    try:
        from glb_render import GlbRenderer
    except ImportError as exc:
        return [{"format": "glb", "bytes": nbytes, "psnr": None, "validator": validation,
                 "renderer": f"none: {exc} (pip install moderngl)"}]
    rows = []
    for pipeline in ("image", "linear"):
        try:
            r = GlbRenderer(glb, pipeline)
        except Exception as exc:  # no EGL / no GL driver: say so, never a number
            return [{"format": "glb", "bytes": nbytes, "psnr": None, "validator": validation,
                     "renderer": f"none: headless OpenGL unavailable ({type(exc).__name__}: {exc})"}]
        images = [r.render(v.camera) for v in views]
        renderer = r.ctx.info["GL_RENDERER"]
        rows.append({"format": f"glb ({pipeline} blending)", "bytes": nbytes, **scores(images, views, exact),
                     "validator": validation,
                     "renderer": f"benchmarks/glb_render.py, moderngl EGL on {renderer}, {pipeline} colour pipeline"})
        r.ctx.release()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--work", default=None, help="Folder for the exports (default RUN_DIR/formats).")
    ap.add_argument("--tag", default="demo192")
    ap.add_argument("--setup", default="", help="How RUN_DIR was made (commands), recorded with the results.")
    args = ap.parse_args()
    work = args.work or os.path.join(args.run_dir, "formats")
    os.makedirs(work, exist_ok=True)
    t0 = time.time()
    files = {"ctgs": os.path.join(work, "model"), "ctgs_k": os.path.join(work, f"model-k{CODEBOOK}"),
             "ply": os.path.join(work, "model.ply"), "splat": os.path.join(work, "model.splat"),
             "spz": os.path.join(work, "model.spz"), "glb": os.path.join(work, "model.glb"),
             "ply_baked": os.path.join(work, "model-baked.ply"), "spz_baked": os.path.join(work, "model-baked.spz"),
             "compressed-ply": os.path.join(work, "model.compressed.ply"), "sog": os.path.join(work, "model.sog"),
             "sog_baked": os.path.join(work, "model-baked.sog"), "glb-splats": os.path.join(work, "model.splats.glb")}
    ctgs_cli("export", args.run_dir, "-o", files["ctgs"], "--no-plain-ply")
    ctgs_cli("compress", files["ctgs"], "-o", files["ctgs_k"], "--codebook-size", str(CODEBOOK))
    export_s = {}
    for fmt in ("ply", "splat", "spz", "compressed-ply", "sog", "glb-splats", "glb"):
        t = time.time()
        ctgs_cli("export", args.run_dir, "--format", fmt, "-o", files[fmt])
        export_s[fmt] = time.time() - t
    for fmt in ("ply", "spz", "sog"):
        t = time.time()
        ctgs_cli("export", args.run_dir, "--format", fmt, "--bake-textures", "-o", files[f"{fmt}_baked"])
        export_s[f"{fmt}_baked"] = time.time() - t

    run = load_run(args.run_dir)
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    views = scene.test
    from ctgs.formats.gltf_splats import read_glb_splats
    from ctgs.formats.plain_ply import read_plain_ply
    from ctgs.formats.playcanvas import read_compressed_ply, read_sog
    from ctgs.formats.splat import read_splat
    from ctgs.formats.spz import read_spz

    rows = []
    exact, _ = read_model(files["ctgs"])
    exact_images = render_views(exact, views)
    for name, model, nbytes, how in (
            ("ctgs", exact, folder_bytes(files["ctgs"]), "read_model, CPU renderer"),
            (f"ctgs K={CODEBOOK} (compress)", read_model(files["ctgs_k"])[0], folder_bytes(files["ctgs_k"]),
             "read_model, CPU renderer"),
            ("ply (3DGS)", read_plain_ply(files["ply"]), os.path.getsize(files["ply"]),
             "read_plain_ply -> untextured surfels, CPU renderer"),
            ("splat", read_splat(files["splat"]), os.path.getsize(files["splat"]),
             "read_splat -> untextured surfels, CPU renderer"),
            ("spz (v3)", read_spz(files["spz"]), os.path.getsize(files["spz"]),
             "read_spz (matches Niantic's reader: tests/formats/test_spz.py) -> untextured surfels, CPU renderer"),
            ("compressed-ply (PlayCanvas)", read_compressed_ply(files["compressed-ply"]),
             os.path.getsize(files["compressed-ply"]),
             "read_compressed_ply (matches splat-transform's reader: tests/formats/test_playcanvas.py) -> untextured "
             "surfels, CPU renderer"),
            ("sog (PlayCanvas)", read_sog(files["sog"]), os.path.getsize(files["sog"]),
             "read_sog (matches splat-transform's reader: tests/formats/test_playcanvas.py) -> untextured surfels, "
             "CPU renderer"),
            ("glb-splats (KHR_gaussian_splatting)", read_glb_splats(files["glb-splats"]),
             os.path.getsize(files["glb-splats"]),
             "read_glb_splats (the file splat-transform writes from our PLY: tests/formats/test_gltf_splats.py) -> "
             "untextured surfels, CPU renderer"),
            ("ply (3DGS), --bake-textures", read_plain_ply(files["ply_baked"]), os.path.getsize(files["ply_baked"]),
             "read_plain_ply -> untextured surfels (a splat per texel), CPU renderer"),
            ("spz (v3), --bake-textures", read_spz(files["spz_baked"]), os.path.getsize(files["spz_baked"]),
             "read_spz -> untextured surfels (a splat per texel), CPU renderer"),
            ("sog (PlayCanvas), --bake-textures", read_sog(files["sog_baked"]), os.path.getsize(files["sog_baked"]),
             "read_sog -> untextured surfels (a splat per texel), CPU renderer")):
        images = exact_images if model is exact else render_views(model, views)
        rows.append({"format": name, "bytes": nbytes, "splats": model.num_primitives,
                     **scores(images, views, exact_images), "renderer": how})
    dc_only = read_model(files["ctgs"])[0]
    dc_only.sh_degree = 0
    rows.append({"format": "(diagnostic) ctgs with SH cut to DC", "bytes": None,
                 **scores(render_views(dc_only, views), views, exact_images),
                 "renderer": "read_model, sh_degree 0, CPU renderer (not a file: what view-independent colour costs)"})
    rows += glb_rows(files["glb"], views, exact_images, os.path.getsize(files["glb"]), validate_glb(files["glb"]))

    result = {
        "benchmark": "export_formats", "date": datetime.date.today().isoformat(),
        "command": " ".join([os.path.relpath(sys.executable), *sys.argv]),
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__},
        "setup": args.setup, "run_dir": os.path.abspath(args.run_dir), "scene_dir": run.scene_dir, "images": run.images,
        "test_views": [v.name for v in views], "resolution": [views[0].camera.width, views[0].camera.height],
        "num_primitives": exact.num_primitives, "num_texels": exact.num_texels,
        "export_seconds": export_s, "rows": rows, "seconds": time.time() - t0,
    }
    out = record.stem("export_formats", args.tag)
    write_record(out, result, markdown)


def markdown(r: dict) -> str:
    lines = [f"# Export formats: bytes and test PSNR ({r['date']})", "",
             f"Run `{r['run_dir']}` ({r['num_primitives']} surfels, {r['num_texels']} texels), "
             f"{len(r['test_views'])} test views at {r['resolution'][0]}x{r['resolution'][1]}. "
             f"Machine: {r['machine']['platform']}, {r['machine']['cpu_count']} CPUs, torch {r['machine']['torch']}.",
             f"Command: `{r['command']}` ({r['seconds']:.0f} s)."]
    if r.get("setup"):
        lines.append(f"Run made with: {r['setup']}")
    lines += ["",
              "PSNR vs exact: the format's render against the exact model's render (what the file keeps of the "
              "model); test PSNR: against the test photos.", "",
              "| format | splats | bytes | MB | test PSNR (dB) | PSNR vs exact (dB) | validator | rendered by |",
              "| --- | ---: | ---: | ---: | ---: | ---: | --- | --- |"]
    for row in r["rows"]:
        b = "" if row["bytes"] is None else f"{row['bytes']}"
        mb = "" if row["bytes"] is None else f"{row['bytes'] / 1e6:.3f}"
        p = "n/a" if row["psnr"] is None else f"{row['psnr']:.2f}"
        pe = "n/a" if row.get("psnr_vs_exact") is None else f"{row['psnr_vs_exact']:.2f}"
        v = row.get("validator")
        val = "" if v is None else (f"{v['errors']} errors, {v['warnings']} warnings" if v.get("status") == "ok"
                                    else v["status"])
        n = row.get("splats", "")
        lines.append(f"| {row['format']} | {n} | {b} | {mb} | {p} | {pe} | {val} | {row['renderer']} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
