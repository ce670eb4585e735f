"""End to end on a small demo scene: content-aware allocation, and the paper's comparisons.

Slow: four 3000-iteration trainings on the CPU backend (configs/demo*.toml; ~23 min on 2 idle cores).
"""

from __future__ import annotations

import json
import os

import pytest

from ctgs.scene.demo import make_demo_scene
from ctgs.stages.train import train_main
from ctgs.train.allocation import texel_density_by_kind
from ctgs.io.run_model import load_run

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CFG = os.path.join(ROOT, "configs")
# demo.toml trains on 1 thread: deterministic, so the numbers match benchmarks/results/train_demo_*.md.
SETS = ("backend='cpu'",)
# The paper's "model only what a scene requires": photo surfaces get >= 10x the texels per unit area of
# flat ones (issue 4).
MIN_DENSITY_RATIO = 10.0
TWO_DGS_THRESHOLD = 3e-5


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    scene = make_demo_scene(str(root / "scene"), num_views=24, width=96, height=72, points=1500)
    out = {}
    s_default = train_main(scene, str(root / "default"), preset="fast", sets=SETS, quiet=True)
    out["default"] = s_default
    # A second seed of the default, for the allocation claim (a ratio of two texel counts; seeds move it ~1x).
    out["default_seed1"] = train_main(scene, str(root / "default_seed1"), preset="fast",
                                      sets=SETS + ("seed=1",), quiet=True)
    # 2DGS with a densification threshold low enough that it ends with MORE parameters than the default
    # (with its stock 2e-4 it stops at ~0.7M, with 5e-5 and a cap at the default's budget at ~1.06M).
    out["2dgs"] = train_main(scene, str(root / "2dgs"), preset="fast", config="2dgs",
                             sets=SETS + (f"densify_grad_threshold={TWO_DGS_THRESHOLD}",), quiet=True)
    out["fixed_texture"] = train_main(scene, str(root / "fixed"), preset="fast", config="fixed_texture",
                                      sets=SETS, quiet=True)
    return scene, root, out


@pytest.mark.slow
def test_content_aware_allocation(runs):
    # The photo : flat ratio of texels per unit area, averaged over seeds 0 and 1 of the default config.
    # Measured (dev VM): 5531 : 516 = 10.7x (seed 0) and 5328 : 456 = 11.7x (seed 1), mean 11.2x; other
    # configurations moved it by ~1x between seeds (benchmarks/results/train_demo_findings.md).
    scene, root, _ = runs
    meta = json.load(open(os.path.join(scene, "demo_meta.json")))
    ratios = []
    for run in ("default", "default_seed1"):
        model = load_run(str(root / run)).model
        density = texel_density_by_kind(model, meta)
        assert density["flat"] > 0 and density["photo"] > 0, density
        ratios.append(density["photo"] / density["flat"])
    assert sum(ratios) / len(ratios) >= MIN_DENSITY_RATIO, ratios


@pytest.mark.slow
def test_default_beats_2dgs_at_equal_params_and_fixed_texture(runs):
    # Measured (seed 0, dev VM): default 30.20 dB / 1.15M params; 2dgs (3e-5) 28.54 dB / 1.28M params;
    # fixed_texture 26.86 dB / 9.1M params (its test PSNR swings: 29.79 dB one evaluation earlier).
    _, _, out = runs
    d, g, f = out["default"], out["2dgs"], out["fixed_texture"]
    assert d["num_params"] <= g["num_params"], (d, g)
    assert d["final_test_psnr"] > g["final_test_psnr"], (d, g)
    assert d["final_test_psnr"] > f["final_test_psnr"], (d, f)
