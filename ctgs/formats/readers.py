"""Every Gaussian file `ctgs export` writes, read back by its ending: `read_gaussian_file(path)` -> untextured surfels
(what a Gaussian viewer gets from the file), for `ctgs eval --model FILE` and the benchmarks."""

from __future__ import annotations

import os

from ctgs.errors import UserError
from ctgs.formats.gltf_splats import read_glb_splats
from ctgs.formats.plain_ply import read_plain_ply
from ctgs.formats.playcanvas import read_compressed_ply, read_sog
from ctgs.formats.splat import read_splat
from ctgs.formats.spz import read_spz
from ctgs.model.surfels import SurfelModel


def _readers() -> dict:
    return {".compressed.ply": read_compressed_ply, ".splats.glb": read_glb_splats, ".ply": read_plain_ply,
            ".splat": read_splat, ".spz": read_spz, ".sog": read_sog}


ENDINGS = (".compressed.ply", ".splats.glb", ".ply", ".splat", ".spz", ".sog")  # longest match first


def gaussian_file_ending(path: str) -> str | None:
    """The ending that names `path`'s format (".sog", ".compressed.ply", ...), or None."""
    name = os.path.basename(path).lower()
    return next((e for e in ENDINGS if name.endswith(e)), None)


def read_gaussian_file(path: str) -> SurfelModel:
    """The surfels of an exported Gaussian file, by its ending; UserError naming the file and the endings otherwise."""
    ending = gaussian_file_ending(path)
    if ending is None:
        raise UserError(f"{path}: not a file `ctgs export` writes for Gaussian viewers (endings: {', '.join(ENDINGS)}); "
                        "pass one of those, or a model folder")
    if not os.path.isfile(path):
        raise UserError(f"{path}: no such file; check the path")
    return _readers()[ending](path)
