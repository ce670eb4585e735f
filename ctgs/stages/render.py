"""`ctgs render RUN_DIR -o OUT_DIR`: render a trained run's test (or all) views to PNG files; with `--path`, a video
(`-o OUT.mp4`) along a camera path fitted to the training cameras or read from a camera path file."""

from __future__ import annotations

import os
import re

import click

MAPS = ("rgb", "normal", "depth", "texels")
PATH_MAPS = ("rgb", "texels")  # what a video can show
DEFAULT_FRAMES = 120
DEFAULT_FPS = 30.0


@click.command(name="render")
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out", required=True, type=click.Path(),
              help="Folder for the rendered PNGs, named after the views (created; an earlier `ctgs render` folder is "
                   "replaced whole, any other non-empty folder refused); with --path, the video file (OUT.mp4).")
@click.option("--backend", type=click.Choice(["auto", "cpu", "cuda", "reference"]), default="auto",
              show_default=True, help="Renderer backend; `reference` is the slow pure-PyTorch one.")
@click.option("--views", type=click.Choice(["test", "train", "all"]), default=None,
              help="Which of the scene's views to render (test = every holdout-th image)  [default: test]")
@click.option("--model", "model_dir", default=None, type=click.Path(file_okay=False),
              help="Render this exported/compressed model folder instead of RUN_DIR/model.pt.")
@click.option("--maps", default="rgb", show_default=True, metavar="LIST",
              help="Comma-separated maps per view: rgb (NAME.png), normal (NAME.normal.png: the blended surfel normal "
                   "in camera space, x right, y down, z forward, as (n + 1) / 2, alpha in the 4th channel), depth "
                   "(NAME.depth.exr: expected camera-space depth, depth / alpha, float32, 0 where nothing is drawn), "
                   "texels (NAME.texels.png: texel size in pixels, NAME.texres.png: texels per surfel, on fixed "
                   "colour scales: docs/guide/rendering.md). With --path: rgb or texels (the texel size).")
@click.option("--scene", "scene_dir", default=None, type=click.Path(file_okay=False),
              help="This machine's copy of the scene the run trained on, when the run moved from the machine or "
                   "folder it trained on (default: the folder its model.pt names).")
@click.option("--path", "path", default=None, metavar="orbit|spiral|interpolate|FILE",
              help="Render a video along a camera path instead of the views: orbit (an ellipse around a 360 capture, "
                   "a circle in front of a forward one), spiral (the same with a rise and fall), interpolate (a "
                   "spline through the training views), or FILE, a camera path saved by `ctgs view` (nerfstudio's "
                   "camera_path.json layout).")
@click.option("--frames", type=click.IntRange(1, 100_000), default=None,
              help=f"Frames of a fitted --path  [default: {DEFAULT_FRAMES}; a FILE has its own]")
@click.option("--fps", type=click.FloatRange(0.0, 1000.0, min_open=True), default=None,
              help=f"Frames per second of the video  [default: {DEFAULT_FPS:g}; a FILE's own]")
@click.option("--size", default=None, metavar="WxH",
              help="Image size in pixels (any: the cameras' focal lengths scale with it)  [default: the views' own; "
                   "with --path the training views' (made even), or a FILE's]")
@click.option("--codec", type=click.Choice(["vp9", "mpeg4"]), default="vp9", show_default=True,
              help="Video codec: vp9 plays in browsers, VLC and mpv; mpeg4 in older players such as QuickTime.")
