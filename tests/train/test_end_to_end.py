"""End to end on a small demo scene: a short content-aware training that checks behaviour and a quality floor.

The paper's claims (allocation ratios, the default vs 2dgs and fixed_texture) need several 3000-iteration
trainings: they are a benchmark, `make bench-claims` (benchmarks/claims.py, results in
benchmarks/results/claims/), not a test.
"""

from __future__ import annotations

import json
import os

import pytest
import torch

from ctgs.evaluation.evaluate import EvalOptions, evaluate
from ctgs.runs import load_run
from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import train_main
from ctgs.train.routines import texels

ITERATIONS = 400
# Measured: the fast preset at 400 iterations on this 96x72 scene, 1 thread, seeds 0-9: 19.3-21.0 dB test PSNR on
# view 008, 16.4-20.1 on view 000 where veil < 0.5 (this run, seed 0: 19.79 on 008); a constant colour scores 13.9
# dB. View 000's camera often sits inside large opaque surfels (docs/studies.md): on seed 0 one carries 95% of its
# blending weight and the view scores 10.0 dB. So the floor holds on every test view that `ctgs eval` does not report
# veiled (veil < 0.5), and at least one must be left: it catches a run that stopped learning, not a small
# regression.
PSNR_FLOOR = 15.5
VEILED = 0.5


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    scene = make_demo_scene(str(root / "scene"), num_views=16, width=96, height=72, points=1500)
    summary = train_main(scene, str(root / "run"), preset="fast", iterations=ITERATIONS,
                         sets=("threads=1", "backend='cpu'"), quiet=True)
    return scene, str(root / "run"), summary


@pytest.mark.slow
def test_short_run_reaches_a_quality_floor_and_runs_every_routine(run):
    _, run_dir, summary = run
    assert summary["iterations"] == ITERATIONS and summary["final_test_psnr"] > 0, summary
    metrics = evaluate(run_dir, EvalOptions(out_dir=os.path.join(run_dir, "eval"), lpips=False))
    clear = [v for v in metrics["per_image"] if v["veil"] < VEILED]
    assert clear and all(v["psnr"] > PSNR_FLOOR for v in clear), metrics["per_image"]
    log = [json.loads(line) for line in open(os.path.join(run_dir, "log.jsonl"))]
    full = [r for r in log if r["type"] == "routine" and r["kind"] == "full"]
    assert any(r["kind"] == "texture_start" for r in log if r["type"] == "routine")
    # The content-aware routine acted in every direction at least once.
    for key in ("upscaled", "downscaled"):
        assert sum(r[key] for r in full) > 0, key
    assert any(r["kind"] == "late" for r in log if r["type"] == "routine")
    model = load_run(run_dir).model
    # The fast preset trims textures after the last iteration, before the final evaluation: model.pt holds the
    # trimmed textures (nothing left to crop), and the last test line scores that model.
    trims = [r for r in log if r["type"] == "routine" and r["kind"] == "trim"]
    assert len(trims) == 1 and trims[0]["texels_after"] == model.num_texels <= trims[0]["texels_before"]
    # (the preset learns the photos' exposures: the learned gains are logged before the last test)
    assert [r["type"] for r in log[log.index(trims[0]):]] == ["routine", "exposure", "test"]
    gains = next(r for r in log if r["type"] == "exposure")["gains"]
    assert len(gains) > 0 and all(0.5 < g < 2 for gs in gains.values() for g in gs)
    assert torch.equal(texels.trim_res(model, 0.004), model.tex_res.cpu())
    # Textures of different texel sizes: the allocation adapted to content.
    assert model.num_texels > 0 and len(set(model.t2p_exp.tolist())) >= 3
    assert summary["params_per_observed_value"] == pytest.approx(model.num_params() / summary["observed_values"])
