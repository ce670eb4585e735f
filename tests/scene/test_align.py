"""Umeyama alignment and camera errors (benchmarks/measures/align.py) on synthetic cameras with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from measures.align import align_cameras, camera_poses, rotation_angle_deg, rotation_vectors, umeyama

# float64 round-off through an SVD and a few products, on coordinates of size ~10-1000: observed ~1e-13.
TIGHT = 1e-9


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))  # [3, 3], det +1


def axis_angle(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues: rotation by `degrees` about `axis` [3]."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def look_at_ring(num: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """num cameras evenly on a horizontal circle (z = 0) looking at the origin.

    Returns centres [C, 3] and camera-to-world rotations [C, 3, 3]."""
    angles = 2 * np.pi * np.arange(num) / num
    centers = radius * np.stack([np.cos(angles), np.sin(angles), np.zeros(num)], axis=1)
    forward = -centers / radius
    down = np.tile([0.0, 0.0, -1.0], (num, 1))
    right = np.cross(down, forward)
    return centers, np.stack([right, down, forward], axis=2)  # columns = camera x, y, z in world


def test_known_similarity_is_recovered_exactly():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3)) * 5.0
    R, s, t = random_rotation(rng), 0.037, np.array([120.0, -45.0, 8.0])
    dst = s * src @ R.T + t
    sim = umeyama(src, dst)
    assert sim.scale == pytest.approx(s, rel=TIGHT)
    assert np.allclose(sim.rotation, R, atol=TIGHT) and np.allclose(sim.translation, t, atol=TIGHT * 100)
    assert np.allclose(sim.apply(src), dst, atol=TIGHT * 100)
    scale, rotation, translation = sim  # tuple unpacking, as callers of the old sfm.umeyama did
    assert scale == sim.scale and rotation is sim.rotation and translation is sim.translation


def test_agrees_with_colmaps_estimator_on_noisy_points():
    """An independent implementation (COLMAP's Eigen-based Sim3 estimate) finds the same least-squares fit."""
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    dst = 3.0 * src @ random_rotation(rng).T + 1.0 + rng.normal(scale=0.05, size=(30, 3))
    ours, theirs = umeyama(src, dst), pycolmap.estimate_sim3d(src, dst)
    assert ours.scale == pytest.approx(theirs.scale, rel=1e-9)
    assert np.allclose(ours.rotation, theirs.rotation.matrix(), atol=1e-9)
    assert np.allclose(ours.translation, np.asarray(theirs.translation), atol=1e-9)


def test_mirrored_points_still_give_a_proper_rotation():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(10, 3))
    sim = umeyama(src, src * np.array([1.0, 1.0, -1.0]))  # a reflection: no rotation maps one onto the other
    assert np.linalg.det(sim.rotation) == pytest.approx(1.0)
    assert np.allclose(sim.rotation @ sim.rotation.T, np.eye(3), atol=TIGHT)


def test_perturbed_cameras_give_the_expected_errors():
    """Perturbations the similarity cannot absorb come back as predicted, in reference units, in any gauge.

    Reference: 8 cameras on a ring of radius RADIUS. Estimate: the reference in another gauge (scale 0.02,
    rotated, shifted), with each centre moved by EPS along +-z (alternating signs: zero mean and no net
    rotation, so the fitted rotation and translation are the true gauge's) and each orientation turned by
    ANGLE degrees about its own random axis (orientations are not used by the fit). The fitted scale is not
    quite the gauge's: least squares from the estimate onto the reference shrinks the estimate's extra
    spread, s = R^2 / (R^2 + EPS^2) (in reference units), so each centre error is
    |(s - 1) x + s d| = EPS R / sqrt(R^2 + EPS^2), just under EPS.
    """
    EPS, ANGLE, NUM, RADIUS = 0.25, 1.5, 8, 10.0
    rng = np.random.default_rng(3)
    ref_c, ref_r = look_at_ring(NUM, RADIUS)
    moved = ref_c + EPS * np.outer((-1.0) ** np.arange(NUM), [0.0, 0.0, 1.0])
    turned = np.stack([axis_angle(rng.normal(size=3), ANGLE) @ r for r in ref_r])
    gauge_r, gauge_s, gauge_t = random_rotation(rng), 0.02, np.array([3.0, -1.0, 7.0])  # reference -> estimate
    est_c = gauge_s * moved @ gauge_r.T + gauge_t
    est_r = gauge_r @ turned

    result = align_cameras(est_c, est_r, ref_c, ref_r)
    assert np.allclose(result.center_errors, EPS * RADIUS / np.hypot(RADIUS, EPS), rtol=1e-9)  # 0.24992
    assert np.allclose(result.rotation_errors_deg, ANGLE, rtol=1e-7)
    assert result.similarity.scale == pytest.approx(RADIUS ** 2 / (RADIUS ** 2 + EPS ** 2) / gauge_s, rel=1e-9)
    assert result.spread_radius == pytest.approx(RADIUS) and result.spread_diameter == pytest.approx(2 * RADIUS)

    exact = align_cameras(gauge_s * ref_c @ gauge_r.T + gauge_t, gauge_r @ ref_r, ref_c, ref_r)
    assert exact.center_errors.max() < TIGHT and exact.rotation_errors_deg.max() < 1e-6


