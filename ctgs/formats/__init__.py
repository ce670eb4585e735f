"""File formats and codecs, one module per format, and FORMATS, the registry `ctgs export` writes from.

Formats (docs/reference/model_format.md): `ctgs` (default, lossless: primitives.ply + textures.bin + manifest.json,
plus plain_3dgs.ply), `ply` (3DGS PLY for Gaussian viewers), `splat` (32 bytes per splat, web viewers),
`spz` (Niantic's compressed Gaussians), `compressed-ply` and `sog` (PlayCanvas's), `glb-splats` (KHR_gaussian_splatting),
`glb` (textured quads for Blender and three.js), `web` (the ctgs folder plus the bundle `ctgs view` serves, in its
web/ subfolder). Adding a format is a module here and one entry in FORMATS. Reading them back: ctgs.formats.readers
(Gaussian files) and ctgs.formats.model_format (model folders); `ctgs compress` is ctgs.formats.compress.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from typing import Callable

from ctgs.formats.gltf import write_glb
from ctgs.formats.gltf_splats import write_glb_splats
from ctgs.formats.model_format import write_model
from ctgs.formats.plain_ply import write_plain_ply
from ctgs.formats.playcanvas import write_compressed_ply, write_sog
from ctgs.formats.splat import write_splat
from ctgs.formats.spz import write_spz
from ctgs.formats.web_bundle import WEB_SUBDIR, scene_cameras, write_web_bundle


@dataclass(frozen=True)
class Export:
    """What a format's writer gets: the model, where to write, where it came from, the CLI options."""

    model: object  # ctgs.model.surfels.SurfelModel
    out: str
    source: dict
    plain_ply: bool
    texel_bits: int = 8  # web: bits per texel channel in the atlas
    baked: bool = False  # ply / splat / spz: textures baked into one splat per texel (ctgs.formats.bake)
    bake_note: str = ""  # what a splat budget changed in the bake


def _ctgs(e: Export) -> str:
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
    write_plain_ply(e.model, e.out, origin=e.source.get("world_origin"))
    return f"{e.model.num_primitives} Gaussians ({_textures(e)}), {os.path.getsize(e.out) / 1e6:.3f} MB"


def _origin_note(e: Export, fmt: str) -> str:
    """A recentred scene's origin, for the formats that have no field for it."""
    if not any(e.source.get("world_origin") or ()):
        return ""
    return (f"; positions in the recentred frame ({fmt} has no field for its origin, "
            f"{e.source['world_origin']} in the COLMAP frame: add it to place the model there)")


def _splat(e: Export) -> str:
    return (f"{e.model.num_primitives} splats ({_textures(e)}), {write_splat(e.model, e.out) / 1e6:.3f} MB"
            f"{_origin_note(e, '.splat')}")


def _spz(e: Export) -> str:
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
    info = write_compressed_ply(e.model, e.out, origin=e.source.get("world_origin"))
    return (f"{info['splats']} splats ({_textures(e)}), SH degree {info['sh_degree']}, tagged 2dgs, "
            f"{info['bytes'] / 1e6:.3f} MB")


def _sog(e: Export) -> str:
    info = write_sog(e.model, e.out)
    palette = f", SH palette of {info['palette']}" if info["palette"] else ""
    return (f"{info['splats']} splats ({_textures(e)}), SH degree {info['sh_degree']}{palette}, tagged 2dgs, "
            f"{info['bytes'] / 1e6:.3f} MB{_origin_note(e, 'SOG')}")


def _glb_splats(e: Export) -> str:
    info = write_glb_splats(e.model, e.out, origin=e.source.get("world_origin"))
    return (f"{info['splats']} splats ({_textures(e)}), SH degree {info['sh_degree']}, KHR_gaussian_splatting, "
            f"{info['bytes'] / 1e6:.3f} MB")


def _glb(e: Export) -> str:
    return f"{e.model.num_primitives} textured quads, " \
           f"{write_glb(e.model, e.out, origin=e.source.get('world_origin')) / 1e6:.3f} MB"


def _web(e: Export) -> str:
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
