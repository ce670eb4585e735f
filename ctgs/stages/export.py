"""`ctgs export SOURCE [-o OUT] [--format F]`: a trained run (or a model folder) -> a model file or folder.

Formats (docs/reference/model_format.md): `ctgs` (default, lossless: primitives.ply + textures.bin + manifest.json,
plus plain_3dgs.ply), `ply` (3DGS PLY for Gaussian viewers), `splat` (32 bytes per splat, web viewers),
`spz` (Niantic's compressed Gaussians), `compressed-ply` and `sog` (PlayCanvas's), `glb-splats` (KHR_gaussian_splatting), `glb` (textured quads for Blender and three.js), `web` (the ctgs
folder plus the bundle `ctgs view` serves, in its web/ subfolder). Adding a format is one entry in FORMATS.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from typing import Callable

import click


@dataclass(frozen=True)
class Export:
    """What a format's writer gets: the model, where to write, where it came from, the CLI options."""

    model: object  # ctgs.model.surfels.SurfelModel
    out: str
    source: dict
    plain_ply: bool
    texel_bits: int = 8  # web: bits per texel channel in the atlas
    baked: bool = False  # ply / splat / spz: textures baked into one splat per texel (ctgs.io.bake)
    bake_note: str = ""  # what a splat budget changed in the bake


def _ctgs(e: Export) -> str:
    from ctgs.io.model_format import write_model

    manifest = write_model(e.model, e.out, plain_ply=e.plain_ply, extra={"source": e.source})
    size = sum(v for k, v in manifest["file_bytes"].items() if k != manifest["plain_ply"])
    return (f"{manifest['num_primitives']} primitives, {manifest['num_texels']} texels, {size / 1e6:.3f} MB "
            f"(+ plain PLY: {e.plain_ply})")


def _textures(e: Export) -> str:
    if not e.baked:
        return "textures folded into the DC colour"
    return "textures baked: a splat per texel or texel block" + e.bake_note if e.bake_note else \
        "textures baked: a splat per texel"


def _ply(e: Export) -> str:
    from ctgs.io.plain_ply import write_plain_ply

    write_plain_ply(e.model, e.out, origin=e.source.get("world_origin"))
    return f"{e.model.num_primitives} Gaussians ({_textures(e)}), {os.path.getsize(e.out) / 1e6:.3f} MB"


def _origin_note(e: Export, fmt: str) -> str:
    """A recentred scene's origin, for the formats that have no field for it."""
    if not any(e.source.get("world_origin") or ()):
        return ""
    return (f"; positions in the recentred frame ({fmt} has no field for its origin, "
            f"{e.source['world_origin']} in the COLMAP frame: add it to place the model there)")


def _splat(e: Export) -> str:
    from ctgs.io.splat import write_splat

    return (f"{e.model.num_primitives} splats ({_textures(e)}), {write_splat(e.model, e.out) / 1e6:.3f} MB"
            f"{_origin_note(e, '.splat')}")


def _spz(e: Export) -> str:
    from ctgs.io.spz import write_spz

    info = write_spz(e.model, e.out)
    notes = _origin_note(e, ".spz")
    if info["tangent_scales_clipped"]:
        notes += (f"; {info['tangent_scales_clipped']} tangent scales outside .spz's e^-10..e^5.94 were clipped "
                  "(the scene's units: rescale it, or export --format ply)")
    if info["colours_clipped"]:
        notes += f"; {info['colours_clipped']} colour values past .spz's range were clipped"
    if info["sh_clipped"]:
        notes += f"; {info['sh_clipped']} SH coefficients past .spz's [-1, 1] were clipped"
    return (f"{e.model.num_primitives} splats ({_textures(e)}), SH degree {info['sh_degree']}, "
            f"{info['fractional_bits']} fractional position bits, {info['bytes'] / 1e6:.3f} MB{notes}")


def _compressed_ply(e: Export) -> str:
    from ctgs.io.playcanvas import write_compressed_ply

    info = write_compressed_ply(e.model, e.out, origin=e.source.get("world_origin"))
    return (f"{info['splats']} splats ({_textures(e)}), SH degree {info['sh_degree']}, tagged 2dgs, "
            f"{info['bytes'] / 1e6:.3f} MB")


def _sog(e: Export) -> str:
    from ctgs.io.playcanvas import write_sog

    info = write_sog(e.model, e.out)
    palette = f", SH palette of {info['palette']}" if info["palette"] else ""
    return (f"{info['splats']} splats ({_textures(e)}), SH degree {info['sh_degree']}{palette}, tagged 2dgs, "
            f"{info['bytes'] / 1e6:.3f} MB{_origin_note(e, 'SOG')}")


def _glb_splats(e: Export) -> str:
    from ctgs.io.gltf_splats import write_glb_splats

    info = write_glb_splats(e.model, e.out, origin=e.source.get("world_origin"))
    return (f"{info['splats']} splats ({_textures(e)}), SH degree {info['sh_degree']}, KHR_gaussian_splatting, "
            f"{info['bytes'] / 1e6:.3f} MB")


def _glb(e: Export) -> str:
    from ctgs.io.gltf import write_glb

    return f"{e.model.num_primitives} textured quads, " \
           f"{write_glb(e.model, e.out, origin=e.source.get('world_origin')) / 1e6:.3f} MB"


