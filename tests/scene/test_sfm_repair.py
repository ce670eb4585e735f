"""The global mapper's repair: which photos are taken out and registered again (ctgs.scene.sfm.worker)."""

from __future__ import annotations

from collections import Counter

import numpy as np

from ctgs.scene.sfm.worker import FAR_FROM_PARTNERS, far_from_partners


def _ring(n: int = 40, seed: int = 0) -> tuple[dict, dict]:
    """Cameras on a circle of radius 5, each sharing points with its four nearest (more with the closer two)."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    centres = {i: np.array([5 * np.cos(a), 5 * np.sin(a), rng.normal(0, 0.05)]) for i, a in enumerate(angles)}
    shared = {i: Counter({(i + 1) % n: 300, (i - 1) % n: 300, (i + 2) % n: 120, (i - 2) % n: 120}) for i in range(n)}
    return centres, shared


def test_a_photo_far_from_the_photos_it_shares_points_with_is_flagged():
    centres, shared = _ring()
    assert far_from_partners(centres, shared) == []  # a healthy ring: nothing to repair
    spacing = np.linalg.norm(centres[0] - centres[1])
    centres[7] = centres[7] + np.array([0.0, 0.0, 3 * FAR_FROM_PARTNERS * spacing])  # flung off the ring
    centres[20] = centres[20] + np.array([0.5 * spacing, 0.0, 0.0])  # a little off: kept
    assert far_from_partners(centres, shared) == [7]


def test_photos_without_partners_or_pose_are_left_to_the_other_checks():
    centres, shared = _ring(10)
    shared[3] = Counter()  # shares no point: the points-per-photo check handles it
    del shared[4]  # nor this one (absent from the model's tracks)
    del centres[5]  # no pose
    assert far_from_partners(centres, shared) == []
    assert far_from_partners({}, {}) == []
