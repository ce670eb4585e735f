"""`ctgs render RUN_DIR -o OUT_DIR`: render a trained run's test (or all) views to PNG files."""

from __future__ import annotations

import os

import click


@click.command(name="render")
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the rendered PNGs, named after the views (created; an earlier render folder is "
                   "replaced whole).")
@click.option("--backend", type=click.Choice(["auto", "cpu", "cuda", "reference"]), default="auto",
              show_default=True, help="Renderer backend; `reference` is the slow pure-PyTorch one.")
@click.option("--views", type=click.Choice(["test", "train", "all"]), default="test", show_default=True,
              help="Which of the scene's views to render (test = every holdout-th image).")
@click.option("--model", "model_dir", default=None, type=click.Path(file_okay=False),
              help="Render this exported/compressed model folder instead of RUN_DIR/model.pt.")
def command(run_dir: str, out_dir: str, backend: str, views: str, model_dir: str | None) -> None:
    """Render RUN_DIR/model.pt (or --model) from the cameras of the scene it was trained on."""
    import torch

    from ctgs.io import atomic
    from ctgs.io.images import write_image
    from ctgs.io.run_model import load_run
    from ctgs.render import render
    from ctgs.scene.loader import load_scene

    atomic.ensure_replaceable(out_dir, lambda names: all(n.endswith(".png") for n in names),
                              "an earlier render folder (PNG files only)")
    device = "cuda" if backend == "cuda" or (backend == "auto" and torch.cuda.is_available()) else "cpu"
    run = load_run(run_dir, device=device)
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout, load_images=False)
    chosen = {"test": scene.test, "train": scene.train, "all": scene.train + scene.test}[views]
    from ctgs.scene.loader import check_same_frame

    model = run.model
    check_same_frame(run.world_origin, scene, run.run_dir)
    if model_dir is not None:
        from ctgs.io.model_format import read_model

        model, files = read_model(model_dir, device=device)
        check_same_frame(files.manifest.get("source", {}).get("world_origin"), scene, model_dir)
    # Rendered into a temporary sibling that becomes OUT_DIR when every view is written (an earlier render
    # folder is replaced whole): a failure part-way leaves nothing behind.
    with torch.no_grad(), atomic.atomic_dir(out_dir) as tmp:
        inputs = model.render_inputs()
        for view in chosen:
            cam = view.camera.to(device, inputs.means.dtype)
            rgb = render(inputs, cam, backend=backend, sh_degree=model.sh_degree).rgb  # [H, W, 3]
            name = os.path.splitext(os.path.basename(view.name))[0] + ".png"
            write_image(os.path.join(tmp, name), rgb.clamp(0, 1).cpu().numpy())
    click.echo(f"{out_dir}: {len(chosen)} {views} views rendered with backend {backend}")
