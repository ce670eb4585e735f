"""benchmarks/seen_pixels.py writes its tables (the classes themselves: tests/scene/test_coverage.py)."""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
import seen_pixels  # noqa: E402

def test_script_writes_tables_for_two_groups(tmp_path, monkeypatch):
    from fixture_run import make_run

    run_a = make_run(str(tmp_path / "a"), views=9, width=40, height=32, n=120)
    run_b = make_run(str(tmp_path / "b"), views=9, width=40, height=32, n=60)
    # both runs must name one scene: point b at a's scene
    blob = torch.load(os.path.join(run_b, "model.pt"), weights_only=False)
    blob["scene_dir"] = torch.load(os.path.join(run_a, "model.pt"), weights_only=False)["scene_dir"]
    torch.save(blob, os.path.join(run_b, "model.pt"))
    monkeypatch.setattr(seen_pixels, "ROOT", str(tmp_path))
    os.makedirs(tmp_path / "benchmarks" / "results")
    monkeypatch.setattr(sys, "argv", ["seen_pixels.py", "--group", f"a={run_a}", "--group", f"b={run_b}",
                                      "--out", "t"])
    seen_pixels.main()
    md = (tmp_path / "benchmarks" / "results" / "seen_pixels_t.md").read_text()
    rec = json.loads((tmp_path / "benchmarks" / "results" / "seen_pixels_t.json").read_text())
    assert "| a |" in md and "| b |" in md and "Reference group: **a**" in md
    views = rec["groups"]["a"][0]["views"]
    for v in views.values():
        shares = [v[f"{c}_pixels"] for c in seen_pixels.CLASSES]
        assert sum(shares) == pytest.approx(1.0, abs=1e-6)
        assert sum(v["share_of_error"].values()) == pytest.approx(1.0, abs=1e-4)
    # the paired difference is b's mean minus a's
    d = np.mean(rec["summary"]["b"]["test_psnr"]) - np.mean(rec["summary"]["a"]["test_psnr"])
    assert f"{d:+.2f}" in md
