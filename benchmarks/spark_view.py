"""Our .spz / PLY / .splat / compressed PLY / SOG exports in a third-party Gaussian viewer: Spark (sparkjs.dev, three.js) in headless Chromium.

ctgs's own checks read an exported file back with our reader and draw it with our renderer (export_formats.py);
Niantic's reader agrees with ours on every array (tests/formats/test_spz.py). What neither shows is what a user sees in
the viewers they have. This loads each file into Spark 2.2 (npm @sparkjsdev/spark with three.js 0.180, installed
into the ctgs cache), places three.js's camera at each test view of the run (COLMAP's right-down-front camera turned
into three.js's right-up-back frame, as spz stores the scene, PLY and .splat turned into it by the usual half
turn of the mesh about x; the projection from the view's intrinsics), draws with
Spark's defaults in headless Chromium (SwiftShader WebGL2, no GPU), and scores the screenshot against the test photo
and against our renderer's image of the same file (read back by ctgs's reader; black background as in the page).

Usage: .venv/bin/python benchmarks/spark_view.py RUN_DIR FILE.spz|.ply|.splat|.compressed.ply|.sog [FILE ...] [--tag NAME] [--work DIR]
Writes benchmarks/results/spark_view/<tag>_<commit>.{json,md,jpg} (the jpg: photo and Spark's image of each file, per view). Needs node, npm (the registry) and Chromium.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import http.server
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from ctgs.runs import load_run  # noqa: E402
import record  # noqa: E402 (benchmarks/record.py)
from record import write_record  # noqa: E402
from ctgs.formats.readers import read_gaussian_file  # noqa: E402
from ctgs.metrics.psnr import psnr  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.resources import cache_dir  # noqa: E402
from ctgs.scene import load_scene  # noqa: E402
from headless import Browser, find_chromium  # noqa: E402 (benchmarks/headless.py)

PACKAGES = ("three@0.180.0", "@sparkjsdev/spark@2.2.0")
FRAMES = 60  # at most this many renders per view (--frames), WAIT_MS apart, until two in a row change nothing
WAIT_MS = 200

PAGE = """<!doctype html><html><head><meta charset="utf-8"><style>html,body{margin:0;background:#000;overflow:hidden}</style>
<script type="importmap">{"imports": {"three": "/node_modules/three/build/three.module.js",
 "three/addons/": "/node_modules/three/examples/jsm/",
 "@sparkjsdev/spark": "/node_modules/@sparkjsdev/spark/dist/spark.module.js"}}</script></head><body>
<script type="module">
import * as THREE from "three";
import { SplatMesh, SparkRenderer } from "@sparkjsdev/spark";
const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0, 0, 0);
scene.add(new SparkRenderer({ renderer }));
const camera = new THREE.PerspectiveCamera();
let mesh = null, meshUrl = null;
window.show = async (url, v) => {
  renderer.setSize(v.width, v.height);
  if (meshUrl !== url) {
    if (mesh) { scene.remove(mesh); mesh.dispose(); }
    mesh = new SplatMesh({ url });
    await mesh.initialized;
    // PLY and .splat hold COLMAP's right-down-front frame: a half turn about x puts them in three.js's frame (the
    // usual Spark recipe for 3DGS files); .spz files are already right-up-back.
    if (v.flipX) mesh.quaternion.set(1, 0, 0, 0);
    scene.add(mesh);
    meshUrl = url;
  }
  camera.matrixAutoUpdate = false;
  camera.matrix.fromArray(v.camToWorld);
  camera.matrixWorld.copy(camera.matrix);
  camera.matrixWorldInverse.copy(camera.matrixWorld).invert();
  camera.projectionMatrix.fromArray(v.projection);
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  // Render until the image stops changing (Spark's depth sort runs in a worker and lands a frame or more later),
  // reading the pixels back each time so that a slow software-GL frame is finished before the next one is asked.
  const gl = renderer.getContext();
  const size = v.width * v.height * 4;
  let prev = new Uint8Array(size), cur = new Uint8Array(size), stable = 0, frames = 0;
  while (frames < v.frames && stable < 2) {
    renderer.render(scene, camera);
    gl.readPixels(0, 0, v.width, v.height, gl.RGBA, gl.UNSIGNED_BYTE, cur);
    frames += 1;
    let same = true;
    for (let i = 0; i < size; i++) { if (cur[i] !== prev[i]) { same = false; break; } }
    stable = same ? stable + 1 : 0;
    [prev, cur] = [cur, prev];
    await new Promise(r => setTimeout(r, v.waitMs));
  }
  return { splats: mesh.numSplats ?? null, frames, stable: stable >= 2 };
};
window.ready = true;
</script></body></html>
"""

FLIP = np.diag([1.0, -1.0, -1.0])  # COLMAP's right-down-front <-> three.js's / spz's right-up-back


def install() -> str:
    """The node_modules folder holding PACKAGES (installed once into the ctgs cache)."""
    npm = shutil.which("npm")
    if not npm or not shutil.which("node"):
        raise SystemExit("spark_view.py: node and npm are needed (the Spark viewer is an npm package)")
    prefix = cache_dir() / "node" / ("spark-" + "-".join(p.replace("@", "").replace("/", "-") for p in PACKAGES))
    if not (prefix / "node_modules" / "@sparkjsdev" / "spark" / "package.json").is_file():
        prefix.mkdir(parents=True, exist_ok=True)
        subprocess.run([npm, "install", "--no-audit", "--no-fund", "--prefix", str(prefix), *PACKAGES], check=True,
                       capture_output=True, timeout=600)
    return str(prefix / "node_modules")


def three_view(camera) -> dict:
    """A ctgs Camera as three.js matrices (column-major): camera-to-world in the RUB world, and the projection."""
    view = camera.viewmat.double().numpy()  # world -> camera, both right-down-front
    r, t = view[:3, :3], view[:3, 3]
    v = np.eye(4)
    v[:3, :3], v[:3, 3] = FLIP @ r @ FLIP, FLIP @ t
    cam_to_world = np.linalg.inv(v)
    w, h, fx, fy, cx, cy = camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
    near, far = max(camera.near, 1e-4), 1e4
    p = np.array([[2 * fx / w, 0, (w - 2 * cx) / w, 0],
                  [0, 2 * fy / h, (2 * cy - h) / h, 0],
                  [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
                  [0, 0, -1, 0]])
    return {"width": w, "height": h, "camToWorld": cam_to_world.T.reshape(-1).tolist(),
            "projection": p.T.reshape(-1).tolist()}


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def serve(root: str) -> tuple[http.server.ThreadingHTTPServer, int]:
    handler = functools.partial(QuietHandler, directory=root)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, server.server_address[1]


def png_rgb(data: bytes) -> torch.Tensor:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    return torch.from_numpy(img.astype(np.float32) / 255.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("files", nargs="+", help=".spz, .ply, .splat, .compressed.ply or .sog files exported from "
                    "RUN_DIR (ctgs export --format spz|ply|splat|compressed-ply|sog ...)")
    ap.add_argument("--tag", required=True)
    ap.add_argument("--work", default=None, help="Folder served to the browser (default RUN_DIR/spark_view).")
    ap.add_argument("--frames", type=int, default=FRAMES, help="Most renders per view before the screenshot.")
    ap.add_argument("--wait-ms", type=int, default=WAIT_MS, help="Pause after each render (Spark's sort runs then).")
    args = ap.parse_args()
    t0 = time.time()
    modules = install()
    work = args.work or os.path.join(args.run_dir, "spark_view")
    os.makedirs(work, exist_ok=True)
    with open(os.path.join(work, "index.html"), "w") as f:
        f.write(PAGE)
    link = os.path.join(work, "node_modules")
    if not os.path.islink(link):
        os.symlink(modules, link)
    names = []
    for path in args.files:
        name = os.path.basename(path)
        shutil.copyfile(path, os.path.join(work, name))
        names.append(name)

    run = load_run(args.run_dir)
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    views = scene.test
    chromium = find_chromium()
    if chromium is None:
        raise SystemExit("spark_view.py: Chromium not found")
    server, port = serve(work)
    rows = []
    shots: dict = {}  # view name -> [photo, Spark screenshot of each file]
    try:
        with Browser(chromium, timeout=1200.0) as browser:  # a million splats: seconds a frame in SwiftShader
            browser.goto(f"http://127.0.0.1:{port}/index.html")
            deadline = time.time() + 60
            while not browser.evaluate("window.ready === true") and time.time() < deadline:
                time.sleep(0.2)
            for name, path in zip(names, args.files):
                ours_model = read_gaussian_file(path)  # each file read back for our renderer
                inputs = ours_model.render_inputs()
                per_view = []
                for view in views:
                    cam = view.camera
                    browser.set_viewport(cam.width, cam.height)
                    t = time.time()
                    spec = {**three_view(cam), "frames": args.frames, "waitMs": args.wait_ms,
                            "flipX": not path.endswith(".spz")}
                    shown = browser.evaluate(f"window.show({json.dumps(name)}, {json.dumps(spec)})", timeout=1200)
                    seconds = time.time() - t
                    shot = png_rgb(browser.screenshot({"x": 0, "y": 0, "width": cam.width, "height": cam.height}))
                    ours = render(inputs, cam, backend="cpu", background=torch.zeros(3)).rgb.clamp(0, 1)
                    gt = torch.as_tensor(view.image).float()
                    shots.setdefault(view.name, [gt]).append(shot)
                    per_view.append({"view": view.name, "psnr_spark_vs_photo": float(psnr(shot, gt)),
                                     "psnr_ours_vs_photo": float(psnr(ours, gt)),
                                     "psnr_spark_vs_ours": float(psnr(shot, ours)), "seconds": seconds,
                                     "spark_splats": shown["splats"], "frames": shown["frames"],
                                     "stable": shown["stable"]})
                    import cv2

                    stem = os.path.join(work, f"{os.path.splitext(name)[0]}_{os.path.splitext(view.name)[0]}")
                    cv2.imwrite(stem + "_spark.png", (shot.numpy()[..., ::-1] * 255).round().astype(np.uint8))
                    cv2.imwrite(stem + "_ours.png", (ours.numpy()[..., ::-1] * 255).round().astype(np.uint8))
                mean = lambda key: float(np.mean([p[key] for p in per_view]))  # noqa: E731
                rows.append({"file": name, "bytes": os.path.getsize(path), "splats": ours_model.num_primitives,
                             "psnr_spark_vs_photo": mean("psnr_spark_vs_photo"),
                             "psnr_ours_vs_photo": mean("psnr_ours_vs_photo"),
                             "psnr_spark_vs_ours": mean("psnr_spark_vs_ours"), "per_view": per_view})
            errors = browser.page_errors()
    finally:
        server.shutdown()
    result = {
        "benchmark": "spark_view", "date": datetime.date.today().isoformat(),
        "command": " ".join([os.path.relpath(sys.executable), *sys.argv]),
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count()},
        "viewer": list(PACKAGES), "chromium": chromium, "frames": args.frames, "wait_ms": args.wait_ms,
        "run_dir": os.path.abspath(args.run_dir),
        "test_views": [v.name for v in views], "page_errors": errors, "rows": rows, "seconds": time.time() - t0,
    }
    out = record.stem("spark_view", args.tag)
    import cv2

    sheet = torch.cat([torch.cat(row, 1) for row in shots.values()], 0).numpy()  # rows: views; columns: photo, files
    # JPEG: a sheet of 384 px photos is 2 MB as PNG; the figures come from the lossless screenshots, not from it.
    cv2.imwrite(out + ".jpg", (sheet[..., ::-1] * 255).round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 85])
    result["contact_sheet"] = os.path.relpath(out + ".jpg", os.path.dirname(HERE))
    write_record(out, result, markdown)


def markdown(r: dict) -> str:
    lines = [f"# Our exports in Spark (headless Chromium, SwiftShader) ({r['date']})", "",
             f"Run `{r['run_dir']}`, test views {', '.join(r['test_views'])}. Viewer: {', '.join(r['viewer'])} "
             f"({r['chromium']}); each view rendered until two renders in a row change no pixel (at most "
             f"{r.get('frames', FRAMES)}, {r.get('wait_ms', WAIT_MS)} ms apart). Machine: {r['machine']['platform']}, "
             f"{r['machine']['cpu_count']} CPUs.",
             f"Command: `{r['command']}` ({r['seconds']:.0f} s). Page errors: {r['page_errors'] or 'none'}.",
             f"Contact sheet `{r['contact_sheet']}`: one row per test view; the photo, then Spark's image of each "
             "file in the order below.", "",
             "Spark vs ours: the screenshot against our renderer's image of the same file (read back by ctgs); "
             "vs photo: against the test photo. Means over the test views.", "",
             "| file | splats | MB | Spark vs photo (dB) | ours vs photo (dB) | Spark vs ours (dB) |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for row in r["rows"]:
        lines.append(f"| {row['file']} | {row['splats']} | {row['bytes'] / 1e6:.3f} | {row['psnr_spark_vs_photo']:.2f} "
                     f"| {row['psnr_ours_vs_photo']:.2f} | {row['psnr_spark_vs_ours']:.2f} |")
    lines += ["", "| file | view | Spark vs photo | ours vs photo | Spark vs ours | renders | stable | seconds |",
              "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: |"]
    for row in r["rows"]:
        for p in row["per_view"]:
            lines.append(f"| {row['file']} | {p['view']} | {p['psnr_spark_vs_photo']:.2f} | "
                         f"{p['psnr_ours_vs_photo']:.2f} | {p['psnr_spark_vs_ours']:.2f} | {p.get('frames', '')} | "
                         f"{p.get('stable', '')} | {p['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
