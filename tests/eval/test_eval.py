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

# Every metrics.json must carry these keys (docs/reference/metrics.md), with these types (None allowed where listed).
SCHEMA = {
    "schema": str, "schema_version": int, "scene": str, "dataset": str, "run_dir": str, "model_source": str,
    "scene_dir": str, "images": str, "holdout": int, "split": str, "num_views": int, "num_test_views": int, "psnr": float, "ssim": float, "open_pixels": float,
    "lpips": (float, type(None)), "lpips_status": str, "points": int, "texels": int, "params": int,
    "texels_per_primitive": float, "model_memory_bytes": int, "bytes_on_disk": int, "texture_encoding": str,
    "codebook_size": (int, type(None)), "compressed": bool, "compression_target": (str, type(None)), "fps": float, "render_ms_mean": float, "backend": str, "device": str,
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
    assert s.shape[:2] == (32, 4 * 40)  # gt | render | error | texel size side by side (a textured model)


def test_eval_on_the_training_views(run_dir, tmp_path):
    """--split train: the views the run was fitted to (7 of the 9 here), into RUN_DIR/eval-train; a validation run's
    validation views are not among them."""
    import shutil

    import torch

    res = _eval(run_dir, "--split", "train", "--backend", "reference", "--no-lpips")
    m = json.load(open(os.path.join(run_dir, "eval-train", "metrics.json")))
    names = [r["name"] for r in m["per_image"]]
    assert m["split"] == "train" and m["num_views"] == 7 and m["num_test_views"] is None
    assert "000.png" not in names and "008.png" not in names and len(set(names)) == 7
    assert "7 training views" in res.output
    test = json.load(open(os.path.join(run_dir, "eval", "metrics.json"))) if os.path.isfile(
        os.path.join(run_dir, "eval", "metrics.json")) else None
    assert test is None or test["split"] == "test"
    # A validation run (validation_holdout = 3: training views 1, 4, 7 of the 7 held out) is scored on the other 4.
    val = tmp_path / "valrun"
    shutil.copytree(run_dir, val, ignore=shutil.ignore_patterns("eval*"))
    ckpt = torch.load(val / "model.pt", weights_only=True)
    ckpt["config"] = {**ckpt["config"], "validation_holdout": 3}
    torch.save(ckpt, val / "model.pt")
    _eval(str(val), "--split", "train", "--backend", "reference", "--no-lpips")
    mv = json.load(open(val / "eval-train" / "metrics.json"))
    assert [r["name"] for r in mv["per_image"]] == [n for i, n in enumerate(names) if i % 3 != 1]
    from ctgs.evaluation.report import build_table

    md, _ = build_table([m, {**m, "split": "test"}])
    assert "(training views)" in md  # never averaged with the test figures


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
    assert cmp["texture_encoding"] == "scalar" and cmp["codebook_size"] == 16
    assert cmp["bytes_on_disk"] < raw["bytes_on_disk"]
    assert cmp["psnr"] != raw["psnr"]

    # The table: a compressed model is its own group (never averaged with its source), and its Mem is
    # what it takes on disk, not 4 bytes per decoded parameter.
    res = CliRunner().invoke(main, ["eval", "--table", str(tmp_path / "e1"), str(tmp_path / "e2"),
                                    "-o", str(tmp_path / "table")])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "table" / "table.md").read_text()
    assert "| SSIM | PSNR | LPIPS | Points | Texels | Params | FPS | Mem | Disk | Texels/Primitive |" in md
    assert "mean (1)" in md and "(compressed balanced: scalar K=16)" in md
    assert "mean (compressed balanced: scalar K=16) (1)" in md
    rows = list(csv.reader(open(tmp_path / "table" / "table.csv")))
    assert len(rows) == 1 + 2 * 2  # header, then each variant: its run and its own mean
    head = rows[0]
    by_label = {r[1]: dict(zip(head, r)) for r in rows[1:]}
    small = by_label["evalrun0 (compressed balanced: scalar K=16)".replace("evalrun0", raw["scene"])]
    assert int(small["Mem"]) == cmp["bytes_on_disk"] == int(small["Disk"])
    assert int(by_label[raw["scene"]]["Mem"]) == 4 * raw["params"]
    assert abs(float(by_label["mean"]["PSNR"]) - raw["psnr"]) < 1e-9  # the raw mean is the raw model alone


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


