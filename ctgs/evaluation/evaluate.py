"""Evaluate a run (or an exported/compressed model of it) on the run's test views (or, split "train", on the views
it was trained on: how well it fits its own photos; the gap to the test views is what did not generalise).

Order matters for the figures: the model is loaded and every test view rendered first (timed,
synchronised, one untimed warm-up), peak memory is read right after rendering, and only then is the
LPIPS network loaded, so neither its weights nor metric computation count as render time or memory.
"""

from __future__ import annotations

import os
import platform
import resource
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.evaluation.report import (METRICS_SCHEMA, METRICS_VERSION, OPEN_ALPHA, ImageMetrics, strip,
                                    write_metrics_json, write_per_image_csv)
from ctgs.formats.model_format import read_model
from ctgs.formats.readers import gaussian_file_ending, read_gaussian_file
from ctgs.io import images, lock, owner
from ctgs.metrics.lpips import load_lpips, lpips_hwc
from ctgs.metrics.psnr import gain_matched_psnr, masked_psnr, psnr
from ctgs.metrics.ssim import masked_ssim, ssim
from ctgs.render import render
from ctgs.render.texel_map import render_map
from ctgs.runs import load_run, run_scene, with_scene
from ctgs.scene.loader import check_same_frame, validation_split

LPIPS_CONVENTION = "LPIPS VGG v0.1, inputs in [0, 1] fed without rescaling to [-1, 1] (3DGS/2DGS convention)"
NUM_STRIPS = 2  # worst and best views (by PSNR) that get a gt | render | error (| texel size) strip each


@dataclass
class EvalOptions:
    out_dir: str
    model_dir: str | None = None  # exported/compressed model folder or exported Gaussian file; None = the run's model.pt
    backend: str | None = None  # None = the run's config backend (or "auto")
    device: str | None = None  # None = cuda if available, else cpu
    lpips: bool = True
    lpips_weights: str | None = None
    scene_dir: str | None = None  # this machine's copy of the run's scene, when the run moved (None: the one it names)
    dataset: str | None = None  # table grouping; None = name of the scene folder's parent
    scene_name: str | None = None  # the scene's name in tables; None = the scene folder's name
    split: str = "test"  # "test": the protocol's test views; "train": the views the run was trained on


def _render_fn(backend: str, background: torch.Tensor | None = None):
    return lambda inputs, cam, deg: render(inputs, cam, backend=backend, sh_degree=deg,
                                           background=None if background is None else background.to(cam.viewmat.device))


def veil_share(inputs, cam, sh_degree: int, backend: str) -> float:
    """The largest share of the view's blending weight (sum of alpha T over its pixels) carried by one primitive
    whose centre lies outside the view (behind the near plane or projecting off the image).

    Blending follows centre depth (docs/reference/renderer.md, Ordering): a surfel far larger than the scene, centred off
    to the side of a camera, is blended in front of the surface it crosses there, a veil over the view. Over the
    training views of 24 herzjesu25 runs (content-aware and 2dgs, 192 and 384 px) no such primitive carried more
    than 12% of a view (benchmarks/results/archive/oversized/herzjesu25_6f7d403.md)."""
    err = torch.zeros(cam.height, cam.width, device=inputs.means.device)
    return outside_share(render(inputs, cam, backend=backend, sh_degree=sh_degree, error_image=err).stats.contrib,
                         inputs.means, cam)


def outside_share(contrib: torch.Tensor, means: torch.Tensor, cam) -> float:
    """veil_share from a render's per-primitive `contrib` [N] (ErrorStats) and the centres `means` [N, 3]."""
    inside = cam.project(means.float())[3]
    outside = contrib.float()[~inside]
    return float(outside.max()) / (cam.width * cam.height) if outside.numel() else 0.0


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _machine(device: torch.device) -> dict:
    info = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "torch": torch.__version__, "torch_threads": torch.get_num_threads()}
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


# an eval folder written before folders were marked: these names only (ctgs.io.owner)
EVAL_FOLDER = owner.names_within(frozenset({"metrics.json", "per_image.csv", "renders", "strips"}), "metrics.json")


