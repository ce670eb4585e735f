"""The best periodic evaluation of a run (train_summary.json `eval_peak`) and `ctgs train`'s note when the run ends
well below it (it overfits its training photos)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.runs import eval_peak


def _log(path, records):
    with open(path, "w") as fh:
        for r in records:
            fh.write(json.dumps(r) + "\n")


def test_eval_peak_reads_the_best_test_line(tmp_path):
    log = tmp_path / "log.jsonl"
    _log(log, [{"type": "step", "it": 1, "psnr": 99.0}, {"type": "test", "it": 100, "psnr": 20.0, "ssim": 0.7},
               {"type": "routine", "it": 150, "kind": "full"}, {"type": "test", "it": 200, "psnr": 22.5, "ssim": 0.8},
               {"type": "test", "it": 300, "psnr": 22.5, "ssim": 0.9}, {"type": "test", "it": 400, "psnr": 21.0,
                                                                         "ssim": 0.85}])
    assert eval_peak(str(log)) == {"it": 200, "psnr": 22.5, "ssim": 0.8}  # training steps ignored, earliest tie
    _log(log, [{"type": "step", "it": 1, "psnr": 30.0}])
    assert eval_peak(str(log)) is None
    assert eval_peak(str(tmp_path / "missing.jsonl")) is None


@pytest.mark.parametrize("views, final, noted", [("test", 21.9, True), ("test", 22.5, False),
                                                 ("validation", 21.9, True), ("training", 21.9, False)])
def test_train_notes_a_run_that_ends_below_its_peak(tmp_path, monkeypatch, views, final, noted):
    from ctgs.stages import train as train_stage

    summary = {"iterations": 30000, "train_seconds": 440.0, "final_test_psnr": final, "num_primitives": 10,
               "num_texels": 0, "num_params": 100, "wall_seconds": 500.0,
               "eval_peak": {"it": 5000, "psnr": 22.92, "ssim": 0.83, "views": views}}
    monkeypatch.setattr(train_stage, "train_main", lambda *a, **k: summary)
    res = CliRunner().invoke(main, ["train", str(tmp_path), "-o", str(tmp_path / "run"), "-q"])
    assert res.exit_code == 0, res.output
    assert (f"{views} PSNR peaked at 22.92 dB at iteration 5000" in res.output) == noted, res.output
    assert ("validation_holdout" in res.output) == (noted and views == "test")
