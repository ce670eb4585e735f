"""K-means texel compression: two codebook sizes (size ratio, rendered change), transparency, bad input."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from factory_io import random_model
from ctgs.cli import main
from ctgs.io.model_format import read_model, write_model
from ctgs.metrics.psnr import psnr
from ctgs.render.camera import Camera
from ctgs.render.reference import render_reference


def _camera() -> Camera:
    view = torch.eye(4)
    view[2, 3] = 5.0  # world origin 5 units in front of the camera
    return Camera(fx=40.0, fy=40.0, cx=24.0, cy=24.0, width=48, height=48, viewmat=view)


def _render(model) -> torch.Tensor:
    with torch.no_grad():
        return render_reference(model.render_inputs(), _camera(), sh_degree=model.sh_degree).rgb


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    model = random_model(n=120, seed=11)
    model.opacity_logits.fill_(3.0)
    model.log_scales.add_(1.0)  # large, opaque surfels so the textures dominate the image
    write_model(model, str(root / "model"))
    return root, model


def _compress(root, k: int, half: bool = True) -> str:
    out = str(root / f"k{k}")
    res = CliRunner().invoke(main, ["compress", str(root / "model"), "-o", out, "-k", str(k)]
                             + ([] if half else ["--no-half"]))
    assert res.exit_code == 0, res.output
    return out


def test_two_codebook_sizes(exported):
    root, model = exported
    reference = _render(model)
    stats = {}
    for k in (4, 256):
        back, files = read_model(_compress(root, k))
        assert files.manifest["texture_encoding"] == "codebook" and files.manifest["codebook_size"] == k
        assert back.num_texels == model.num_texels and back.num_params() == model.num_params()
        # Everything but textures and the fp16 SH is untouched by compression.
        for name in ("means", "log_scales", "quats", "opacity_logits", "k_min", "t2p_exp", "tex_res", "tex_offset"):
            assert torch.equal(getattr(back, name), getattr(model, name)), name
        torch.testing.assert_close(back.sh, model.sh, atol=2e-3, rtol=1e-3)  # float16 storage
        # At most k distinct texel colours remain.
        assert len(torch.unique(back.textures_raw, dim=0)) <= k
        stats[k] = (files.bytes_on_disk, psnr(_render(back), reference),
                    float((back.textures - model.textures).pow(2).mean().sqrt()))
    before = read_model(str(root / "model"))[1].bytes_on_disk
    assert stats[4][0] < stats[256][0] < before  # uint8 indices + fp16 SH beat float32 texels
    assert before / stats[256][0] > 1.5
    assert stats[256][2] < stats[4][2]  # more colours: smaller texel error ...
    assert stats[256][1] > stats[4][1]  # ... and a render closer to the uncompressed one
    assert stats[4][1] < 60.0  # and compression did change the image (the test can fail)


def test_codebook_larger_than_texels_is_user_error(exported):
    root, model = exported
    out = root / "too_big"
    res = CliRunner().invoke(main, ["compress", str(root / "model"), "-o", str(out), "-k", str(model.num_texels + 1)])
    assert res.exit_code == 2 and "larger than" in res.output
    assert not out.exists()
    assert not [p for p in os.listdir(root) if p.startswith(".tmp")]


def test_compressed_is_not_recompressed(exported):
    root, _ = exported
    src = _compress(root, 8, half=False)
    res = CliRunner().invoke(main, ["compress", src, "-o", str(root / "again")])
    assert res.exit_code == 2 and "already compressed" in res.output


def test_index_dtype_is_compact(exported):
    root, _ = exported
    from ctgs.io.texture_blob import HEADER

    data = open(os.path.join(_compress(root, 4), "textures.bin"), "rb").read()
    index_code = HEADER.unpack_from(data)[8]
    assert index_code == 1  # uint8
    assert np.frombuffer(data[:8], "S8")[0] == b"CTGSTEX"


def test_untextured_model_compresses_without_codebook(tmp_path):
    model = random_model(n=10, texture_mode="none")
    model.tex_res.zero_()
    model.tex_offset.zero_()
    model.textures_raw = model.textures_raw[:0]
    write_model(model, str(tmp_path / "m"))
    res = CliRunner().invoke(main, ["compress", str(tmp_path / "m"), "-o", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    back, files = read_model(str(tmp_path / "c"))
    assert back.num_texels == 0 and files.manifest["compression"]["codebook_size"] is None
