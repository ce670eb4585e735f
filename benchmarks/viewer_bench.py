"""The web viewer in headless Chromium: per-view PSNR against `ctgs render`, where the difference comes
from, frame times, bundle bytes; a screenshot of the viewer.
Results: benchmarks/results/viewer_bench/demo_<commit>.{md,json} and demo_screenshot_<commit>.png beside them.

Usage: .venv/bin/python benchmarks/viewer_bench.py [--run RUN_DIR] [--work /tmp/ctgs_viewer_bench]
       [--frames 20] [--big-surfels 200000] [--size 1280x720] [--skip-big]

Without --run it trains the demo model of `make demo` (96x72 demo scene, 24 views, 1500 points,
preset `fast`: 3000 iterations, seed 0; ~7 min on one idle thread). The ~200k-surfel model is synthetic
(`big_model`): object-centric like the paper's Mip-NeRF 360 captures, texel counts like the paper's.
Software GL only (SwiftShader) unless --gpu (Chromium with ANGLE on Vulkan; label the results).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ctgs.io.images import read_rgb, write_image  # noqa: E402
from ctgs.runs import load_run  # noqa: E402
from ctgs.formats.web_bundle import read_web_bundle, scene_cameras, write_web_bundle  # noqa: E402
from ctgs.model.surfels import SurfelModel, jagged_offsets  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.render.camera import Camera  # noqa: E402
from ctgs.viewer.server import ViewerServer  # noqa: E402
from headless import Browser, find_chromium  # noqa: E402 (benchmarks/headless.py)
from viewer_page import PANEL_CSS_PX, ViewerPage  # noqa: E402 (benchmarks/viewer_page.py)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(REPO, "benchmarks", "results", "viewer_bench")
DEMO_SCENE = dict(num_views=24, width=96, height=72, points=1500)
# The paper's texels per primitive range from 30.8 (bonsai) to 450.5 (bicycle), 214 on average over
# Mip-NeRF 360 (46.6M texels / 218K points): the big model draws each surfel's count uniformly from
# [30, 400] (mean 215).
BIG_TEXELS = (30, 400)
SCREENSHOT_VIEW = (640, 480)
COVERAGE_SIZE = (320, 240)  # demo image size for the coverage-quad timing (96x72 is too small to tell)  # CSS pixels of the image area in the committed screenshot


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else -10 * math.log10(mse)


def db(v) -> str:
    """A PSNR for the tables: identical images (inf, stored as "inf" in the JSON) say so."""
    return "identical" if v in ("inf", math.inf) else f"{v:.2f}"


def json_safe(x):
    """inf -> "inf" (JSON has no infinity)."""
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x


def quantise(rgb: torch.Tensor) -> np.ndarray:
    """Float image -> what a PNG written by `ctgs render` reads back as (8 bits, round to nearest)."""
    return np.round(rgb.clamp(0, 1).double().cpu().numpy() * 255) / 255


def machine() -> dict:
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    chromium = find_chromium()
    version = subprocess.run([chromium, "--version"], capture_output=True, text=True).stdout.strip() if chromium else ""
    return {"host": platform.node(), "cpu": cpu, "cores": os.cpu_count(), "torch": torch.__version__,
            "chromium": version, "loadavg_start": os.getloadavg()}


# ---- models --------------------------------------------------------------------------------------------
def demo_run(work: str, run: str | None) -> str:
    if run:
        return run
    from ctgs.scene.demo import make_demo_scene

    scene = make_demo_scene(os.path.join(work, "scene"), **DEMO_SCENE)
    run = os.path.join(work, "run")
    if not os.path.isfile(os.path.join(run, "model.pt")):
        subprocess.run([sys.executable, "-m", "ctgs", "train", scene, "-o", run, "--preset", "fast", "--set",
                        "threads=1", "--seed", "0", "-q"], check=True)
    return run


def big_model(n: int, seed: int = 0) -> tuple[SurfelModel, list[dict]]:
    """n surfels on the surfaces of a ground disc and a few ellipsoids (everything in view of an orbit
    camera, as in object-centric captures); tangent to the surface, sizes so that ~4 surfels overlap
    a surface point, opacities skewed high, SH degree 3, texel counts uniform in BIG_TEXELS with a
    grid spanning +-3 sigma ("fixed" texel size mode). Returns the model and 8 orbit cameras."""
    g = np.random.default_rng(seed)
    # surfaces: ground disc radius 3 at y = 1 (y down), five ellipsoids resting on it; surfels per
    # surface in proportion to its area (ellipsoid areas approximated by 4 pi (abc)^(2/3))
    centres = np.array([[0, 0.2, 0], [1.6, 0.5, 0.6], [-1.5, 0.4, -0.5], [0.4, 0.55, -1.7], [-0.6, 0.6, 1.6]])
    radii = np.array([[0.9, 0.8, 0.9], [0.5, 0.5, 0.6], [0.6, 0.6, 0.5], [0.5, 0.45, 0.5], [0.4, 0.4, 0.5]])
    area_ground, area_obj = np.pi * 3.0**2, 4 * np.pi * (radii.prod(1) ** (2 / 3)).sum()
    n_ground = int(round(n * area_ground / (area_ground + area_obj)))
    r = 3.0 * np.sqrt(g.random(n_ground))
    phi = 2 * np.pi * g.random(n_ground)
    ground = np.stack([r * np.cos(phi), np.ones(n_ground), r * np.sin(phi)], 1)
    ground_n = np.tile([0.0, -1.0, 0.0], (n_ground, 1))
    n_obj = n - n_ground
    which = g.choice(len(centres), n_obj, p=radii.prod(1) ** (2 / 3) / (radii.prod(1) ** (2 / 3)).sum())
    d = g.normal(size=(n_obj, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    obj = centres[which] + d * radii[which]
    obj_n = d / radii[which] ** 2
    obj_n /= np.linalg.norm(obj_n, axis=1, keepdims=True)
    means = np.concatenate([ground, obj]).astype(np.float32)
    normals = np.concatenate([ground_n, obj_n])
    # ~4 surfels cover each surface point within 2 sigma: n pi (2 sigma)^2 = 4 area
    sigma = np.sqrt(4 * (area_ground + area_obj) / (n * np.pi * 4))
    scales = sigma * np.exp(g.normal(0, 0.35, size=(n, 2)))
    # rotation whose third column is the normal, random spin about it
    a = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 0, 1.0]])
    u = np.cross(normals, a)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    spin = 2 * np.pi * g.random(n)
    u, v = np.cos(spin)[:, None] * u + np.sin(spin)[:, None] * v, -np.sin(spin)[:, None] * u + np.cos(spin)[:, None] * v
    rot = torch.from_numpy(np.stack([u, v, normals], 2))  # columns u, v, n
    quats = _rotmat_to_quat(rot).float()
    texels = g.integers(BIG_TEXELS[0], BIG_TEXELS[1] + 1, n)
    aspect = scales[:, 0] / scales[:, 1]
    res_u = np.clip(np.rint(np.sqrt(texels * aspect)), 1, None).astype(np.int64)
    res_v = np.clip(np.rint(texels / res_u), 1, None).astype(np.int64)
    res = torch.from_numpy(np.stack([res_u, res_v], 1).astype(np.int32))
    t = int((res_u * res_v).sum())
    k = 3
    sh = torch.from_numpy(g.normal(0, 0.1, size=(n, (k + 1) ** 2, 3)).astype(np.float32))
    sh[:, 0] = torch.from_numpy(((g.random((n, 3)) - 0.5) * 2.0).astype(np.float32))
    opacity = 0.2 + 0.8 * np.sqrt(g.random(n))
    model = SurfelModel(
        means=torch.from_numpy(means), log_scales=torch.from_numpy(np.log(scales).astype(np.float32)),
        quats=quats, opacity_logits=torch.from_numpy(np.log(opacity / (1 - opacity + 1e-6)).astype(np.float32)),
        sh=sh, textures_raw=torch.from_numpy(g.normal(0, 1.0, size=(t, 3)).astype(np.float32)),
        k_min=torch.full((n,), 1e-3), t2p_exp=torch.zeros(n, dtype=torch.int32), tex_res=res,
        tex_offset=jagged_offsets(res), sh_degree=k, texture_mode="fixed")
    cams = []
    for i in range(8):
        ang = 2 * np.pi * i / 8
        eye = np.array([5.5 * np.cos(ang), -2.2, 5.5 * np.sin(ang)])
        cams.append(_orbit_camera(f"orbit_{i}", eye, np.array([0.0, 0.4, 0.0]), 1280, 720))
    return model, cams


def _rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] -> [N, 4] (w, x, y, z) (Shepperd's method via the largest diagonal term)."""
    m = R.double()
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = torch.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], 1)
    best = cands.argmax(1)
    q = torch.zeros(len(m), 4, dtype=torch.float64)
    for b in range(4):
        s = best == b
        M = m[s]
        if b == 0:
            w = torch.sqrt(1 + tr[s]) / 2
            q[s] = torch.stack([w, (M[:, 2, 1] - M[:, 1, 2]) / (4 * w), (M[:, 0, 2] - M[:, 2, 0]) / (4 * w),
                                (M[:, 1, 0] - M[:, 0, 1]) / (4 * w)], 1)
        else:
            i, j, k = b - 1, b % 3, (b + 1) % 3
            x = torch.sqrt(1 + M[:, i, i] - M[:, j, j] - M[:, k, k]) / 2
            out = torch.zeros(len(M), 4, dtype=torch.float64)
            out[:, 0] = (M[:, k, j] - M[:, j, k]) / (4 * x)
            out[:, 1 + i] = x
            out[:, 1 + j] = (M[:, j, i] + M[:, i, j]) / (4 * x)
            out[:, 1 + k] = (M[:, k, i] + M[:, i, k]) / (4 * x)
            q[s] = out
    return q


