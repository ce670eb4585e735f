"""Where a trained model spent its texels, on one test view: the photo, the render, the texel size in pixels and the
texels per surfel (ctgs.render.texel_map, the pictures of `ctgs render --maps texels`), side by side with their scales;
and, over the pixels the textured surfels cover, how the texel size follows the photo's detail: its geometric mean
over the flattest quarter of the pixels and over the most detailed quarter, and the rank correlation of the two.

Detail: the photo's grey-level gradient magnitude (Sobel), averaged over DETAIL_WINDOW x DETAIL_WINDOW pixels.
Results: benchmarks/results/texel_figure/<name>_<commit>.{png,md,json}.

Usage: .venv/bin/python benchmarks/texel_figure.py RUN_DIR --name bonsai252_images_4_fast5min [--view NAME] [--zoom 2]
"""

from __future__ import annotations

import argparse
import os
import sys
from datetime import datetime, timezone

import cv2
import numpy as np
import torch

import record

sys.path.insert(0, record.ROOT)
from ctgs.io.images import read_rgb, write_image  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.render.texel_map import blend, compose, legend, value_of  # noqa: E402
from ctgs.runs import load_run, run_scene  # noqa: E402

DETAIL_WINDOW = 9  # pixels
MIN_COVER = 0.5  # pixels where the textured surfels' blended weight is at least this are scored
HEADER_PX = 22
GAP_PX = 8


def _ranks(x: np.ndarray) -> np.ndarray:
    r = np.empty(len(x))
    r[np.argsort(x, kind="stable")] = np.arange(len(x))
    return r


def detail(photo: np.ndarray) -> np.ndarray:
    """[H, W] local detail of an RGB photo in [0, 1]: gradient magnitude of its grey levels, box-averaged."""
    grey = cv2.cvtColor(np.ascontiguousarray(photo, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    g = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    return cv2.blur(g, (DETAIL_WINDOW, DETAIL_WINDOW))


def _panel(img: np.ndarray, title: str, zoom: int, under: np.ndarray | None = None) -> np.ndarray:
    big = cv2.resize(img, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    head = np.zeros((HEADER_PX, big.shape[1], 3), np.uint8)  # (OpenCV writes text into 8-bit images only)
    cv2.putText(head, title, (4, HEADER_PX - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    head = head.astype(np.float32) / 255.0
    parts = [head, big] + ([under] if under is not None else [np.zeros((28, big.shape[1], 3), np.float32)])
    return np.concatenate(parts, 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--name", required=True, help="record name: scene, resolution, variant")
    ap.add_argument("--view", default=None, help="test view name (default: the first)")
    ap.add_argument("--zoom", type=int, default=2, help="pixels of the figure per rendered pixel")
    args = ap.parse_args()
    run = load_run(args.run)
    scene = run_scene(run, load_images=False)
    view = next((v for v in scene.test if v.name == args.view), None) if args.view else scene.test[0]
    if view is None:
        raise SystemExit(f"{args.view}: not a test view of {scene.root}")
    cam = view.camera
    photo = read_rgb(view.image_path)
    inputs = run.model.render_inputs()
    bg = torch.tensor(run.config.get("background") or (0.0, 0.0, 0.0))
    with torch.no_grad():
        rgb = render(inputs, cam, sh_degree=run.model.sh_degree, background=bg).rgb.clamp(0, 1).numpy()
        maps, stats = {}, {}
        for which in ("texel_size", "texture_res"):
            r, g, a = blend(inputs, cam, which)
            maps[which] = compose(r, g, a).numpy()
            covered = (g >= MIN_COVER).numpy()
            stats[which] = value_of(torch.where(g > 0, r / g.clamp_min(1e-12), torch.zeros_like(r)), which).numpy()
    d = detail(photo)
    keep = covered
    dk, px, res = d[keep], stats["texel_size"][keep], stats["texture_res"][keep]
    lo_q, hi_q = np.quantile(dk, [0.25, 0.75])
    flat, busy = dk <= lo_q, dk >= hi_q
    gmean = lambda v: float(np.exp(np.mean(np.log(v))))  # noqa: E731
    result = {
        "run": os.path.abspath(args.run),
        "scene": os.path.basename(scene.root), "view": view.name, "size": [cam.width, cam.height],
        "trained": {k: run.config.get(k) for k in ("preset", "method", "images", "time_budget", "threads", "seed")},
        "train_seconds": (run.summary or {}).get("train_seconds"), "test_psnr": (run.summary or {}).get("final_test_psnr"),
        "iterations": run.iteration, "primitives": run.model.num_primitives, "texels": int(run.model.num_texels),
        "pixels_scored": int(keep.sum()), "pixels": int(keep.size),
        "texel_px_flat": gmean(px[flat]), "texel_px_detailed": gmean(px[busy]),
        "texels_per_surfel_flat": gmean(res[flat]), "texels_per_surfel_detailed": gmean(res[busy]),
        "spearman_detail_texel_px": float(np.corrcoef(_ranks(dk), _ranks(px))[0, 1]),
        "spearman_detail_texels_per_surfel": float(np.corrcoef(_ranks(dk), _ranks(res))[0, 1]),
        "commit": record.commit(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([os.path.relpath(sys.executable, record.ROOT)] + sys.argv),
    }
    w = cam.width * args.zoom
    panels = [_panel(photo, "photo", args.zoom), _panel(rgb, "render", args.zoom),
              _panel(maps["texel_size"], "texel size (pixels)", args.zoom, legend("texel_size", w)),
              _panel(maps["texture_res"], "texels per surfel", args.zoom, legend("texture_res", w))]
    gap = np.zeros((panels[0].shape[0], GAP_PX, 3), np.float32)
    figure = np.concatenate([x for p in panels for x in (p, gap)][:-1], 1)
    stem = record.stem("texel_figure", args.name)
    write_image(stem + ".png", figure)
    result["figure"] = os.path.relpath(stem + ".png", record.ROOT)

    def markdown(r: dict) -> str:
        return "\n".join([
            f"# Where the texels went: {r['scene']}, test view {r['view']} ({r['size'][0]}x{r['size'][1]})", "",
            f"Written by benchmarks/texel_figure.py on {r['date']} at commit {r['commit']}. Command: `{r['command']}`",
            "", f"Model: {r['iterations']} iterations, {r['primitives']:,} surfels, {r['texels']:,} texels, test PSNR "
            f"{r['test_psnr']:.2f} dB; trained with {', '.join(f'{k} {v}' for k, v in r['trained'].items())} "
            f"({r['train_seconds']:.0f} s of steps). Figure: "
            f"`{r['figure']}` (photo, render, texel size in pixels, texels per surfel).", "",
            f"Over the {r['pixels_scored']:,} of {r['pixels']:,} pixels the textured surfels cover (blended weight >= "
            f"{MIN_COVER}), by the photo's detail (gradient magnitude over {DETAIL_WINDOW}x{DETAIL_WINDOW} pixels):",
            "", "| pixels | texel size (px, geometric mean) | texels per surfel (geometric mean) |",
            "| --- | ---: | ---: |",
            f"| flattest quarter | {r['texel_px_flat']:.2f} | {r['texels_per_surfel_flat']:.1f} |",
            f"| most detailed quarter | {r['texel_px_detailed']:.2f} | {r['texels_per_surfel_detailed']:.1f} |", "",
            f"Rank correlation with the detail: texel size {r['spearman_detail_texel_px']:+.2f}, texels per surfel "
            f"{r['spearman_detail_texels_per_surfel']:+.2f}.", ""])

    record.write_record(stem, result, markdown)


if __name__ == "__main__":
    main()