def test_the_robust_fit_is_not_pulled_by_far_cameras_and_says_which_it_left_out():
    """Two of 40 cameras misplaced by a fifth of the spread (as a global mapper may place a pair): the least-squares
    fit shows every camera off; the robust fit recovers the gauge exactly from the other 38, reports the two at
    their true displacement and marks them as not fitted. On cameras with only small noise it is the plain fit."""
    rng = np.random.default_rng(5)
    ref_c, ref_r = look_at_ring(40, radius=10.0)
    ref_c = ref_c + np.outer(np.sin(np.arange(40)), [0.0, 0.0, 1.0])  # off one plane, so the fit is well posed
    gauge_r, gauge_s, gauge_t = random_rotation(rng), 0.3, np.array([1.0, 2.0, -4.0])
    moved = ref_c.copy()
    moved[[7, 8]] += np.array([[2.0, 0.5, 0.0], [1.5, 1.0, 0.5]])
    est_c, est_r = gauge_s * moved @ gauge_r.T + gauge_t, gauge_r @ ref_r

    plain = align_cameras(est_c, est_r, ref_c, ref_r)
    robust = align_cameras(est_c, est_r, ref_c, ref_r, robust=True)
    others = np.ones(40, dtype=bool)
    others[[7, 8]] = False
    assert plain.fitted.all() and np.median(plain.center_errors[others]) > 0.01
    assert (robust.fitted == others).all()
    assert robust.center_errors[others].max() < TIGHT and robust.similarity.scale == pytest.approx(1 / gauge_s)
    assert np.allclose(robust.center_errors[[7, 8]], np.linalg.norm(moved - ref_c, axis=1)[[7, 8]], rtol=1e-9)

    noisy = gauge_s * ref_c @ gauge_r.T + gauge_t + rng.normal(scale=0.003, size=est_c.shape)
    plain, robust = (align_cameras(noisy, est_r, ref_c, ref_r, robust=r) for r in (False, True))
    assert robust.fitted.all() and np.allclose(robust.center_errors, plain.center_errors)


def test_camera_poses_from_view_matrices():
    rng = np.random.default_rng(4)
    centers, cam_to_world = look_at_ring(5, radius=3.0)
    centers = centers + rng.normal(size=3)
    viewmats = np.tile(np.eye(4), (5, 1, 1))
    viewmats[:, :3, :3] = np.transpose(cam_to_world, (0, 2, 1))
    viewmats[:, :3, 3] = -np.einsum("cij,cj->ci", viewmats[:, :3, :3], centers)
    got_c, got_r = camera_poses(viewmats)
    assert np.allclose(got_c, centers, atol=TIGHT) and np.allclose(got_r, cam_to_world, atol=TIGHT)


def test_rotation_angle_is_accurate_from_tiny_to_half_turn():
    for degrees in (1e-7, 1e-3, 0.5, 90.0, 179.0, 180.0):
        got = rotation_angle_deg(axis_angle([1.0, 2.0, -0.5], degrees))
        assert got == pytest.approx(degrees, rel=1e-6, abs=1e-10)


def test_rotation_vectors_invert_rodrigues():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    for degrees in (0.0, 1e-7, 0.3, 45.0, 170.0):
        got = rotation_vectors(axis_angle(axis, degrees)[None])[0]
        assert np.allclose(got, np.radians(degrees) * axis, rtol=1e-7, atol=1e-15)


@pytest.mark.parametrize("src, dst, message", [
    (np.zeros((5, 2)), np.zeros((5, 2)), r"src must have shape \[N, 3\], got \[5, 2\]"),
    (np.ones((4, 3)), np.ones((5, 3)), r"same shape \[N, 3\], got \[4, 3\] and \[5, 3\]"),
    (np.eye(3)[:2], np.eye(3)[:2], r"at least 3 points"),
    (np.outer(np.arange(6.0), [1.0, 2.0, 3.0]), np.random.default_rng(0).normal(size=(6, 3)), r"collinear"),
    (np.full((4, 3), np.nan), np.ones((4, 3)), r"non-finite"),
])
def test_bad_input_names_the_argument_and_shape(src, dst, message):
    with pytest.raises(ValueError, match=message):
        umeyama(src, dst)
