"""`ctgs export --format ...` from the command line, and the Khronos glTF validator on its .glb.

The validator is the npm package gltf-validator, installed once into the per-user cache (npm_cache.py); the
test skips only where node or npm is missing.
"""

from __future__ import annotations

import json
import os
import subprocess

import pytest
import torch
from click.testing import CliRunner
from factory_io import random_model
from npm_cache import npm_package

from ctgs.cli import main

VALIDATOR = "gltf-validator@2.0.0-dev.3.10"  # pinned: its report format is what the test reads
VALIDATE_JS = """
const validator = require(process.argv[1]);
const bytes = new Uint8Array(require('fs').readFileSync(process.argv[2]));
validator.validateBytes(bytes).then(r => console.log(JSON.stringify(r)), e => { console.error(String(e)); process.exit(2); });
"""


def _run_dir(tmp_path, n: int = 50) -> str:
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"model": random_model(n=n, sh_degree=3, seed=8).state_dict(), "scene_dir": str(tmp_path / "scene"),
                "images": "images", "holdout": 8, "iteration": 7, "config": {}}, run / "model.pt")
    return str(run)


def _export(*args: str) -> str:
    res = CliRunner().invoke(main, ["export", *args])
    assert res.exit_code == 0, res.output
    return res.output


@pytest.mark.parametrize("fmt,name,what", [("ply", "model.ply", "50 Gaussians"), ("splat", "model.splat", "50 splats"),
                                           ("spz", "model.spz", "50 splats"), ("glb", "model.glb", "50 textured quads"),
                                           ("compressed-ply", "model.compressed.ply", "50 splats"),
                                           ("sog", "model.sog", "50 splats"),
                                           ("glb-splats", "model.splats.glb", "50 splats")])
def test_default_output_names(tmp_path, fmt, name, what):
    run = _run_dir(tmp_path)
    out = _export(run, "--format", fmt)
    assert os.path.isfile(os.path.join(run, name)) and what in out
    assert not [f for f in os.listdir(run) if f.endswith(".tmp")]


def test_export_from_a_model_folder(tmp_path):
    """A model folder (e.g. a compressed one) exports too; its file lands next to it."""
    run = _run_dir(tmp_path)
    _export(run, "-o", str(tmp_path / "model"))
    _export(str(tmp_path / "model"), "--format", "splat")
    assert (tmp_path / "model.splat").stat().st_size == 50 * 32


def test_file_formats_refuse_a_folder_as_output(tmp_path):
    run = _run_dir(tmp_path)
    res = CliRunner().invoke(main, ["export", run, "--format", "glb", "-o", str(tmp_path)])
    assert res.exit_code != 0 and "is a folder; --format glb writes one file" in res.output


@pytest.fixture(scope="session")
def gltf_validator() -> tuple[str, str]:
    """(node, path of the gltf-validator package); installs it into the cache on first use."""
    return npm_package(VALIDATOR, "gltf-validator", "the Khronos glTF validator")


def validate(validator: tuple[str, str], path: str) -> dict:
    node, package = validator
    p = subprocess.run([node, "-e", VALIDATE_JS, package, path], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def test_glb_passes_the_khronos_validator(tmp_path, gltf_validator):
    run = _run_dir(tmp_path, n=120)
    _export(run, "--format", "glb")
    report = validate(gltf_validator, os.path.join(run, "model.glb"))
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    assert report["info"]["drawCallCount"] >= 1 and report["info"]["totalVertexCount"] == 4 * 120


def test_the_validator_catches_a_broken_glb(tmp_path, gltf_validator):
    """The check can fail: a .glb whose accessor points past its buffer is reported as an error."""
    run = _run_dir(tmp_path, n=10)
    _export(run, "--format", "glb")
    path = os.path.join(run, "model.glb")
    raw = bytearray(open(path, "rb").read())
    json_len = int.from_bytes(raw[12:16], "little")
    doc = json.loads(raw[20: 20 + json_len])
    doc["accessors"][0]["count"] *= 1000
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    bad = raw[:12] + len(text).to_bytes(4, "little") + raw[16:20] + text + raw[20 + json_len:]
    bad[8:12] = len(bad).to_bytes(4, "little")
    open(path, "wb").write(bytes(bad))
    assert validate(gltf_validator, path)["issues"]["numErrors"] > 0


@pytest.mark.parametrize("fmt", ["splat", "spz", "SOG"])
def test_formats_without_an_origin_field_say_where_it_lies(tmp_path, fmt):
    """A run on a recentred (far) scene: .splat and .spz cannot hold its origin, so the export line says it."""
    run = _run_dir(tmp_path)
    ckpt = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    ckpt["world_origin"] = [120000.0, 0.0, -5.0]
    torch.save(ckpt, os.path.join(run, "model.pt"))
    out = _export(run, "--format", {"SOG": "sog"}.get(fmt, fmt))
    assert f"{fmt} has no field for its origin, [120000.0, 0.0, -5.0] in the COLMAP frame" in out
