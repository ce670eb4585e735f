"""benchmarks/seen_pixels.py: which test pixels the training cameras hold, from cameras and SfM points alone."""

from __future__ import annotations

import json
import math
import os
import sys

import numpy as np
import pytest
import torch

from ctgs.render.camera import Camera

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
import seen_pixels  # noqa: E402

W, H, F = 40, 30, 40.0
SEEN, FEW, PARTLY, UNSEEN = 0, 1, 2, 3


def cam(x: float = 0.0, yaw_deg: float = 0.0) -> Camera:
    """Camera centred at (x, 0, 0), turned by yaw about the world y axis (0: looking down +z)."""
    a = math.radians(yaw_deg)
    r_c2w = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                         dtype=torch.float64)
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = r_c2w.T
    vm[:3, 3] = -r_c2w.T @ torch.tensor([x, 0.0, 0.0], dtype=torch.float64)
    return Camera(fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H, viewmat=vm)


def wall(depth_lo: float = 4.0, depth_hi: float = 6.0) -> np.ndarray:
    """SfM points filling the test view between two depths."""
    rng = np.random.default_rng(0)
    z = rng.uniform(depth_lo, depth_hi, 400)
    return np.stack([rng.uniform(-0.4, 0.4, 400) * z, rng.uniform(-0.3, 0.3, 400) * z, z], 1).astype(np.float32)


def test_the_same_camera_three_times_holds_every_pixel():
    cls = seen_pixels.seen_classes(cam(), [cam(), cam(), cam()], wall())
    assert cls.shape == (H, W)
    assert bool((cls == SEEN).all())


def test_one_or_two_cameras_make_few():
    assert bool((seen_pixels.seen_classes(cam(), [cam()], wall()) == FEW).all())
    assert bool((seen_pixels.seen_classes(cam(), [cam(), cam(), cam(yaw_deg=180)], wall()) == FEW).all())


def test_a_camera_looking_away_sees_nothing():
    assert bool((seen_pixels.seen_classes(cam(), [cam(yaw_deg=180)], wall()) == UNSEEN).all())


def test_a_sideways_step_loses_near_depths_on_one_side():
    """A training camera one unit to the right (same direction): at infinity it holds every direction the test
    camera sees, at depth 4 it misses the test view's left columns (x < 1 - 0.5 * 4 = -1, i.e. u < 10)."""
    cls = seen_pixels.seen_classes(cam(), [cam(x=1.0)] * 3, wall())
    left, right = cls[:, :8], cls[:, 22:]
    assert bool((left == PARTLY).all())
    assert bool((right == SEEN).all())
    # the boundary moves with the depth range: nearer SfM points push it further right
    near = seen_pixels.seen_classes(cam(), [cam(x=1.0)] * 3, wall(2.0, 3.0))
    assert int((near == PARTLY).sum()) > int((cls == PARTLY).sum())


def test_too_few_sfm_points_in_view_is_an_error():
    behind = wall() * np.array([1, 1, -1], np.float32)
    with pytest.raises(ValueError, match="SfM points"):
        seen_pixels.seen_classes(cam(), [cam()], behind)


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
