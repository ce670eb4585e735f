"""Scene-relative rules, presets, config checks (ranges, did-you-mean, --list-keys)."""

from __future__ import annotations

import os

import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.train.config import schedule
from ctgs.train.config import PRESETS, TrainConfig, describe_keys, load_config, parse_set
from ctgs.train.config.rules import resolve
from rule_table import rule_table

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_rules_are_the_identity_at_the_papers_scale():
    c = TrainConfig()
    r = resolve(c, 1.0e6)
    assert (r.tau_tr_start, r.tau_tr_end, r.max_texture_res, r.lambda_texture) == (64.0, 32.0, 256, 1e-8)
    assert schedule.factor(r) == 1.0 and schedule.texture_start(r) == 500


def test_rules_scale_the_texture_cap_with_the_linear_size_and_lambda_with_the_area():
    c = TrainConfig()
    r = resolve(c, 500 * 500)  # half the paper's width
    assert r.max_texture_res == 128 and r.lambda_texture == pytest.approx(4e-8)
    # tau_tr counts texels of >= 2 px: already pixel-relative, no rule.
    assert (r.tau_tr_start, r.tau_tr_end) == (64.0, 32.0)
    tiny = resolve(c, 100 * 100)
    assert tiny.max_texture_res == 64  # the floor stays above tau_tr_end
    # The opt-in exponent: 0.5 keeps split decisions at the same fraction of the image (tau x linear size).
    half = resolve(TrainConfig(tau_tr_pixel_exponent=0.5), 500 * 500)
    assert (half.tau_tr_start, half.tau_tr_end) == pytest.approx((32.0, 16.0))
    # The paper preset uses every value as written.
    p = resolve(load_config(None, preset="paper"), 250 * 250)
    assert (p.tau_tr_start, p.tau_tr_end, p.max_texture_res, p.lambda_texture) == (64.0, 32.0, 256, 1e-8)
    # The rule table documents every rule with its value at the paper's scale and at 200 px.
    rows = rule_table(c, {"paper": (1000, 1000), "200px": (200, 150)}, {"30k": 30000, "3k": 3000})
    lam = next(r for r in rows if r["setting"] == "lambda_texture")
    assert lam["values"]["paper"] == 1e-8 and lam["values"]["200px"] == pytest.approx(1e-8 * 1e6 / 3e4)
    ts = next(r for r in rows if r["setting"] == "texture_start")
    assert ts["values"] == {"30k": 500, "3k": 50}


def test_presets_load_and_paper_is_the_authors_recipe():
    paper = load_config(None, preset="paper")
    assert paper.iterations == 30000 and paper.scale_rules is False and paper.preset == "paper"
    assert {k: v for k, v in paper.to_dict().items() if k not in ("scale_rules", "preset")} == \
        {k: v for k, v in TrainConfig().to_dict().items() if k not in ("scale_rules", "preset")}
    its = [load_config(None, preset=p).iterations for p in ("preview", "fast", "balanced")]
    assert its == sorted(its) and len(set(its)) == 3
    assert set(PRESETS) == {"preview", "fast", "balanced", "paper"}
    # Opacity resets in content-aware runs: only `balanced` took them (chosen on validation views); the paper has none.
    assert [load_config(None, preset=p).content_opacity_reset for p in ("preview", "fast", "balanced", "paper")] == \
        [False, False, True, False]
    # A config overlay and --set apply on top of the preset.
    c = load_config("2dgs", {"iterations": 77}, preset="fast")
    assert c.method == "2dgs" and c.iterations == 77 and c.random_background is True
    with pytest.raises(UserError, match="preset"):
        load_config(None, preset="turbo")
    with pytest.raises(UserError, match="no such config"):
        load_config("nonexistent_config")


def test_default_toml_lists_every_key_with_its_default():
    d = load_config(os.path.join(ROOT, "configs", "default.toml"))
    assert d == TrainConfig()
    text = open(os.path.join(ROOT, "configs", "default.toml")).read()
    for key, _, _ in describe_keys():
        if key != "preset":
            assert f"\n{key} = " in text, key


@pytest.mark.parametrize("key,value,what", [
    ("top_fraction", 0.0, "in \\(0, 1\\]"), ("top_fraction", 1.5, "in \\(0, 1\\]"), ("tau_ds", 0.0, "> 0"),
    ("schedule_scale", -1.0, ">= 0"), ("max_texture_res", 48, "a power of two"), ("init_opacity", 1.0, "in \\(0, 1\\)"),
    ("routine_every", 0, "> 0"), ("time_budget", -5.0, ">= 0"),
])
def test_out_of_range_values_name_the_key(key, value, what):
    with pytest.raises(UserError, match=f"{key}=.*must be {what}"):
        load_config(None, {key: value})


def test_unknown_key_suggests_the_closest():
    with pytest.raises(UserError, match="did you mean 'tau_ds'"):
        load_config(None, parse_set(["tau_dss=0.1"]))
    with pytest.raises(UserError, match="list-keys"):
        load_config(None, parse_set(["zzzz=1"]))


def test_list_keys_prints_every_key():
    r = CliRunner().invoke(main, ["train", "--list-keys"])
    assert r.exit_code == 0, r.stderr
    for key, default, _ in describe_keys():
        assert f"{key} = {default!r}" in r.stdout
    # each key says which methods' strategies read it (ctgs.train.strategies: KEYS)
    assert "tau_ds = 0.02    [content_aware]\n" in r.stdout
    assert "densify_every = 100    [2dgs, fixed_texture]\n" in r.stdout
    assert "fixed_texture_res = 16    [fixed_texture]\n" in r.stdout and "\nseed = 0\n" in r.stdout