def _orbit_camera(name: str, eye: np.ndarray, target: np.ndarray, w: int, h: int) -> dict:
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    view = np.eye(4)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    f = 0.9 * w  # ~70 degrees horizontal field of view
    return {"name": name, "split": "test", "width": w, "height": h, "fx": f, "fy": f, "cx": w / 2, "cy": h / 2,
            "near": 0.01, "viewmat": view.reshape(-1).tolist()}


def camera_of(c: dict) -> Camera:
    return Camera(fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"], width=c["width"], height=c["height"],
                  viewmat=torch.tensor(c["viewmat"], dtype=torch.float64).reshape(4, 4).float(), near=c["near"])


# ---- measurements ------------------------------------------------------------------------------------
def cpu_renders(run_dir: str, out: str, textures: bool) -> None:
    """`ctgs render` of the test views (textures on) or the same renderer with textures dropped."""
    if textures:
        subprocess.run([sys.executable, "-m", "ctgs", "render", run_dir, "-o", out], check=True)
        return
    from ctgs.scene.loader import load_scene

    r = load_run(run_dir)
    r.model.texture_mode = "none"
    os.makedirs(out, exist_ok=True)
    with torch.no_grad():
        inputs = r.model.render_inputs()
        for v in load_scene(r.scene_dir, images=r.images, holdout=r.holdout, load_images=False).test:
            rgb = render(inputs, v.camera, backend="cpu", sh_degree=r.model.sh_degree).rgb
            write_image(os.path.join(out, os.path.splitext(v.name)[0] + ".png"), rgb.clamp(0, 1).numpy())


