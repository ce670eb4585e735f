"""Config loading: defaults, TOML with `base`, --set overrides, unknown keys and wrong types are errors."""

from __future__ import annotations

import dataclasses
import glob
import os

import pytest

from ctgs.errors import UserError
from ctgs.train.config import TrainConfig, load_config, parse_set

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_defaults_match_the_paper():
    c = TrainConfig()
    assert (c.iterations, c.tau_ds, c.tau_tr_start, c.tau_tr_end, c.tau_tr_iters) == (30000, 0.02, 64.0, 32.0, 7000)
    assert (c.lr_texture, c.adam_eps, c.texture_start, c.routine_every, c.max_texture_res) == (7e-4, 1e-15, 500, 250, 256)
    assert c.top_fraction == 0.1 and c.lambda_texture == 1e-8 and c.lambda_opacity == 0.01


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(ROOT, "configs", "*.toml"))))
def test_every_shipped_config_loads(path):
    cfg = load_config(path)
    assert cfg.iterations >= 1


def test_experiments_change_only_their_key():
    d = load_config(os.path.join(ROOT, "configs", "default.toml"))
    assert d == TrainConfig()
    assert load_config(os.path.join(ROOT, "configs", "higher_tau_ds.toml")).tau_ds == 0.04
    assert load_config(os.path.join(ROOT, "configs", "points40k.toml")).max_primitives == 40000
    assert load_config(os.path.join(ROOT, "configs", "2dgs.toml")).method == "2dgs"


def test_surfaces_overlay_adds_the_normal_term_to_any_method():
    fast = load_config(preset="fast")
    surfaces = load_config("surfaces", preset="fast")
    assert surfaces.lambda_normal == 0.05 and surfaces.method == fast.method
    assert dataclasses.replace(surfaces, lambda_normal=fast.lambda_normal) == fast
    both = load_config("2dgs_surfaces", preset="fast")
    assert both == dataclasses.replace(load_config("2dgs", preset="fast"), lambda_normal=0.05)


def test_unknown_key_names_the_key(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("tau_dss = 0.1\n")
    with pytest.raises(UserError, match="tau_dss"):
        load_config(str(p))
    with pytest.raises(UserError, match="nope"):
        load_config(None, parse_set(["nope=1"]))


def test_set_overrides_and_types():
    cfg = load_config(None, parse_set(["tau_ds=0.05", "method=2dgs", "iterations=10", "random_rotation=false"]))
    assert cfg.tau_ds == 0.05 and cfg.method == "2dgs" and cfg.iterations == 10 and cfg.random_rotation is False
    with pytest.raises(UserError, match="iterations"):
        load_config(None, {"iterations": "many"})
    with pytest.raises(UserError, match="method"):
        load_config(None, {"method": "nerf"})
