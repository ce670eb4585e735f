"""ctgs.scene.coverage: which pixels of a camera the training cameras hold, from cameras and SfM points alone."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ctgs.render.camera import Camera
from ctgs.scene import coverage

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
    cls = coverage.seen_classes(cam(), [cam(), cam(), cam()], wall())
    assert cls.shape == (H, W)
    assert bool((cls == SEEN).all())


def test_one_or_two_cameras_make_few():
    assert bool((coverage.seen_classes(cam(), [cam()], wall()) == FEW).all())
    assert bool((coverage.seen_classes(cam(), [cam(), cam(), cam(yaw_deg=180)], wall()) == FEW).all())


def test_a_camera_looking_away_sees_nothing():
    assert bool((coverage.seen_classes(cam(), [cam(yaw_deg=180)], wall()) == UNSEEN).all())


def test_a_sideways_step_loses_near_depths_on_one_side():
    """A training camera one unit to the right (same direction): at infinity it holds every direction the test
    camera sees, at depth 4 it misses the test view's left columns (x < 1 - 0.5 * 4 = -1, i.e. u < 10)."""
    cls = coverage.seen_classes(cam(), [cam(x=1.0)] * 3, wall())
    left, right = cls[:, :8], cls[:, 22:]
    assert bool((left == PARTLY).all())
    assert bool((right == SEEN).all())
    # the boundary moves with the depth range: nearer SfM points push it further right
    near = coverage.seen_classes(cam(), [cam(x=1.0)] * 3, wall(2.0, 3.0))
    assert int((near == PARTLY).sum()) > int((cls == PARTLY).sum())


def test_too_few_sfm_points_in_view_is_an_error():
    behind = wall() * np.array([1, 1, -1], np.float32)
    with pytest.raises(ValueError, match="SfM points"):
        coverage.seen_classes(cam(), [cam()], behind)