def decomposition(run_dir: str, bundles: dict[int, str], cams: list[dict]) -> dict:
    """Per test view, PSNR vs the CPU render (8-bit images) of: the CPU render of the stored bundle
    (texel precision only), and the reference renderer with and without the T < 1e-4 early stop
    (blend-all = what a rasteriser does; the ordering is the same)."""
    import ctgs.render.reference as ref_mod

    r = load_run(run_dir)
    deg = r.model.sh_degree
    full = r.model.render_inputs()
    decoded = {bits: read_web_bundle(path)[0] for bits, path in bundles.items()}
    out = {}
    for c in cams:
        cam = camera_of(c)
        with torch.no_grad():
            base = quantise(render(full, cam, backend="cpu", sh_degree=deg).rgb)
            row = {f"texels_{bits}bit": psnr(base, quantise(render(d, cam, backend="cpu", sh_degree=deg).rgb))
                   for bits, d in decoded.items()}
            row["reference_with_stop"] = psnr(base, quantise(render(full, cam, backend="reference", sh_degree=deg).rgb))
            saved = ref_mod.T_EPS
            ref_mod.T_EPS = 0.0  # never stop: blend every contribution, as the browser does
            try:
                row["reference_blend_all"] = psnr(base, quantise(render(full, cam, backend="reference",
                                                                        sh_degree=deg).rgb))
            finally:
                ref_mod.T_EPS = saved
        out[c["name"]] = row
    return out