def evaluate(run_dir: str, opts: EvalOptions) -> dict:
    """Write metrics.json, per_image.csv, renders/*.png and strips/*.png into opts.out_dir; returns metrics."""
    owner.check_ours(opts.out_dir, "eval", "an earlier `ctgs eval` folder", legacy=EVAL_FOLDER)
    run = with_scene(load_run(run_dir), opts.scene_dir)
    device = torch.device(opts.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    scored = _scored_model(run, opts, device)
    backend = _backend(run, opts, device)
    background = [float(c) for c in run.config.get("background") or (0.0, 0.0, 0.0)]  # the run's (ctgs train)
    scene = run_scene(run, background=background)
    if scored.manifest is None:
        check_same_frame(run.world_origin, scene, run.run_dir)
    else:
        check_same_frame(scored.manifest.get("source", {}).get("world_origin"), scene, opts.model_dir)
    views = _views(run, scene, opts.split)
    renders, alphas, times, veils, peak = _render_views(scored.model, views, backend, device,
                                                        torch.tensor(background, dtype=torch.float32))

    net, status = None, None
    if opts.lpips:
        net, st = load_lpips(opts.lpips_weights, device)
        status = f"{LPIPS_CONVENTION}; VGG16 weights: {st.detail}" if st.available else st.detail
    else:
        status = "unavailable: skipped (--no-lpips)"

    # Everything is written into a temporary sibling that becomes opts.out_dir only when complete: a
    # failure (here or in a later view) leaves no half-written eval folder, and an earlier one intact.
    with lock.inside_run(opts.out_dir), owner.owned_dir(opts.out_dir, "eval") as out:
        rows, strips = _write_views(out, views, renders, alphas, times, veils, net, device,
                                    _texel_maps(scored.model, backend, device))
        metrics = _metrics(run, opts, scored, rows, strips, times, renders, net is not None, status, backend,
                           device, peak)
        write_metrics_json(os.path.join(out, "metrics.json"), metrics)
    return metrics


@dataclass
class _Scored:
    """The model an eval scores and where it came from: the run's model.pt, a model folder (manifest) or an
    exported Gaussian file (exported: its ending)."""
    model: object
    bytes_on_disk: int
    source: str
    manifest: dict | None
    exported: str | None


def _scored_model(run, opts: EvalOptions, device: torch.device) -> _Scored:
    model, bytes_on_disk, source = run.model, run.model_bytes, os.path.join(run.run_dir, "model.pt")
    manifest, exported = None, None
    if opts.model_dir and not os.path.isdir(opts.model_dir):  # an exported Gaussian file: what a viewer gets from it
        model, exported = read_gaussian_file(opts.model_dir), gaussian_file_ending(opts.model_dir)
        bytes_on_disk, source = os.path.getsize(opts.model_dir), os.path.abspath(opts.model_dir)
    elif opts.model_dir:
        model, files = read_model(opts.model_dir)
        bytes_on_disk, source, manifest = files.bytes_on_disk, os.path.abspath(opts.model_dir), files.manifest
    model = type(model).from_state_dict(model.state_dict(), device=device)
    return _Scored(model, bytes_on_disk, source, manifest, exported)


def _backend(run, opts: EvalOptions, device: torch.device) -> str:
    backend = opts.backend or str(run.config.get("backend", "auto"))
    if opts.backend is None and backend == "cuda" and device.type != "cuda":
        backend = "auto"  # trained on a GPU, evaluated where there is none: the run's backend is not a request
    if backend == "auto":  # the renderer's rule: cuda when the inputs live on a GPU, else cpu
        backend = "cuda" if device.type == "cuda" else "cpu"
    return backend


def _views(run, scene, split: str) -> list:
    """The views `split` scores (a validation run's training views exclude its validation views)."""
    if split == "train":
        # a validation run (validation_holdout > 0) was trained without its validation views
        views, _ = validation_split(scene.train, int(run.config.get("validation_holdout", 0)))
        if not views:
            raise UserError(f"{run.scene_dir}: no training views (holdout={run.holdout}); nothing to score with "
                            "--split train")
        return views
    if split == "test":
        if not scene.test:
            raise UserError(f"{run.scene_dir}: no test views (holdout={run.holdout}); train with holdout > 0 to "
                            "evaluate, or evaluate the training views with --split train")
        return scene.test
    raise UserError(f"eval split {split!r}: use test or train")


def _render_views(model, views: list, backend: str, device: torch.device, background: torch.Tensor | None = None):
    """Each view rendered and timed (after one warm-up render) over `background` (the run's), with its alpha and veil
    share; and the peak memory of the process (or of the GPU)."""
    render = _render_fn(backend, background)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    renders, alphas, times, veils = [], [], [], []
    with torch.no_grad():
        inputs = model.render_inputs()
        render(inputs, views[0].camera.to(device), model.sh_degree)  # warm-up: JIT build, caches
        for view in views:
            cam = view.camera.to(device)
            _sync(device)
            t0 = time.perf_counter()
            out = render(inputs, cam, model.sh_degree)
            _sync(device)
            times.append(time.perf_counter() - t0)
            renders.append(out.rgb.clamp(0.0, 1.0).float().cpu())
            alphas.append(out.alpha.reshape(out.rgb.shape[:2]).float().cpu())
            veils.append(veil_share(inputs, cam, model.sh_degree, backend))  # after the timing: not in the FPS
    if device.type == "cuda":
        peak = (torch.cuda.max_memory_allocated(device), "cuda_max_memory_allocated")
    else:
        peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, "process_max_rss")
    return renders, alphas, times, veils, peak


