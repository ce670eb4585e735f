"""`ctgs export SOURCE [-o OUT] [--format F]`: a trained run (or a model folder) -> a model file or folder.

Formats: ctgs.formats.FORMATS (docs/reference/model_format.md).
"""

from __future__ import annotations

import os

import click

from ctgs.errors import UserError
from ctgs.formats import BAKED_FORMATS, FORMATS, Export, spz
from ctgs.formats.bake import bake_bound, bake_texels, plan_levels
from ctgs.formats.model_format import MANIFEST, read_model
from ctgs.io import lock
from ctgs.runs import load_run


def load_source(path: str):
    """(model, source info) from a run folder (model.pt) or a model folder (manifest.json)."""
    if os.path.isfile(os.path.join(path, MANIFEST)):
        model, files = read_model(path)
        return model, {"model_dir": os.path.abspath(path), **files.manifest.get("source", {})}
    run = load_run(path)
    info = {"run_dir": run.run_dir, "scene_dir": run.scene_dir, "images": run.images, "holdout": run.holdout,
            "iteration": run.iteration}
    if any(run.world_origin):  # a recentred scene: where the model's origin lies in the COLMAP frame
        info["world_origin"] = list(run.world_origin)
    return run.model, info


def default_out(source: str, fmt: str) -> str:
    if os.path.isfile(os.path.join(source, MANIFEST)):  # a model folder: a file next to it
        base = os.path.normpath(source)
        return base + (FORMATS[fmt].suffix or "-export")
    return os.path.join(source, "model" + FORMATS[fmt].suffix)


@click.command(name="export")
@click.argument("source", metavar="RUN_DIR", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out", default=None, type=click.Path(),
              help="Output (default RUN_DIR/model for ctgs, RUN_DIR/model.<format> otherwise); replaced atomically.")
@click.option("--format", "fmt", type=click.Choice(list(FORMATS)), default="ctgs", show_default=True,
              help="; ".join(f"{name}: {f.help}" for name, f in FORMATS.items()) + ".")
@click.option("--plain-ply/--no-plain-ply", default=True, show_default=True,
              help="With --format ctgs: also write plain_3dgs.ply into the folder.")
@click.option("--texel-bits", type=click.Choice(["8", "16"]), default="8", show_default=True,
              help="With --format web: bits per texel channel in the atlas (8: signed bytes, 16: half floats).")
@click.option("--bake-textures", is_flag=True,
              help="With --format ply, splat, spz, compressed-ply, sog or glb-splats: one small splat per texel instead "
                   "of one per surfel, so Gaussian "
                   "viewers show the texture detail (many times the splats and bytes; docs/reference/model_format.md).")
@click.option("--bake-max-splats", type=click.IntRange(min=1), default=None,
              help="With --bake-textures: at most this many splats; past it, textures are baked on coarser texels "
                   "(2x2, 4x4... blocks averaged) or folded, the flattest first. spz: at most its readers' 10M "
                   "points in any case.")
def command(source: str, out: str | None, fmt: str, plain_ply: bool, texel_bits: str, bake_textures: bool,
            bake_max_splats: int | None) -> None:
    """Write RUN_DIR's model (or a model folder's, e.g. a compressed one) in the chosen format."""
    if bake_textures and fmt not in BAKED_FORMATS:
        raise UserError(f"--bake-textures applies to --format {', '.join(BAKED_FORMATS)}; --format {fmt} keeps the "
                        "textures themselves: drop the option")
    if bake_max_splats is not None and not bake_textures:
        raise UserError("--bake-max-splats applies with --bake-textures: add it, or drop --bake-max-splats")
    model, info = load_source(source)
    out = out or default_out(source, fmt)
    if FORMATS[fmt].suffix and os.path.isdir(out):  # formats with a suffix write one file
        raise UserError(f"{out}: is a folder; --format {fmt} writes one file, pass a file name with -o")
    note = ""
    if bake_textures:
        budget = bake_max_splats
        if fmt == "spz" and (budget is None or budget > spz.MAX_POINTS):
            budget = spz.MAX_POINTS  # what .spz readers accept
        levels = None
        if budget is not None and bake_bound(model) > budget:  # else the full bake fits: nothing to plan
            plan = plan_levels(model, budget)
            levels = plan["level"]
            if plan["splats"] < plan["full_splats"]:
                note = (f", fitted to {budget} splats (the full bake: {plan['full_splats']}; surfels on their own "
                        f"texels {int((levels == 0).sum())}, on coarser texels {int((levels > 0).sum())}, folded "
                        f"{int((levels < 0).sum())})")
        model = bake_texels(model, levels=levels, max_splats=spz.MAX_POINTS if fmt == "spz" else None)
    parent = os.path.dirname(os.path.abspath(out))
    os.makedirs(parent, exist_ok=True)
    with lock.inside_run(out):  # never while a training writes the run folder OUT is in
        summary = FORMATS[fmt].write(Export(model=model, out=out, source=info, plain_ply=plain_ply,
                                            texel_bits=int(texel_bits), baked=bake_textures, bake_note=note))
    click.echo(f"{out}: {summary}")