def test_open_pixels_and_psnr_over_the_covered_ones(run_dir, tmp_path):
    """Each view's open share (rendered alpha < OPEN_ALPHA) and PSNR over the other pixels, against a direct render."""
    import torch

    from ctgs.runs import load_run
    from ctgs.metrics.psnr import masked_psnr, psnr
    from ctgs.evaluation.report import OPEN_ALPHA
    from ctgs.render import render
    from ctgs.scene import load_scene

    _eval(run_dir, "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e"))
    m = json.load(open(tmp_path / "e" / "metrics.json"))
    run = load_run(run_dir)
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    inputs = run.model.render_inputs()
    opens = []
    for view, row in zip(scene.test, m["per_image"]):
        with torch.no_grad():
            out = render(inputs, view.camera, backend="reference", sh_degree=run.model.sh_degree)
        open_px = out.alpha.reshape(out.rgb.shape[:2]) < OPEN_ALPHA
        gt = torch.as_tensor(view.image, dtype=torch.float32)
        assert row["open"] == pytest.approx(float(open_px.float().mean()), abs=1e-6)
        assert row["psnr_covered"] == pytest.approx(masked_psnr(out.rgb.clamp(0, 1), gt, ~open_px), abs=1e-4)
        rgb = out.rgb.clamp(0, 1).double()
        gain = float((rgb * gt).sum() / (rgb * rgb).sum())  # the least-squares exposure gain, and PSNR after it
        assert row["gain"] == pytest.approx(gain, rel=1e-5)
        assert row["psnr_gain"] == pytest.approx(psnr((rgb * gain).clamp(0, 1), gt), abs=1e-4)
        assert row["psnr_gain"] >= row["psnr"] - 1e-6 or gain * float(rgb.max()) > 1  # (clipping aside, no worse)
        opens.append(row["open"])
    assert 0 < max(opens) < 1  # the fixture's sparse surfels leave some background showing
    assert m["open_pixels"] == pytest.approx(sum(opens) / len(opens))
    rows = list(csv.DictReader(open(tmp_path / "e" / "per_image.csv")))
    assert [float(r["open"]) for r in rows] == pytest.approx(opens, abs=1e-5)
    assert [float(r["gain"]) for r in rows] == pytest.approx([r["gain"] for r in m["per_image"]], abs=1e-5)
    assert m["psnr_gain_matched"] == pytest.approx(sum(r["psnr_gain"] for r in m["per_image"]) / len(rows))


def test_gain_matched_psnr_undoes_an_exposure_and_nothing_else():
    """A photo that is the render x 0.8 is matched exactly (gain 0.8, PSNR at its 100 dB cap); a render that differs
    by more than a gain keeps that error; an all-black render gets gain 1."""
    import torch

    from ctgs.metrics.psnr import gain_matched_psnr, psnr

    g = torch.Generator().manual_seed(0)
    render = torch.rand(12, 10, 3, generator=g) * 0.9
    gain, p = gain_matched_psnr(render, render * 0.8)
    assert gain == pytest.approx(0.8, rel=1e-6) and p == pytest.approx(100.0)  # (float32 photo: 0.8 to 1e-7)
    noisy = (render * 0.8 + 0.05 * torch.randn(12, 10, 3, generator=g)).clamp(0, 1)
    gain, p = gain_matched_psnr(render, noisy)
    assert abs(gain - 0.8) < 0.05 and psnr(render, noisy) < p < 30
    assert gain_matched_psnr(torch.zeros(4, 4, 3), torch.rand(4, 4, 3, generator=g))[0] == 1.0


def test_a_model_that_covers_nothing_is_all_open_and_says_so(run_dir, tmp_path):
    """The extreme: every pixel open -> open 1.0, no covered PSNR (null / empty), and the CLI names the view."""
    import shutil

    import torch

    run = str(tmp_path / "transparent")
    shutil.copytree(run_dir, run)
    state = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    state["model"]["opacity_logits"] = torch.full_like(state["model"]["opacity_logits"], -30.0)
    torch.save(state, os.path.join(run, "model.pt"))
    res = _eval(run, "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e"))
    m = json.load(open(tmp_path / "e" / "metrics.json"))
    assert m["open_pixels"] == 1.0
    assert all(r["open"] == 1.0 and r["psnr_covered"] is None for r in m["per_image"])
    assert all(r["psnr_covered"] == "" for r in csv.DictReader(open(tmp_path / "e" / "per_image.csv")))
    assert "100.0% of the pixels open" in res.output


def test_masked_psnr():
    import torch

    from ctgs.metrics.psnr import masked_psnr

    a, b = torch.zeros(4, 5, 3), torch.zeros(4, 5, 3)
    b[0, :] = 0.5  # error only in the first row
    everything = torch.ones(4, 5, dtype=torch.bool)
    assert masked_psnr(a, b, everything) == pytest.approx(psnr(a, b))
    first_row = torch.zeros(4, 5, dtype=torch.bool)
    first_row[0] = True
    assert masked_psnr(a, b, first_row) == pytest.approx(-10 * __import__("math").log10(0.25))
    assert masked_psnr(a, b, ~first_row) == 100.0  # an exact match: the MSE floor
    assert masked_psnr(a, b, torch.zeros(4, 5, dtype=torch.bool)) is None
    with pytest.raises(ValueError):
        masked_psnr(a, b, torch.ones(5, 4, dtype=torch.bool))