def _metrics(run, opts: EvalOptions, scored: _Scored, rows: list, strips: list, times: list, renders: list,
             scored_lpips: bool, status: str, backend: str, device: torch.device, peak: tuple) -> dict:
    """metrics.json's content (docs/reference/metrics.md)."""
    model, manifest, exported = scored.model, scored.manifest, scored.exported
    summary = run.summary or {}
    mean = lambda key: float(np.mean([getattr(r, key) for r in rows]))  # noqa: E731
    return {
        "schema": METRICS_SCHEMA, "schema_version": METRICS_VERSION,
        "scene": opts.scene_name or os.path.basename(os.path.normpath(run.scene_dir)),
        "dataset": opts.dataset or os.path.basename(os.path.dirname(os.path.normpath(run.scene_dir))),
        "run_dir": run.run_dir, "model_source": scored.source, "scene_dir": run.scene_dir,
        "images": run.images, "holdout": run.holdout, "split": opts.split, "num_views": len(rows),
        "num_test_views": len(rows) if opts.split == "test" else None,
        "test_list": "test_views.txt" if getattr(run, "test_views", None) else None,  # the scene's own test views
        "psnr": mean("psnr"), "ssim": mean("ssim"), "open_pixels": mean("open"),
        # exposure diagnostic (not the protocol's PSNR): PSNR after each view's least-squares gain
        "psnr_gain_matched": mean("psnr_gain"), "gain_range": [min(r.gain for r in rows), max(r.gain for r in rows)],
        "veil_max": max(r.veil for r in rows),
        "lpips": mean("lpips") if scored_lpips else None, "lpips_status": status,
        "points": model.num_primitives, "texels": model.num_texels, "params": model.num_params(),
        "texels_per_primitive": model.num_texels / max(model.num_primitives, 1),
        "model_memory_bytes": 4 * model.num_params(), "bytes_on_disk": scored.bytes_on_disk,
        "texture_encoding": manifest["texture_encoding"] if manifest else ("folded" if exported else "raw"),
        "exported_file": exported,  # the ending of an exported Gaussian file (--model FILE), else None
        "codebook_size": manifest.get("codebook_size") if manifest else None,
        "compressed": bool(manifest and "compression" in manifest),
        "compression_target": ((manifest or {}).get("compression") or {}).get("target"),
        "fps": len(times) / sum(times), "render_ms_mean": 1e3 * sum(times) / len(times),
        "backend": backend, "device": str(device), "resolution": [renders[0].shape[1], renders[0].shape[0]],
        "peak_memory_bytes": peak[0], "peak_memory_kind": peak[1],
        "train_seconds": summary.get("train_seconds"), "iterations": summary.get("iterations", run.iteration),
        "machine": _machine(device),
        "files": {"per_image_csv": "per_image.csv", "renders": "renders/", "strips": [f"strips/{s}" for s in strips]},
        "per_image": [asdict(r) for r in rows],
    }


