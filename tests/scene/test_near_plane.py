"""The near plane from the scene's content (ctgs.scene.loader.near_plane, content_depth)."""

from __future__ import annotations

import numpy as np
import pytest

from ctgs.render.camera import Camera
from ctgs.scene.loader import NEAR_CONTENT_FRACTION, NEAR_FRACTION, content_depth, near_plane

SIZE = (100.0, 100.0, 50.0, 50.0, 100, 100)  # fx, fy, cx, cy, W, H


def wall(depth: float, n: int = 1000, seed: int = 0) -> np.ndarray:
    """Points on a wall `depth` in front of the identity camera, inside its view."""
    xy = np.random.default_rng(seed).uniform(-0.4 * depth, 0.4 * depth, (n, 2))
    return np.column_stack([xy, np.full(n, depth)])


def test_content_depth_is_the_nearest_views_low_quantile_robust_to_stray_points():
    eye = np.eye(4)
    closer = np.eye(4)
    closer[2, 3] = -3.0  # a camera 3 units closer to the wall
    pts = wall(5.0)
    assert content_depth([eye], [SIZE], pts) == pytest.approx(5.0)
    assert content_depth([eye, closer], [SIZE, SIZE], pts) == pytest.approx(2.0)  # smallest over views
    stray = np.vstack([pts, [[0.0, 0.0, 0.01]]])  # one bad SfM point just in front of the lens
    assert content_depth([eye], [SIZE], stray) == pytest.approx(5.0)
    behind_or_outside = np.array([[0.0, 0.0, -1.0], [100.0, 0.0, 1.0]])
    assert content_depth([eye], [SIZE], behind_or_outside) is None


def test_near_plane_takes_the_larger_rule_and_falls_back():
    assert near_plane(10.0, 5.0) == pytest.approx(NEAR_CONTENT_FRACTION * 5.0)
    assert near_plane(1e4, 5.0) == pytest.approx(NEAR_FRACTION * 1e4)  # content right at the cameras: extent rule
    assert near_plane(10.0, None) == pytest.approx(NEAR_FRACTION * 10.0)
    assert near_plane(0.0, None) == Camera.near
    assert near_plane(float("nan"), float("inf")) == Camera.near
