"""`ctgs render RUN_DIR -o OUT_DIR`: render a trained run's test (or all) views to PNG files."""

from __future__ import annotations

import os

import click


@click.command(name="render")
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the rendered PNGs, named after the views (created; an earlier `ctgs render` folder is "
                   "replaced whole, any other non-empty folder refused).")
@click.option("--backend", type=click.Choice(["auto", "cpu", "cuda", "reference"]), default="auto",
              show_default=True, help="Renderer backend; `reference` is the slow pure-PyTorch one.")
@click.option("--views", type=click.Choice(["test", "train", "all"]), default="test", show_default=True,
              help="Which of the scene's views to render (test = every holdout-th image).")
@click.option("--model", "model_dir", default=None, type=click.Path(file_okay=False),
              help="Render this exported/compressed model folder instead of RUN_DIR/model.pt.")
@click.option("--maps", default="rgb", show_default=True, metavar="LIST",
              help="Comma-separated maps per view: rgb (NAME.png), normal (NAME.normal.png: the blended surfel normal "
                   "in camera space, x right, y down, z forward, as (n + 1) / 2, alpha in the 4th channel), depth "
                   "(NAME.depth.exr: expected camera-space depth, depth / alpha, float32, 0 where nothing is drawn).")
@click.option("--scene", "scene_dir", default=None, type=click.Path(file_okay=False),
              help="This machine's copy of the scene the run trained on, when the run moved from the machine or "
                   "folder it trained on (default: the folder its model.pt names).")
def command(run_dir: str, out_dir: str, backend: str, views: str, model_dir: str | None, maps: str,
            scene_dir: str | None) -> None:
    """Render RUN_DIR/model.pt (or --model) from the cameras of the scene it was trained on."""
    import torch

    from ctgs.io import lock, owner
    from ctgs.io.images import write_image
    from ctgs.render import render
    from ctgs.runs import load_run, run_scene, with_scene

    wanted = [m.strip() for m in maps.split(",") if m.strip()]
    unknown = sorted(set(wanted) - set(MAPS))
    if unknown or not wanted:
        raise click.BadParameter(f"{maps!r}: use a comma-separated list of {', '.join(MAPS)}", param_hint="--maps")
    owner.check_ours(out_dir, "render", "an earlier `ctgs render` folder")
    device = "cuda" if backend == "cuda" or (backend == "auto" and torch.cuda.is_available()) else "cpu"
    run = with_scene(load_run(run_dir, device=device), scene_dir)
    scene = run_scene(run, load_images=False)
    chosen = {"test": scene.test, "train": scene.train, "all": scene.train + scene.test}[views]
    from ctgs.scene.loader import check_same_frame

    model = run.model
    check_same_frame(run.world_origin, scene, run.run_dir)
    if model_dir is not None:
        from ctgs.formats.model_format import read_model

        model, files = read_model(model_dir, device=device)
        check_same_frame(files.manifest.get("source", {}).get("world_origin"), scene, model_dir)
    # Rendered into a temporary sibling that becomes OUT_DIR when every view is written (an earlier render
    # folder is replaced whole): a failure part-way leaves nothing behind.
    with torch.no_grad(), lock.inside_run(out_dir), owner.owned_dir(out_dir, "render") as tmp:
        inputs = model.render_inputs()
        bg = torch.tensor(run.config.get("background") or (0.0, 0.0, 0.0), dtype=inputs.means.dtype, device=device)
        for view in chosen:
            cam = view.camera.to(device, inputs.means.dtype)
            stem = os.path.join(tmp, os.path.splitext(os.path.basename(view.name))[0])
            if "rgb" in wanted:
                rgb = render(inputs, cam, backend=backend, sh_degree=model.sh_degree, background=bg).rgb  # [H, W, 3]
                write_image(stem + ".png", rgb.clamp(0, 1).cpu().numpy())
            if "normal" in wanted or "depth" in wanted:
                normal, alpha, depth = geometry_maps(inputs, cam, backend)
                if "normal" in wanted:
                    rgba = torch.cat([(normal + 1) * 0.5, alpha[..., None]], -1)
                    write_image(stem + ".normal.png", rgba.clamp(0, 1).cpu().numpy(), bits=16)
                if "depth" in wanted:
                    write_image(stem + ".depth.exr", depth.cpu().numpy(), half=False)
    click.echo(f"{out_dir}: {len(chosen)} {views} views rendered ({', '.join(wanted)}) with backend {backend}")


MAPS = ("rgb", "normal", "depth")


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
