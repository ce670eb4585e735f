"""benchmarks/gpu_train_phases.py: per-phase timing from a run's log.jsonl, with the baselines' own schedule
(densification) rather than the content-aware one's (texture start, tau_tr, routines)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPT = os.path.join(ROOT, "benchmarks", "gpu_train_phases.py")


def _run(tmp_path, name: str, method: str, iterations: int, stop: int) -> str:
    run = tmp_path / name
    run.mkdir()
    (run / "config.toml").write_text(f'method = "{method}"\niterations = {iterations}\n')
    recs = [{"type": "start", "method": method, "device": "cuda", "pixels": 100.0}]
    for it in range(100, stop + 1, 100):
        n = 10 + it // 10
        # 1 ms per iteration up to 1/2 of the run (densification / routines), 2 ms after
        half = iterations // 2
        secs = 0.001 * it if it <= half else 0.001 * half + 0.002 * (it - half)
        recs.append({"type": "step", "it": it, "n": n, "texels": 0, "seconds": secs, "wall": secs + 1})
    recs.append({"type": "test", "it": stop, "psnr": 20.0, "ssim": 0.8})
    (run / "log.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n")
    return str(run)


def test_phases_follow_each_method_and_label_an_extrapolation(tmp_path):
    base = _run(tmp_path, "base", "2dgs", 3000, 3000)
    ours = _run(tmp_path, "ours", "content_aware", 3000, 2600)  # stopped early: extrapolated, and labelled so
    out = tmp_path / "phases"
    subprocess.run([sys.executable, SCRIPT, base, ours, "-o", str(out), "--note", "a note"], check=True,
                   capture_output=True, text=True)
    data = json.loads(out.with_suffix(".json").read_text())
    runs = {r["run"]: r for r in data["runs"]}
    # the baseline at 3000 iterations: densification 50-1500 (the paper's 500-15000 scaled by 0.1), then the tail
    assert [(p["phase"], p["from"], p["to"]) for p in runs["base"]["phases"]] == [
        ("before densification", 0, 50), ("densification", 50, 1500), ("tail", 1500, 3000)]
    tail = runs["base"]["phases"][-1]
    assert abs(tail["s_per_1000"] - 2.0) < 1e-9 and tail["covered"] == 1500
    assert runs["base"]["extrapolated_train_seconds"] is None
    assert [p["phase"] for p in runs["ours"]["phases"]][:2] == ["before texture start", "until tau_tr settles"]
    assert runs["ours"]["iterations_run"] == 2600
    assert abs(runs["ours"]["extrapolated_train_seconds"] - (1.5 + 1100 * 0.002 + 400 * 0.002)) < 1e-6
    md = out.with_suffix(".md").read_text()
    assert "a note" in md and "Extrapolation, not a measurement" in md