def _texel_maps(model, backend: str, device: torch.device):
    """view -> [H, W, 3] the texel-size map of a textured model (the strips' fourth panel), None for a model without
    textures (2DGS, an exported Gaussian file)."""
    if model.texture_mode == "none" or not model.num_texels:
        return None
    inputs = model.render_inputs()

    def texel_map(view) -> np.ndarray:
        with torch.no_grad():
            return render_map(inputs, view.camera.to(device), "texel_size", backend).float().cpu().numpy()

    return texel_map


def _write_views(out: str, views: list, renders: list, alphas: list, times: list, veils: list, net,
                 device, texel_map=None) -> tuple[list[ImageMetrics], list[str]]:
    """Per-view metrics, out/renders/*.png, out/strips/*.png and out/per_image.csv; returns (rows, strip names).
    texel_map: view -> its texel-size picture, the strips' fourth panel (_texel_maps), or None."""
    os.makedirs(os.path.join(out, "renders"))
    os.makedirs(os.path.join(out, "strips"))
    rows: list[ImageMetrics] = []
    gts = []
    for view, rgb, alpha, dt, veil in zip(views, renders, alphas, times, veils):
        gt = torch.as_tensor(view.image, dtype=torch.float32)
        if gt.shape != rgb.shape:
            raise UserError(f"{view.image_path}: image is {list(gt.shape)}, render {list(rgb.shape)}; "
                            "the scene changed since training")
        mask = None if getattr(view, "mask", None) is None else torch.as_tensor(view.mask)
        keep = None if mask is None else mask[..., None]  # masked pixels: out of the scores, zero in both images
        scored, seen = (rgb, gt) if mask is None else (torch.where(keep, rgb, 0.0), torch.where(keep, gt, 0.0))
        lp = None
        if net is not None:
            lp = lpips_hwc(net, scored.to(device), seen.to(device))
        open_px = alpha < OPEN_ALPHA
        used = ~open_px if mask is None else ~open_px & mask
        rows.append(ImageMetrics(view.name, psnr(rgb, gt) if mask is None else masked_psnr(rgb, gt, mask),
                                 float(ssim(rgb, gt)) if mask is None else masked_ssim(rgb, gt, mask), lp, dt * 1e3,
                                 float(open_px.float().mean()), masked_psnr(rgb, gt, used), veil,
                                 *gain_matched_psnr(scored, seen)))
        images.write_image(os.path.join(out, "renders", os.path.splitext(view.name)[0] + ".png"), rgb.numpy())
        gts.append(gt)

    order = sorted(range(len(rows)), key=lambda i: rows[i].psnr)
    # Distinct views: the worst NUM_STRIPS, then the best among the rest (few test views may overlap).
    per_side = min(NUM_STRIPS, max(1, len(order) // 2))
    worst = order[:per_side]
    best = [i for i in order[::-1] if i not in worst][:per_side]
    strips = []
    for rank, i in [("worst", i) for i in worst] + [("best", i) for i in best]:
        name = f"{rank}_{os.path.splitext(rows[i].name)[0]}.png"
        texels = texel_map(views[i]) if texel_map is not None else None
        images.write_image(os.path.join(out, "strips", name), strip(gts[i].numpy(), renders[i].numpy(), texels))
        strips.append(name)
    write_per_image_csv(os.path.join(out, "per_image.csv"), rows)

    return rows, strips
