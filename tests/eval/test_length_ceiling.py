"""benchmarks/length_ceiling.py and benchmarks/device/run_many.py: the recorded figures recompute from the stored
records, stopped runs are reported as such, and the device driver's bookkeeping holds for failing jobs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
import length_ceiling  # noqa: E402

RECORDS = os.path.join(ROOT, "benchmarks", "results", "length_ceiling_herzjesu25_h200_s35")


def test_the_recorded_figures_recompute(tmp_path):
    runs = [os.path.join(RECORDS, f"v192_{r}_s{s}") for r in ("fast", "balanced", "paper30k") for s in range(4)]
    base = length_ceiling.main([*runs, "--name", "t", "--reference", "v192_fast", "--out-dir", str(tmp_path),
                                "--cpu", "v192_fast=22.66,21.99,22.54,22.68"])
    out = json.load(open(base + ".json"))
    rec = out["recipes"]
    assert round(out["reference_final_mean"], 2) == 22.34
    assert [round(rec[r]["peak_psnr"], 2) for r in ("v192_fast", "v192_balanced", "v192_paper30k")] == \
        [22.91, 22.76, 22.74]
    assert (rec["v192_balanced"]["reached"], rec["v192_paper30k"]["reached"]) == (6667, 11000)
    assert rec["v192_paper30k"]["final_mean"] is None  # stopped runs have no final value
    assert round(out["cross_check"]["v192_fast"]["difference"], 2) == -0.13
    md = open(base + ".md").read()
    assert "no (curve only to iteration 11000)" in md and "| v192_fast | 22.34 | 22.91 (2400) | +0.57 | no |" in md


def _run(folder, evals, iterations, final=None):
    os.makedirs(folder)
    with open(os.path.join(folder, "log.jsonl"), "w") as fh:
        for it, psnr in evals:
            fh.write(json.dumps({"type": "test", "it": it, "psnr": psnr, "ssim": 0.5}) + "\n")
    open(os.path.join(folder, "config.toml"), "w").write(f"iterations = {iterations}\n")
    if final is not None:
        json.dump({"final_test_psnr": final, "final_test_ssim": 0.5}, open(os.path.join(folder, "train_summary.json"), "w"))


def test_a_curve_that_reaches_the_margin_says_so(tmp_path):
    _run(tmp_path / "a_s0", [(100, 20.0), (200, 21.0)], 200, final=21.0)
    _run(tmp_path / "b_s0", [(100, 21.0), (200, 22.5), (300, 22.0)], 1000)
    base = length_ceiling.main([str(tmp_path / "a_s0"), str(tmp_path / "b_s0"), "--name", "t", "--reference", "a",
                                "--out-dir", str(tmp_path)])
    md = open(base + ".md").read()
    assert "| b | - (stopped) | 22.50 (200) | +1.50 | yes (curve only to iteration 300) |" in md


def test_bad_inputs_are_named(tmp_path):
    _run(tmp_path / "unnamed", [(100, 20.0)], 100, final=20.0)
    with pytest.raises(SystemExit, match="RECIPE_sSEED"):
        length_ceiling.main([str(tmp_path / "unnamed"), "--name", "t", "--reference", "a", "--out-dir", str(tmp_path)])
    _run(tmp_path / "a_s0", [(100, 20.0)], 1000)
    with pytest.raises(SystemExit, match="no run of 'a' finished"):
        length_ceiling.main([str(tmp_path / "a_s0"), "--name", "t", "--reference", "a", "--out-dir", str(tmp_path)])


def test_run_many_bookkeeping(tmp_path):
    jobs = tmp_path / "jobs.txt"
    jobs.write_text("# a comment\nx /no/such/scene --backend cpu\n\ny /no/such/scene --backend cpu  # trailing\n"
                    "z /no/such/scene --backend cpu\n")
    root = tmp_path / "root"
    subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "device", "run_many.py"), str(jobs), "--slots",
                    "2", "--stop-after", "120", "--root", str(root)], check=True, cwd=ROOT, timeout=300)
    status = json.load(open(root / "status.json"))
    assert (root / "DONE").exists()
    assert [status["jobs"][n]["state"] for n in "xyz"] == ["failed"] * 3
    assert all(status["jobs"][n]["rc"] != 0 for n in "xyz")
    assert "/no/such/scene" in (root / "x.log").read_text()
    jobs.write_text("x a\nx b\n")
    r = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "device", "run_many.py"), str(jobs),
                        "--stop-after", "1", "--root", str(root)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0 and "used twice" in r.stderr