def browser_psnr(page: ViewerPage, cams: list[tuple[int, dict]], ref_dir: str, textures: bool) -> dict:
    out = {}
    for i, c in cams:
        page.fit_viewport(c["width"], c["height"])
        shot = page.capture(i, textures=textures)
        out[c["name"]] = psnr(shot, read_rgb(os.path.join(ref_dir, os.path.splitext(c["name"])[0] + ".png")))
    return out


def tight_vs_box(page: ViewerPage, cams: list[tuple[int, dict]]) -> dict:
    """Per view, the largest difference (8-bit levels) between the tight coverage quads and bounds.h's
    conservative pixel boxes: 0 means the tight quads lose nothing."""
    out = {}
    for i, c in cams:
        page.fit_viewport(c["width"], c["height"])
        tight = page.capture(i)
        page.browser.evaluate("window.viewer.renderer.tightQuads = false")
        boxes = page.capture(i)
        page.browser.evaluate("window.viewer.renderer.tightQuads = true")
        out[c["name"]] = float(np.abs(tight - boxes).max() * 255)
    return out


def coverage_ratio(page: ViewerPage, camera: int, size, rounds: int, frames: int) -> dict:
    """Rendering work with bounds.h's pixel boxes / with the tight quads (the images are identical), in
    browser CPU time per frame (software GL: the rendering itself; fair on a busy machine, unlike wall
    time), `rounds` interleaved runs of `frames` frames each."""
    tight, box = [], []
    frame_times(page, camera, size, 1)  # warm-up: buffers for the new size, shader variants
    for _ in range(rounds):
        tight.append(frame_times(page, camera, size, frames)["cpu_ms_per_frame"])
        box.append(frame_times(page, camera, size, frames, tight=False)["cpu_ms_per_frame"])
    return {"size": list(size) if size else None, "tight_cpu_ms": tight, "box_cpu_ms": box,
            "ratio_per_round": [b / t for t, b in zip(tight, box)],
            "ratio_of_medians": float(np.median(box) / np.median(tight))}


def frame_times(page: ViewerPage, camera: int, size: tuple[int, int] | None, frames: int, tight: bool = True) -> dict:
    """Wall-clock draw times (issue to GPU completion) and the browser's CPU time per frame over an orbit."""
    if size:
        page.fit_viewport(*size)
    cpu0 = page.browser.cpu_seconds()
    res = page.benchmark(camera, frames, size=size, tight=tight)
    cpu = page.browser.cpu_seconds() - cpu0
    draw, sort = np.array(res["drawMs"]), np.array(res["sortMs"])
    return {"width": res["width"], "height": res["height"], "frames": frames, "drawn_surfels": res["count"],
            "draw_ms_median": float(np.median(draw)), "draw_ms_min": float(draw.min()),
            "draw_ms_max": float(draw.max()), "sort_ms_median": float(np.median(sort)),
            "fps_from_draw": 1000.0 / float(np.median(draw)),
            # frames + 1 draws: benchmark() first shows the start view
            "cpu_ms_per_frame": 1000.0 * cpu / (frames + 1)}


