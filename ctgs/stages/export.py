"""`ctgs export RUN_DIR [-o MODEL_DIR]`: a trained run -> model folder (docs/model_format.md)."""

from __future__ import annotations

import os

import click


@click.command(name="export")
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out_dir", default=None, type=click.Path(file_okay=False),
              help="Model folder to write (default RUN_DIR/model); replaced atomically.")
@click.option("--plain-ply/--no-plain-ply", default=True, show_default=True,
              help="Also write plain_3dgs.ply, an untextured approximation for existing 3DGS viewers.")
def command(run_dir: str, out_dir: str | None, plain_ply: bool) -> None:
    """Write RUN_DIR's model as primitives.ply + textures.bin + manifest.json (+ plain_3dgs.ply)."""
    from ctgs.io.model_format import write_model
    from ctgs.io.run_model import load_run

    run = load_run(run_dir)
    out_dir = out_dir or os.path.join(run_dir, "model")
    source = {"run_dir": run.run_dir, "scene_dir": run.scene_dir, "images": run.images,
              "holdout": run.holdout, "iteration": run.iteration}
    manifest = write_model(run.model, out_dir, plain_ply=plain_ply, extra={"source": source})
    size = sum(v for k, v in manifest["file_bytes"].items() if k != manifest["plain_ply"])
    click.echo(f"{out_dir}: {manifest['num_primitives']} primitives, {manifest['num_texels']} texels, "
               f"{size / 1e6:.3f} MB (+ plain PLY: {plain_ply})")
