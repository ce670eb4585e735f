"""benchmarks/gpu_train_probe.py: the allocator-trace replay that names what is alive at a memory peak."""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "benchmarks"))
import gpu_train_probe  # noqa: E402

MB = 2**20


def _ev(action, addr, mb, where="/x/ctgs/train/routines/texels.py", line=10, name="upscale"):
    frames = [{"filename": "/usr/lib/torch/functional.py", "line": 1, "name": "interp"},
              {"filename": where, "line": line, "name": name}]
    return {"action": action, "addr": addr, "size": int(mb * MB), "frames": frames}


def test_peak_live_set_finds_the_peak_and_groups_sites():
    trace = [
        _ev("alloc", 1, 100),                                   # 100
        _ev("alloc", 2, 300, "/x/ctgs/model/jagged.py", 40, "remap"),  # 400
        _ev("alloc", 3, 300, "/x/ctgs/model/jagged.py", 40, "remap"),  # 700 <- peak
        _ev("free_requested", 2, 300),
        _ev("free_completed", 2, 300),                         # 400
        _ev("alloc", 4, 200),                                   # 600
        _ev("free_completed", 99, 5000),                        # allocated before the trace: ignored
        _ev("free_completed", 3, 300),
        _ev("alloc", 5, 250),                                   # 550
    ]
    out = gpu_train_probe.peak_live_set(trace)
    assert out["peak_rise_mb"] == 700.0 and out["peak_index"] == 2 and out["events"] == len(trace)
    assert out["sites"][0] == {"site": "ctgs/model/jagged.py:40 remap", "mb": 600.0, "count": 2}
    assert out["sites"][1] == {"site": "ctgs/train/routines/texels.py:10 upscale", "mb": 100.0, "count": 1}
    assert len(out["sites"]) == 2


def test_peak_live_set_of_an_empty_trace():
    assert gpu_train_probe.peak_live_set([]) == {"peak_rise_mb": 0.0, "peak_index": -1, "events": 0, "sites": []}


def test_site_falls_back_to_the_innermost_frame():
    assert gpu_train_probe._site([{"filename": "/t/torch/nn.py", "line": 3, "name": "f"}]) == "/t/torch/nn.py:3 f"
    assert gpu_train_probe._site([]) == "(no frames)"
