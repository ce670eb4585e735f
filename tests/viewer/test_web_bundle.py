"""Web bundle: atlas packing, round trip, what the texel precision costs, bad inputs (no browser)."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgs.errors import UserError
from ctgs.formats.web_bundle import (BUNDLE_JSON, SNORM8_MAX, pack_atlas, read_bundle_json, read_web_bundle,
                                write_web_bundle)
from ctgs.render import render
from viewer_models import camera, psnr, textured_model

# What storing the texels costs in the image, on textured_model(seed=0) whose textures swing up to
# +-0.9 (observed: 8 bit 65.3 dB, 16 bit 91.3 dB); the browser test's goal is 35 dB, so 8 bits leave
# ample room. Floors ~10 dB under the observed values: a layout bug (a texel in the wrong place) costs
# far more than that.
MIN_PSNR_8BIT = 55.0
MIN_PSNR_16BIT = 80.0


def _render(inputs, cam, sh_degree=3) -> torch.Tensor:
    with torch.no_grad():
        return render(inputs, cam, backend="cpu", sh_degree=sh_degree).rgb.clamp(0, 1)


@pytest.mark.parametrize("page_size", [16, 64, 2048])
def test_atlas_rectangles_fit_their_pages_and_never_overlap(page_size):
    g = np.random.default_rng(1)
    res = g.integers(1, 17, size=(300, 2))
    res[::11] = 0  # no texture: no space
    layout = pack_atlas(res, page_size)
    occupied = [np.zeros((page_size, page_size), dtype=np.int32) for _ in layout.page_rows]
    for (w, h), (x, y, p) in zip(res, layout.pos):
        if w == 0:
            continue
        assert x + w <= page_size and y + h <= layout.page_rows[p] <= page_size
        occupied[p][y:y + h, x:x + w] += 1
    assert max(o.max() for o in occupied) == 1
    used = sum(int((o > 0).sum()) for o in occupied)
    assert used == int((res[:, 0] * res[:, 1]).sum())


def test_texture_larger_than_a_page_is_a_user_error():
    with pytest.raises(UserError, match="does not fit an atlas page"):
        pack_atlas(np.array([[3, 3], [40, 2]]), 32)


@pytest.mark.parametrize("bits", [8, 16])
def test_round_trip_and_quantisation_cost(tmp_path, bits):
    model = textured_model(seed=0)
    cam = camera()
    cams = [{"name": "a.png", "split": "test", "width": cam.width, "height": cam.height, "fx": cam.fx,
             "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "near": cam.near,
             "viewmat": cam.viewmat.double().reshape(-1).tolist()}]
    bundle = write_web_bundle(model, str(tmp_path / "web"), cams, texel_bits=bits)
    decoded, meta = read_web_bundle(str(tmp_path / "web"))
    assert meta["cameras"] == cams and bundle["num_surfels"] == model.num_primitives
    ref = model.render_inputs()
    # geometry is stored exactly (float32), SH as float16
    for name in ("means", "scales", "opacities"):
        assert torch.equal(getattr(decoded, name), getattr(ref, name).float()), name
    assert torch.allclose(decoded.quats, ref.quats / ref.quats.norm(dim=-1, keepdim=True), atol=1e-7)
    assert torch.allclose(decoded.texel_size, ref.texel_size.float(), rtol=1e-6)
    assert torch.allclose(decoded.sh, ref.sh, rtol=2**-10, atol=1e-7)
    assert torch.equal(decoded.tex_res, ref.tex_res)
    # texels: jagged order restored, within the encoding's step
    step = 1.0 / (2 * SNORM8_MAX) if bits == 8 else 2.0**-11
    err = (decoded.textures - ref.textures).abs().max().item()
    assert err <= step + 1e-7, err
    # what the precision costs in the image
    full, stored = _render(ref, cam), _render(decoded, cam)
    quality = psnr(full, stored)
    assert quality >= (MIN_PSNR_8BIT if bits == 8 else MIN_PSNR_16BIT), f"{bits}-bit texels: {quality:.1f} dB"
    # the textures matter in this model (else the check above would be vacuous)
    no_tex = _render(replace(decoded, tex_res=torch.zeros_like(decoded.tex_res)), cam)
    assert psnr(full, no_tex) < 30.0


def test_texture_mode_none_stores_no_texels(tmp_path):
    model = textured_model(seed=2, texture_mode="none")
    bundle = write_web_bundle(model, str(tmp_path / "web"), [])
    decoded, _ = read_web_bundle(str(tmp_path / "web"))
    assert bundle["num_texels"] == 0 and bundle["atlas"]["pages"] == []
    assert int(decoded.tex_res.abs().sum()) == 0


def test_only_the_active_sh_bands_are_stored(tmp_path):
    model = textured_model(seed=3, sh_degree=3)
    model.sh_degree = 1
    write_web_bundle(model, str(tmp_path / "web"), [])
    decoded, bundle = read_web_bundle(str(tmp_path / "web"))
    assert bundle["sh_degree"] == 1 and decoded.sh.shape[1] == 4


def test_rewrite_replaces_a_bundle_but_never_another_folder(tmp_path):
    model = textured_model(n=10, seed=4)
    write_web_bundle(model, str(tmp_path / "web"), [])
    write_web_bundle(model, str(tmp_path / "web"), [], texel_bits=16)
    assert read_bundle_json(str(tmp_path / "web"))["atlas"]["texel_format"] == "float16"
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    with pytest.raises(UserError, match="not an earlier ctgs web bundle: it holds files ctgs did not write"):
        write_web_bundle(model, str(tmp_path / "other"), [])
    assert (tmp_path / "other" / "keep.txt").exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]


@pytest.mark.parametrize("content, message", [
    (None, "no bundle.json"),
    ("{not json", "unreadable"),
    (json.dumps({"format": "something"}), "not a ctgs web bundle"),
    (json.dumps({"format": "ctgs-web", "version": 99}), "version 99"),
])
def test_bad_bundle_json_is_one_clear_error(tmp_path, content, message):
    if content is not None:
        (tmp_path / BUNDLE_JSON).write_text(content)
    with pytest.raises(UserError, match=message):
        read_bundle_json(str(tmp_path))


@pytest.mark.parametrize("bits, page", [(12, 2048), (8, 1000)])
def test_bad_options_are_user_errors(tmp_path, bits, page):
    with pytest.raises(UserError):
        write_web_bundle(textured_model(n=5), str(tmp_path / "web"), [], texel_bits=bits, page_size=page)
