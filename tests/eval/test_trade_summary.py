"""benchmarks/trade_summary.py: every registered record resolves, and its seeded means are the figures the README quotes."""

from __future__ import annotations

import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "benchmarks"))
import trade_summary  # noqa: E402


@pytest.mark.parametrize("scene", list(trade_summary.REGISTRY))
def test_every_registered_record_resolves(scene):
    points = trade_summary.summarise(scene)
    assert len(points) == sum(len(v) for v in trade_summary.REGISTRY[scene].values())
    for p in points:
        assert p["n"] >= 1 and 10 < p["psnr"] < 40 and p["wall_min"] > 0 and p["params"] > 0, p


def test_the_seeded_equal_time_means():
    points = {(p["size"], p["method"], p["label"]): p for p in trade_summary.summarise("herzjesu25")}
    ca = points[("192x128", "content-aware", "fast, length chosen on validation")]
    gs = points[("192x128", "2dgs", "length chosen on validation")]
    assert (ca["n"], round(ca["psnr"], 2), gs["n"], round(gs["psnr"], 2)) == (8, 23.30, 8, 22.76)
    ca = points[("384x256", "content-aware", "fast, length chosen on validation")]
    gs = points[("384x256", "2dgs", "length chosen on validation")]
    assert (ca["n"], round(ca["psnr"], 2), gs["n"], round(gs["psnr"], 2)) == (3, 22.30, 3, 23.14)


def test_an_unknown_run_label_is_named(tmp_path):
    with pytest.raises(SystemExit, match="no run matches"):
        trade_summary.runs_of(os.path.join(trade_summary.RESULTS, "paired/herzjesu25_balanced_fast_eca05b4.json"),
                              ("paired", "no_such_label"))