def test_eval_an_exported_gaussian_file(run_dir, tmp_path):
    """`--model FILE`: an exported Gaussian file, read back as a viewer reads it (texture folded in), scored on the
    same views; its own group in tables; a file of another kind is refused with the endings named."""
    runner = CliRunner()
    assert runner.invoke(main, ["export", run_dir, "--format", "sog", "-o", str(tmp_path / "m.sog")]).exit_code == 0
    _eval(run_dir, "--model", str(tmp_path / "m.sog"), "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e"))
    m = json.load(open(tmp_path / "e" / "metrics.json"))
    assert m["exported_file"] == ".sog" and m["texture_encoding"] == "folded" and m["texels"] == 0
    assert m["bytes_on_disk"] == (tmp_path / "m.sog").stat().st_size
    _eval(run_dir, "--backend", "reference", "--no-lpips", "-o", str(tmp_path / "e0"))
    base = json.load(open(tmp_path / "e0" / "metrics.json"))
    assert m["psnr"] != base["psnr"] and base["exported_file"] is None  # textures folded: not the exact model
    from ctgs.evaluation.report import variant

    assert variant(m) == "exported .sog"
    (tmp_path / "x.txt").write_text("x")
    res = runner.invoke(main, ["eval", run_dir, "--model", str(tmp_path / "x.txt"), "--no-lpips", "-o",
                               str(tmp_path / "e2")])
    assert res.exit_code != 0 and "x.txt: not a file `ctgs export` writes" in res.output
    assert not (tmp_path / "e2").exists()


def test_a_run_trained_on_a_gpu_evaluates_where_there_is_none(run_dir, tmp_path):
    """A run whose config says backend = "cuda" (trained on a GPU) is evaluated on the CPU backend on a machine
    without one, unless --backend asks for cuda (then the renderer's one-line error)."""
    import shutil

    import torch

    if torch.cuda.is_available():
        pytest.skip("checks the machine without a GPU")
    run = str(tmp_path / "gpu_run")
    shutil.copytree(run_dir, run)
    state = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    state["config"]["backend"] = "cuda"
    torch.save(state, os.path.join(run, "model.pt"))
    _eval(run, "--no-lpips", "-o", str(tmp_path / "e"))
    assert json.load(open(tmp_path / "e" / "metrics.json"))["backend"] == "cpu"
    res = CliRunner().invoke(main, ["eval", run, "--no-lpips", "--backend", "cuda", "-o", str(tmp_path / "e2")])
    assert res.exit_code != 0 and "needs an NVIDIA GPU" in res.output


def test_a_moved_run_names_its_missing_scene_and_takes_scene(run_dir, tmp_path):
    """A run whose model.pt names a scene folder that is not here (trained on another machine) fails with one line
    that names it and the fix; --scene (eval and render) reads this machine's copy instead."""
    import shutil

    import torch

    run = str(tmp_path / "moved")
    shutil.copytree(run_dir, run)
    state = torch.load(os.path.join(run, "model.pt"), weights_only=True)
    here = state["scene_dir"]
    state["scene_dir"] = "/nonexistent/gpu-server/scenes/demo"
    torch.save(state, os.path.join(run, "model.pt"))
    res = CliRunner().invoke(main, ["eval", run, "--no-lpips", "--backend", "cpu", "-o", str(tmp_path / "e")])
    assert res.exit_code != 0 and "/nonexistent/gpu-server/scenes/demo" in res.output and "--scene" in res.output
    assert not os.path.exists(tmp_path / "e")
    res = CliRunner().invoke(main, ["render", run, "-o", str(tmp_path / "r"), "--backend", "cpu"])
    assert res.exit_code != 0 and "--scene" in res.output
    _eval(run, "--no-lpips", "--backend", "cpu", "--scene", here, "-o", str(tmp_path / "e"))
    m = json.load(open(tmp_path / "e" / "metrics.json"))
    assert m["scene_dir"] == os.path.abspath(here) and m["num_test_views"] == 2
    res = CliRunner().invoke(main, ["render", run, "-o", str(tmp_path / "r"), "--backend", "cpu", "--scene", here])
    assert res.exit_code == 0, res.output
    assert len([f for f in os.listdir(tmp_path / "r") if f.endswith(".png")]) == 2
    res = CliRunner().invoke(main, ["eval", run, "--no-lpips", "--scene", str(tmp_path / "nope"), "-o",
                                    str(tmp_path / "e3")])
    assert res.exit_code != 0 and "scene folder not found" in res.output