def command(run_dir: str, out: str, backend: str, views: str | None, model_dir: str | None, maps: str,
            scene_dir: str | None, path: str | None, frames: int | None, fps: float | None, size: str | None,
            codec: str) -> None:
    """Render RUN_DIR/model.pt (or --model) from the cameras of the scene it was trained on, or along --path."""
    import torch

    from ctgs.runs import load_run, run_scene, with_scene
    from ctgs.scene.loader import check_same_frame

    wanted = [m.strip() for m in maps.split(",") if m.strip()]
    unknown = sorted(set(wanted) - set(MAPS))
    if unknown or not wanted:
        raise click.BadParameter(f"{maps!r}: use a comma-separated list of {', '.join(MAPS)}", param_hint="--maps")
    wh = _size(size)
    if path is None:
        for name, value in (("--frames", frames), ("--fps", fps)):
            if value is not None:
                raise click.BadParameter("applies to a video: pass --path too", param_hint=name)
    else:
        from ctgs.io.video import check_path

        if views is not None:
            raise click.BadParameter("a video follows --path, not the scene's views: pass one of them",
                                     param_hint="--views")
        if len(wanted) != 1 or wanted[0] not in PATH_MAPS:
            raise click.BadParameter(f"{maps!r}: a video shows one of {', '.join(PATH_MAPS)}", param_hint="--maps")
        check_path(out, codec)
    device = "cuda" if backend == "cuda" or (backend == "auto" and torch.cuda.is_available()) else "cpu"
    run = with_scene(load_run(run_dir, device=device), scene_dir)
    scene = run_scene(run, load_images=False)
    model = run.model
    check_same_frame(run.world_origin, scene, run.run_dir)
    if model_dir is not None:
        from ctgs.formats.model_format import read_model

        model, files = read_model(model_dir, device=device)
        check_same_frame(files.manifest.get("source", {}).get("world_origin"), scene, model_dir)
    bg = run.config.get("background") or (0.0, 0.0, 0.0)
    if path is None:
        _views(model, scene, views or "test", out, wanted, backend, device, bg, wh)
    else:
        _video(model, scene, path, out, wanted[0], backend, device, bg, wh, frames, fps, codec)


def _size(size: str | None) -> tuple[int, int] | None:
    if size is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", size)
    if not m or not 1 <= int(m.group(1)) <= 16384 or not 1 <= int(m.group(2)) <= 16384:
        raise click.BadParameter(f"{size!r}: pass WIDTHxHEIGHT in pixels, e.g. 800x600", param_hint="--size")
    return int(m.group(1)), int(m.group(2))


def resized(camera, size: tuple[int, int] | None):
    """`camera` for an image of size = (W, H) pixels (focal lengths and principal point scaled), or as it is."""
    from dataclasses import replace

    if size is None:
        return camera
    sx, sy = size[0] / camera.width, size[1] / camera.height
    return replace(camera, fx=camera.fx * sx, fy=camera.fy * sy, cx=camera.cx * sx, cy=camera.cy * sy,
                   width=size[0], height=size[1])


def _views(model, scene, views: str, out_dir: str, wanted: list[str], backend: str, device: str, bg,
           size: tuple[int, int] | None) -> None:
    import torch

    from ctgs.io import lock, owner
    from ctgs.io.images import write_image
    from ctgs.render import render
    from ctgs.render.texel_map import render_map

    if os.path.isfile(out_dir):
        raise click.BadParameter(f"{out_dir} is a file: pass a folder for the views (a video needs --path)",
                                 param_hint="-o")
    owner.check_ours(out_dir, "render", "an earlier `ctgs render` folder")
    chosen = {"test": scene.test, "train": scene.train, "all": scene.train + scene.test}[views]
    # Rendered into a temporary sibling that becomes OUT_DIR when every view is written (an earlier render
    # folder is replaced whole): a failure part-way leaves nothing behind.
    with torch.no_grad(), lock.inside_run(out_dir), owner.owned_dir(out_dir, "render") as tmp:
        inputs = model.render_inputs()
        bgt = torch.tensor(bg, dtype=inputs.means.dtype, device=device)
        for view in chosen:
            cam = resized(view.camera, size).to(device, inputs.means.dtype)
            stem = os.path.join(tmp, os.path.splitext(os.path.basename(view.name))[0])
            if "rgb" in wanted:
                rgb = render(inputs, cam, backend=backend, sh_degree=model.sh_degree, background=bgt).rgb  # [H, W, 3]
                write_image(stem + ".png", rgb.clamp(0, 1).cpu().numpy())
            if "normal" in wanted or "depth" in wanted:
                normal, alpha, depth = geometry_maps(inputs, cam, backend)
                if "normal" in wanted:
                    rgba = torch.cat([(normal + 1) * 0.5, alpha[..., None]], -1)
                    write_image(stem + ".normal.png", rgba.clamp(0, 1).cpu().numpy(), bits=16)
                if "depth" in wanted:
                    write_image(stem + ".depth.exr", depth.cpu().numpy(), half=False)
            if "texels" in wanted:
                write_image(stem + ".texels.png", render_map(inputs, cam, "texel_size", backend).cpu().numpy())
                write_image(stem + ".texres.png", render_map(inputs, cam, "texture_res", backend).cpu().numpy())
    click.echo(f"{out_dir}: {len(chosen)} {views} views rendered ({', '.join(wanted)}) with backend {backend}")


