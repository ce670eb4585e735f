"""`ctgs eval` on a tiny fixture run: metrics.json schema, CSV, renders, strips, --model, --table, bad input."""

from __future__ import annotations

import csv
import json
import os

import pytest
from click.testing import CliRunner

from fixture_run import make_run
from ctgs.cli import main
from ctgs.metrics.psnr import psnr

# Every metrics.json must carry these keys (docs/metrics.md), with these types (None allowed where listed).
SCHEMA = {
    "schema": str, "schema_version": int, "scene": str, "dataset": str, "run_dir": str, "model_source": str,
    "scene_dir": str, "images": str, "holdout": int, "num_test_views": int, "psnr": float, "ssim": float,
    "lpips": (float, type(None)), "lpips_status": str, "points": int, "texels": int, "params": int,
    "texels_per_primitive": float, "model_memory_bytes": int, "bytes_on_disk": int, "texture_encoding": str,
    "codebook_size": (int, type(None)), "compressed": bool, "fps": float, "render_ms_mean": float, "backend": str, "device": str,
    "resolution": list, "peak_memory_bytes": int, "peak_memory_kind": str, "train_seconds": (float, type(None)),
    "iterations": int, "machine": dict, "files": dict, "per_image": list,
}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return make_run(str(tmp_path_factory.mktemp("evalrun")))


def _eval(*args) -> dict:
    res = CliRunner().invoke(main, ["eval", *args])
    assert res.exit_code == 0, res.output
    return res


def test_eval_writes_schema_and_artifacts(run_dir):
    _eval(run_dir, "--backend", "reference")
    out = os.path.join(run_dir, "eval")
    m = json.load(open(os.path.join(out, "metrics.json")))
    for key, typ in SCHEMA.items():
        assert key in m, key
        assert isinstance(m[key], typ), (key, m[key])
    assert m["schema"] == "ctgs-metrics" and m["num_test_views"] == 2  # 9 views, every 8th: 000 and 008
    assert m["points"] == 150 and m["texels"] == 150 * 16 and m["params"] == 59 * 150 + 3 * 2400
    assert m["model_memory_bytes"] == 4 * m["params"] and m["train_seconds"] == 1.5
    assert m["bytes_on_disk"] == os.path.getsize(os.path.join(run_dir, "model.pt"))
    assert m["fps"] > 0 and m["peak_memory_bytes"] > 0
    if m["lpips"] is None:
        assert m["lpips_status"].startswith("unavailable:")
    else:
        assert 0 < m["lpips"] < 1.5 and "[0, 1]" in m["lpips_status"]
    rows = list(csv.DictReader(open(os.path.join(out, "per_image.csv"))))
    assert [r["name"] for r in rows] == ["000.png", "008.png"] or len(rows) == 2
    # The CSV and the means agree.
    assert abs(sum(float(r["psnr"]) for r in rows) / 2 - m["psnr"]) < 1e-3
    assert sorted(os.listdir(os.path.join(out, "renders"))) == sorted(os.path.splitext(r["name"])[0] + ".png" for r in rows)
    strips = m["files"]["strips"]
    assert any(s.startswith("strips/worst_") for s in strips) and any(s.startswith("strips/best_") for s in strips)
    from ctgs.io.images import read_image

    s = read_image(os.path.join(out, strips[0]))
    assert s.shape[:2] == (32, 3 * 40)  # gt | render | error side by side


def test_eval_exported_and_compressed_models(run_dir, tmp_path):
    runner = CliRunner()
    assert runner.invoke(main, ["export", run_dir, "-o", str(tmp_path / "model")]).exit_code == 0
    assert runner.invoke(main, ["compress", str(tmp_path / "model"), "-o", str(tmp_path / "small"), "-k", "16"]).exit_code == 0
    _eval(run_dir, "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e0"))  # the run's own model.pt
    _eval(run_dir, "--model", str(tmp_path / "model"), "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e1"))
    _eval(run_dir, "--model", str(tmp_path / "small"), "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e2"))
    base = json.load(open(tmp_path / "e0" / "metrics.json"))
    raw = json.load(open(tmp_path / "e1" / "metrics.json"))
    cmp = json.load(open(tmp_path / "e2" / "metrics.json"))
    # The export is bit-exact, so its renders are too: same PSNR per view, same PNG bytes.
    assert [r["psnr"] for r in raw["per_image"]] == [r["psnr"] for r in base["per_image"]]
    for name in os.listdir(tmp_path / "e0" / "renders"):
        assert (tmp_path / "e1" / "renders" / name).read_bytes() == (tmp_path / "e0" / "renders" / name).read_bytes()
    assert raw["lpips"] is None and "skipped" in raw["lpips_status"]
    assert cmp["texture_encoding"] == "codebook" and cmp["codebook_size"] == 16
    assert cmp["bytes_on_disk"] < raw["bytes_on_disk"]
    assert cmp["psnr"] != raw["psnr"]

    res = CliRunner().invoke(main, ["eval", "--table", str(tmp_path / "e1"), str(tmp_path / "e2"),
                                    "-o", str(tmp_path / "table")])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "table" / "table.md").read_text()
    assert "| SSIM | PSNR | LPIPS | Points | Texels | Params | FPS | Mem | Texels/Primitive |" in md
    assert "mean (2)" in md and "(compressed, K=16)" in md
    lines = (tmp_path / "table" / "table.csv").read_text().strip().splitlines()
    assert len(lines) == 1 + 2 + 1  # header, two runs, the dataset mean


def test_run_without_model_is_user_error(tmp_path):
    (tmp_path / "run").mkdir()
    for cmd in (["eval", str(tmp_path / "run")], ["export", str(tmp_path / "run")]):
        res = CliRunner().invoke(main, cmd)
        assert res.exit_code == 2 and "no finished model" in res.output
    assert os.listdir(tmp_path / "run") == []


def test_truncated_run_model_is_user_error(run_dir, tmp_path):
    (tmp_path / "run").mkdir()
    data = open(os.path.join(run_dir, "model.pt"), "rb").read()
    (tmp_path / "run" / "model.pt").write_bytes(data[: len(data) // 2])
    res = CliRunner().invoke(main, ["export", str(tmp_path / "run")])
    assert res.exit_code == 2 and "unreadable" in res.output
    assert os.listdir(tmp_path / "run") == ["model.pt"]


def test_table_needs_metrics(tmp_path):
    res = CliRunner().invoke(main, ["eval", "--table", str(tmp_path), "-o", str(tmp_path / "t")])
    assert res.exit_code == 2 and "no metrics.json" in res.output


def test_psnr_known_value():
    import torch

    a = torch.zeros(4, 4, 3)
    assert abs(psnr(a, a + 0.1) - 20.0) < 1e-5  # 0.1 is inexact in float32
    assert psnr(a, a) == 100.0  # capped: JSON has no infinity