def screenshot(page: ViewerPage, camera: int, path: str) -> None:
    """The whole page (panel and image) with the canvas filling SCREENSHOT_VIEW (free-camera size)."""
    b = page.browser
    b.set_viewport(PANEL_CSS_PX + SCREENSHOT_VIEW[0], SCREENSHOT_VIEW[1])
    b.evaluate(f"window.viewer.show({{camera: {camera}, fit: false}})", timeout=600)
    b.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")  # readout repainted
    with open(path, "wb") as f:
        f.write(b.screenshot())


# ---- main -------------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--run", default=None, help="trained run folder (default: train the demo model)")
    ap.add_argument("--work", default="/tmp/ctgs_viewer_bench")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--big-frames", type=int, default=5)
    ap.add_argument("--big-surfels", type=int, default=200_000)
    ap.add_argument("--size", default="1280x720", help="frame-time image size besides the demo's own")
    ap.add_argument("--skip-big", action="store_true")
    ap.add_argument("--gpu", action="store_true", help="Chromium on the GPU (ANGLE/Vulkan), not SwiftShader")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    os.makedirs(args.work, exist_ok=True)
    info = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "command": " ".join(sys.argv),
            "machine": machine(), "gl": "GPU (ANGLE/Vulkan)" if args.gpu else "software (SwiftShader)"}
    t0 = time.time()
    os.makedirs(RESULTS, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short=7", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip() or "nogit"
    base = os.path.join(RESULTS, f"demo{args.tag}_{commit}")

    def stage(name: str) -> None:  # progress, and the figures so far (a crash keeps them)
        info.setdefault("stage_seconds", {})[name] = round(time.time() - t0, 1)
        print(f"[{time.time() - t0:7.1f} s] {name}", flush=True)
        with open(base + ".partial.json", "w") as f:
            json.dump(json_safe(info), f, indent=1)

    run = demo_run(args.work, args.run)
    r = load_run(run)
    cams = scene_cameras(r.scene_dir, r.images, r.holdout)
    bundles = {}
    for bits in (8, 16):
        bundles[bits] = os.path.join(args.work, f"web{bits}")
        b = write_web_bundle(r.model, bundles[bits], cams, texel_bits=bits)
        info[f"demo_bundle_{bits}bit"] = {k: b[k] for k in ("num_surfels", "num_texels", "bytes_per_surfel",
                                                            "bytes_per_texel")}
        info[f"demo_bundle_{bits}bit"].update(atlas_fill=b["atlas"]["fill"], pages=len(b["atlas"]["pages"]),
                                              surfels_bytes=b["surfels"]["bytes"], atlas_bytes=b["atlas"]["bytes"])
    on_dir, off_dir = os.path.join(args.work, "render_on"), os.path.join(args.work, "render_off")
    shutil.rmtree(on_dir, ignore_errors=True)
    shutil.rmtree(off_dir, ignore_errors=True)
    cpu_renders(run, on_dir, True)
    cpu_renders(run, off_dir, False)
    stage("cpu renders")
    test = [(i, c) for i, c in enumerate(cams) if c["split"] == "test"]
    info["decomposition"] = decomposition(run, bundles, [c for _, c in test])
    info["textures_on_vs_off"] = {c["name"]: psnr(read_rgb(os.path.join(on_dir, os.path.splitext(c["name"])[0] + ".png")),
                                                  read_rgb(os.path.join(off_dir, os.path.splitext(c["name"])[0] + ".png")))
                                  for _, c in test}
    stage("decomposition")
    with Browser(gpu=args.gpu, timeout=600) as browser:
        for bits in (8, 16):
            with ViewerServer(bundles[bits]) as srv:
                page = ViewerPage(browser, srv.url)
                info["gl_renderer"], info["accumulation"] = page.info["glRenderer"], page.info["accumFormat"]
                info[f"psnr_{bits}bit_on"] = browser_psnr(page, test, on_dir, True)
                info[f"psnr_{bits}bit_off"] = browser_psnr(page, test, off_dir, False)
                if bits == 8:
                    info["tight_vs_box_max_diff_255"] = tight_vs_box(page, test)
                    info["frames_demo_image_size"] = frame_times(page, test[0][0], None, args.frames)
                    info["frames_demo_resized"] = frame_times(page, test[0][0], size, args.frames)
                    info["demo_tight_vs_box"] = coverage_ratio(page, test[0][0], COVERAGE_SIZE, 3, 3)
                    screenshot(page, test[0][0], os.path.join(args.work, "screenshot.png"))
            stage(f"browser, {bits}-bit bundle")
        if not args.skip_big:
            model, big_cams = big_model(args.big_surfels)
            big_dir = os.path.join(args.work, "web_big")
            b = write_web_bundle(model, big_dir, big_cams, texel_bits=8)
            del model
            stage("big bundle written")
            info["big_bundle_8bit"] = {k: b[k] for k in ("num_surfels", "num_texels", "bytes_per_surfel",
                                                         "bytes_per_texel")}
            info["big_bundle_8bit"].update(atlas_fill=b["atlas"]["fill"], pages=len(b["atlas"]["pages"]),
                                           surfels_bytes=b["surfels"]["bytes"], atlas_bytes=b["atlas"]["bytes"])
            with ViewerServer(big_dir) as srv:
                t = time.time()
                page = ViewerPage(browser, srv.url)
                info["big_load_s"] = time.time() - t
                info["frames_big"] = frame_times(page, 0, None, args.big_frames)
                info["big_tight_vs_box"] = coverage_ratio(page, 0, None, 2, args.big_frames)
                stage("big model frame times")
    info["machine"]["loadavg_end"] = os.getloadavg()
    info["seconds"] = time.time() - t0
    if os.path.exists(base + ".partial.json"):
        os.remove(base + ".partial.json")
    with open(base + ".json", "w") as f:
        json.dump(json_safe(info), f, indent=1)
    shot = os.path.join(RESULTS, f"demo_screenshot{args.tag}_{commit}.png")
    shutil.copyfile(os.path.join(args.work, "screenshot.png"), shot)
    with open(base + ".md", "w") as f:
        f.write(markdown(info))
    print(markdown(info))


def markdown(info: dict) -> str:
    m = info["machine"]
    lines = [f"# Web viewer (`ctgs view`) in headless Chromium, {info['gl']}", "",
             f"Written by benchmarks/viewer_bench.py on {info['date']}: `{info['command']}`. Machine: {m['host']} "
             f"({m['cpu']}, {m['cores']} cores, load average {m['loadavg_start'][0]:.1f} at start, "
             f"{m['loadavg_end'][0]:.1f} at end), {m['chromium']}, WebGL2 renderer: {info['gl_renderer']}, "
             f"accumulation buffer {info['accumulation']}.", "",
             "Demo model: `make demo`'s (96x72 demo scene, 24 views, every 8th a test view, preset `fast`, "
             "3000 iterations, seed 0). Images are compared as the 8-bit PNGs both sides produce.", "",
             "## Browser vs `ctgs render`, per test view (PSNR, dB)", "",
             "| view | 8-bit texels, textures on | 8-bit, textures off | 16-bit texels, textures on | 16-bit, off "
             "| (ctgs render: textures on vs off) |", "| --- | --- | --- | --- | --- | --- |"]
    for name in info["psnr_8bit_on"]:
        lines.append(f"| {name} | {db(info['psnr_8bit_on'][name])} | {db(info['psnr_8bit_off'][name])} | "
                     f"{db(info['psnr_16bit_on'][name])} | {db(info['psnr_16bit_off'][name])} | "
                     f"{db(info['textures_on_vs_off'][name])} |")
    lines += ["", "## Where the difference comes from (CPU-side, PSNR vs the `ctgs render` image, dB)", "",
              "texel precision: the CPU renderer on the bundle's stored texels; blend-all: the reference renderer "
              "without the T < 1e-4 early stop (what the browser's rasteriser does; same depth order), beside the "
              "reference with the stop (agreement of two renderers of the same definition).", "",
              "| view | 8-bit texels | 16-bit texels | reference, blend-all | reference, with stop |",
              "| --- | --- | --- | --- | --- |"]
    for name, row in info["decomposition"].items():
        lines.append(f"| {name} | {db(row['texels_8bit'])} | {db(row['texels_16bit'])} | "
                     f"{db(row['reference_blend_all'])} | {db(row['reference_with_stop'])} |")
    lines += ["", "## Frame times (an orbit of N frames)", "",
              "draw: wall clock from issuing a frame to GPU completion (forced by a one-pixel read back), median "
              "and range; with software GL it grows with the machine's load (see the load averages above). "
              "browser CPU: CPU time of all browser processes per frame (SwiftShader renders on the CPU, so this "
              "is the rendering work, nearly independent of the load; two cores can at best halve it in wall "
              "time). sort: the Web Worker's depth sort (runs beside the drawing).", "",
              "| model | surfels | texels | image | frames | draw ms (median, min-max) | ~fps | browser CPU ms/frame "
              "| sort ms (worker) |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rows = [("demo", info["demo_bundle_8bit"], info["frames_demo_image_size"]),
            ("demo", info["demo_bundle_8bit"], info["frames_demo_resized"])]
    if "frames_big" in info:
        rows.append(("synthetic ~200k", info["big_bundle_8bit"], info["frames_big"]))
    for name, b, fr in rows:
        lines.append(f"| {name} | {b['num_surfels']:,} | {b['num_texels']:,} | {fr['width']}x{fr['height']} | "
                     f"{fr['frames']} | {fr['draw_ms_median']:.1f} ({fr['draw_ms_min']:.1f}-{fr['draw_ms_max']:.1f}) | "
                     f"{fr['fps_from_draw']:.2f} | {fr['cpu_ms_per_frame']:.0f} | {fr['sort_ms_median']:.1f} |")
    lines += ["", "## Bundle size", "", "| model | texel format | bytes/surfel | bytes/texel | atlas fill | pages |",
              "| --- | --- | --- | --- | --- | --- |"]
    for name, key in (("demo", "demo_bundle_8bit"), ("demo", "demo_bundle_16bit"), ("synthetic ~200k", "big_bundle_8bit")):
        if key in info:
            b = info[key]
            fmt = "float16" if "16" in key else "snorm8"
            lines.append(f"| {name} | {fmt} | {b['bytes_per_surfel']:.1f} | {b['bytes_per_texel']:.2f} | "
                         f"{b['atlas_fill']:.3f} | {b['pages']} |")
    if "tight_vs_box_max_diff_255" in info:
        diffs = ", ".join(f"{k} {v:.0f}" for k, v in info["tight_vs_box_max_diff_255"].items())
        lines += ["", f"Tight coverage quads vs bounds.h's pixel boxes on the demo test views, largest pixel "
                      f"difference in 8-bit levels: {diffs}."]
    for label, key in (("demo", "demo_tight_vs_box"), ("synthetic ~200k", "big_tight_vs_box")):
        if key in info:
            c = info[key]
            where = f"{c['size'][0]}x{c['size'][1]}" if c["size"] else "its camera's size"
            lines += ["", f"Coverage quads, {label} at {where}: browser CPU time per frame with bounds.h's pixel "
                          f"boxes / with the tight quads, interleaved rounds: "
                          f"{', '.join(f'{r:.2f}' for r in c['ratio_per_round'])} (ratio of medians "
                          f"{c['ratio_of_medians']:.2f}; tight {[round(t) for t in c['tight_cpu_ms']]} ms, "
                          f"boxes {[round(b) for b in c['box_cpu_ms']]} ms)."]
    if "big_load_s" in info:
        lines += ["", f"Loading the ~200k bundle (download from 127.0.0.1, uploads, shader compilation, first "
                      f"sort and draw) took {info['big_load_s']:.1f} s."]
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--table-only"]:  # rebuild the .md from a results JSON: --table-only FILE.json
        with open(sys.argv[2]) as fh:
            info = json_safe(json.load(fh))
        with open(sys.argv[2], "w") as fh:
            json.dump(info, fh, indent=1)
        with open(sys.argv[2][:-len(".json")] + ".md", "w") as fh:
            fh.write(markdown(info))
    else:
        main()