def _web(e: Export) -> str:
    from ctgs.io.web_bundle import WEB_SUBDIR, scene_cameras, write_web_bundle

    scene = e.source.get("scene_dir")
    cameras = scene_cameras(scene, e.source.get("images", "images"), int(e.source.get("holdout", 8))) \
        if scene and os.path.isdir(scene) else []  # first: a scene that cannot be read leaves nothing written
    summary = _ctgs(e)
    try:
        web = write_web_bundle(e.model, os.path.join(e.out, WEB_SUBDIR), cameras, texel_bits=e.texel_bits)
    except BaseException:
        shutil.rmtree(e.out, ignore_errors=True)  # the folder without its bundle is not what was asked for
        raise
    return (f"{summary}; {WEB_SUBDIR}/: web bundle, {web['bytes_per_surfel']:.0f} B/surfel, "
            f"{web['bytes_per_texel']:.2f} B/texel, {len(cameras)} cameras (`ctgs view {e.out}`)")


@dataclass(frozen=True)
class Format:
    write: Callable[[Export], str]  # writes e.out, returns a one-line summary
    suffix: str  # default output: RUN_DIR/model<suffix> ("" = a folder)
    help: str


FORMATS: dict[str, Format] = {
    "ctgs": Format(_ctgs, "", "lossless model folder (primitives.ply + textures.bin + manifest.json)"),
    "ply": Format(_ply, ".ply", "3DGS PLY for Gaussian viewers (textures folded into one colour per surfel)"),
    "splat": Format(_splat, ".splat", ".splat, 32 bytes per splat, for web viewers (DC colour, 8-bit opacity "
                                      "and rotation)"),
    "spz": Format(_spz, ".spz", "Niantic .spz v3, gzip of quantised Gaussians (about a tenth of the PLY; what the PLY "
                                "keeps, quantised)"),
    "compressed-ply": Format(_compressed_ply, ".compressed.ply",
                             "PlayCanvas compressed PLY (SuperSplat, PlayCanvas): 16 bytes per splat + 1 per SH "
                             "coefficient, quantised per 256 splats"),
    "sog": Format(_sog, ".sog", "PlayCanvas SOG bundle (SuperSplat, PlayCanvas): lossless WebP images of quantised "
                                "attributes and codebook indices"),
    "glb": Format(_glb, ".glb", "glTF binary, one textured quad per surfel (Blender, three.js)"),
    "glb-splats": Format(_glb_splats, ".splats.glb", "glTF binary of Gaussians, the ratified KHR_gaussian_splatting "
                                                     "extension (PlayCanvas, Babylon.js, CesiumJS), float32"),
    "web": Format(_web, "", "the ctgs folder plus web/, the bundle `ctgs view` serves (WebGL2, textures kept)"),
}

BAKED_FORMATS = ("ply", "splat", "spz", "compressed-ply", "sog", "glb-splats")  # the Gaussian formats, which otherwise fold each texture into one colour


def load_source(path: str):
    """(model, source info) from a run folder (model.pt) or a model folder (manifest.json)."""
    from ctgs.io.model_format import MANIFEST, read_model

    if os.path.isfile(os.path.join(path, MANIFEST)):
        model, files = read_model(path)
        return model, {"model_dir": os.path.abspath(path), **files.manifest.get("source", {})}
    from ctgs.io.run_model import load_run

    run = load_run(path)
    info = {"run_dir": run.run_dir, "scene_dir": run.scene_dir, "images": run.images, "holdout": run.holdout,
            "iteration": run.iteration}
    if any(run.world_origin):  # a recentred scene: where the model's origin lies in the COLMAP frame
        info["world_origin"] = list(run.world_origin)
    return run.model, info


def default_out(source: str, fmt: str) -> str:
    from ctgs.io.model_format import MANIFEST

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
    from ctgs.errors import UserError

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
        from ctgs.io.bake import bake_bound, bake_texels, plan_levels
        from ctgs.io.spz import MAX_POINTS

        budget = bake_max_splats
        if fmt == "spz" and (budget is None or budget > MAX_POINTS):
            budget = MAX_POINTS  # what .spz readers accept
        levels = None
        if budget is not None and bake_bound(model) > budget:  # else the full bake fits: nothing to plan
            plan = plan_levels(model, budget)
            levels = plan["level"]
            if plan["splats"] < plan["full_splats"]:
                note = (f", fitted to {budget} splats (the full bake: {plan['full_splats']}; surfels on their own "
                        f"texels {int((levels == 0).sum())}, on coarser texels {int((levels > 0).sum())}, folded "
                        f"{int((levels < 0).sum())})")
        model = bake_texels(model, levels=levels, max_splats=MAX_POINTS if fmt == "spz" else None)
    parent = os.path.dirname(os.path.abspath(out))
    os.makedirs(parent, exist_ok=True)
    summary = FORMATS[fmt].write(Export(model=model, out=out, source=info, plain_ply=plain_ply,
                                        texel_bits=int(texel_bits), baked=bake_textures, bake_note=note))
    click.echo(f"{out}: {summary}")
