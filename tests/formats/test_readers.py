"""read_gaussian_file: every Gaussian file `ctgs export` writes comes back through one call, chosen by its ending
(the longest first: `.compressed.ply` is not a 3DGS PLY, `.splats.glb` not a textured-quad glb)."""

from __future__ import annotations

import pytest
import torch
from factory_io import random_model

from ctgs.errors import UserError
from ctgs.formats.gltf_splats import write_glb_splats
from ctgs.formats.plain_ply import write_plain_ply
from ctgs.formats.playcanvas import write_compressed_ply, write_sog
from ctgs.formats.readers import gaussian_file_ending, read_gaussian_file
from ctgs.formats.splat import write_splat
from ctgs.formats.spz import write_spz

WRITERS = {"m.ply": write_plain_ply, "m.splat": write_splat, "m.spz": write_spz, "m.compressed.ply": write_compressed_ply,
           "m.sog": write_sog, "m.splats.glb": write_glb_splats}


@pytest.mark.parametrize("name", list(WRITERS))
def test_every_export_reads_back_by_its_ending(tmp_path, name):
    m = random_model(n=40, sh_degree=1, seed=3)
    WRITERS[name](m, str(tmp_path / name))
    back = read_gaussian_file(str(tmp_path / name))
    assert back.num_primitives == 40 and back.texture_mode == "none"
    # every format keeps the centres (to its quantisation; the PlayCanvas formats reorder the splats)
    d = torch.cdist(back.means.double(), m.means.double()).min(1).values
    assert float(d.max()) < 0.02


def test_endings_and_refusals(tmp_path):
    assert gaussian_file_ending("a/B.Compressed.PLY") == ".compressed.ply"
    assert gaussian_file_ending("x.splats.glb") == ".splats.glb" and gaussian_file_ending("x.glb") is None
    with pytest.raises(UserError, match=r"x.glb: not a file `ctgs export` writes for Gaussian viewers"):
        read_gaussian_file(str(tmp_path / "x.glb"))
    with pytest.raises(UserError, match=r"missing.spz: no such file"):
        read_gaussian_file(str(tmp_path / "missing.spz"))