def _video(model, scene, path: str, out: str, what: str, backend: str, device: str, bg,
           size: tuple[int, int] | None, frames: int | None, fps: float | None, codec: str) -> None:
    import numpy as np
    import torch
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
        TimeRemainingColumn

    from ctgs.errors import UserError
    from ctgs.io import lock
    from ctgs.io.video import check_size, open_video
    from ctgs.render import render
    from ctgs.render.texel_map import render_map
    from ctgs.scene.camera_path import PATH_KINDS, fit_path, path_cameras, read_camera_path, vertical_fov

    if not scene.train:
        raise UserError(f"{scene.root}: no training views to fit a camera path to; render a path file instead "
                        "(--path FILE)")
    ref = scene.train[0].camera
    near = float(ref.near)
    if path in PATH_KINDS:
        n = frames or DEFAULT_FRAMES
        viewmats = fit_path(path, [v.camera.viewmat for v in scene.train], n, scene.points)
        fov = float(np.median([vertical_fov(v.camera) for v in scene.train]))
        width, height = size or (ref.width - ref.width % 2, ref.height - ref.height % 2)
        rate = fps or DEFAULT_FPS
    else:
        if frames is not None:
            raise click.BadParameter(f"{path} holds its own frames (camera_path); --frames applies to "
                                     f"{'|'.join(PATH_KINDS)}", param_hint="--frames")
        file = read_camera_path(path)
        viewmats, fov = file.viewmats, file.fov_y
        width, height = size or (file.width, file.height)
        rate = fps or file.fps
    check_size(width, height, "--size" if size else (path if path not in PATH_KINDS else "the training views"))
    cams = path_cameras(viewmats, fov, width, height, near)
    columns = [TextColumn("[bold]render"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("ETA"),
               TimeRemainingColumn()]
    with torch.no_grad(), lock.inside_run(out), open_video(out, rate, width, height, codec) as video, \
            Progress(*columns, console=Console(stderr=True)) as progress:
        inputs = model.render_inputs()
        bgt = torch.tensor(bg, dtype=inputs.means.dtype, device=device)
        task = progress.add_task("frames", total=len(cams))
        for cam in cams:
            cam = cam.to(device, inputs.means.dtype)
            if what == "rgb":
                img = render(inputs, cam, backend=backend, sh_degree=model.sh_degree, background=bgt).rgb
            else:
                img = render_map(inputs, cam, "texel_size", backend)
            video.write(img.clamp(0, 1).cpu().numpy())
            progress.advance(task)
    click.echo(f"{out}: {len(cams)} frames of {width}x{height} at {rate:g} fps ({len(cams) / rate:.1f} s, {codec}, "
               f"{what}) along {path} with backend {backend}")


def geometry_maps(inputs, camera, backend: str):
    """(normal [H, W, 3] unit camera-space blended surfel normal facing the camera, 0 where nothing is drawn;
    alpha [H, W]; expected depth [H, W] = depth / alpha, 0 where alpha <= 1e-6): one render with the surfels'
    normals as colour (ctgs.train.components.normal, the maps 2DGS's normal term compares)."""
    import torch

    from ctgs.train.components.normal import blended_normal, expected_depth, render_normals

    out = render_normals(inputs, camera, backend)
    n = blended_normal(out)
    norm = n.norm(dim=-1, keepdim=True)
    normal = torch.where(norm > 1e-8, n / norm.clamp_min(1e-8), torch.zeros_like(n))
    return normal, out.alpha, expected_depth(out.depth, out.alpha)
