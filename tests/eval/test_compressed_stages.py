"""A compressed model of every texel mode loads and renders through eval, render and export."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from fixture_run import make_run
from ctgs.cli import main
from ctgs.io.images import read_image
from ctgs.io.owner import MARKER
from ctgs.formats.model_format import read_model
from ctgs.metrics.psnr import psnr

MODES = [("scalar", "256"), ("vector", "64"), ("f16", None)]
# PSNR of a compressed model's 8-bit test renders against the raw model's (balanced attribute codecs).
# Observed 39.5 dB (vector K=64) to 52.8 dB; a decoding bug (textures given to the wrong primitives) gave 29.5.
MIN_PSNR_TO_RAW_DB = 35.0


@pytest.fixture(scope="module")
def compressed(tmp_path_factory):
    root = tmp_path_factory.mktemp("stages")
    run = make_run(str(root))
    runner = CliRunner()
    res = runner.invoke(main, ["export", run, "-o", str(root / "model"), "--no-plain-ply"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["eval", run, "--model", str(root / "model"), "--backend", "reference", "--no-lpips",
                               "-o", str(root / "e_raw")])
    assert res.exit_code == 0, res.output
    out = {}
    for mode, k in MODES:
        out[mode] = str(root / f"c_{mode}")
        args = ["compress", str(root / "model"), "-o", out[mode], "--texels", mode] + (["-k", k] if k else [])
        res = runner.invoke(main, args)
        assert res.exit_code == 0, res.output
    return run, root, out


def _ok(args):
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    return res


@pytest.mark.parametrize("mode", [m for m, _ in MODES])
def test_compressed_model_through_eval_render_export(compressed, mode):
    run, root, models = compressed
    model_dir = models[mode]
    model, files = read_model(model_dir)
    assert files.manifest["texture_encoding"] == mode

    _ok(["eval", run, "--model", model_dir, "--backend", "reference", "--no-lpips", "-o", str(root / f"e_{mode}")])
    m = json.load(open(root / f"e_{mode}" / "metrics.json"))
    assert m["compressed"] and m["texture_encoding"] == mode and m["compression_target"] == "balanced"
    assert m["bytes_on_disk"] == files.bytes_on_disk and m["points"] == model.num_primitives
    raw = json.load(open(root / "e_raw" / "metrics.json"))
    assert m["bytes_on_disk"] < raw["bytes_on_disk"]
    for name in os.listdir(root / "e_raw" / "renders"):  # the compressed model draws what the raw one draws
        a = read_image(str(root / f"e_{mode}" / "renders" / name))
        b = read_image(str(root / "e_raw" / "renders" / name))
        assert psnr(torch.from_numpy(a), torch.from_numpy(b)) > MIN_PSNR_TO_RAW_DB

    _ok(["render", run, "--model", model_dir, "--backend", "reference", "-o", str(root / f"r_{mode}")])
    names = sorted(set(os.listdir(root / f"r_{mode}")) - {MARKER})
    assert names == sorted(os.listdir(root / f"e_{mode}" / "renders"))
    for name in names:  # render and eval draw the same compressed model
        a = read_image(str(root / f"r_{mode}" / name))
        b = read_image(str(root / f"e_{mode}" / "renders" / name))
        assert np.abs(a - b).max() <= 1 / 255 + 1e-6

    _ok(["export", model_dir, "-o", str(root / f"x_{mode}")])
    back, xfiles = read_model(str(root / f"x_{mode}"))
    assert xfiles.manifest["version"] == 1 and os.path.isfile(root / f"x_{mode}" / "plain_3dgs.ply")
    for name, t in model.state_dict().items():  # the export holds the decoded model exactly
        assert (t == back.state_dict()[name]) if not hasattr(t, "shape") else bool((t == back.state_dict()[name]).all())


def test_export_of_a_compressed_folder_leaves_it_untouched(compressed):
    run, root, models = compressed
    _ok(["export", models["scalar"], "--no-plain-ply"])  # default output: a sibling, MODEL-export
    assert read_model(models["scalar"] + "-export")[1].manifest["version"] == 1
    assert read_model(models["scalar"])[1].manifest["version"] == 2
