"""Comparing reconstructed cameras with reference cameras, up to a similarity.

Structure from motion fixes the world only up to a similarity (where the origin is, which way is up, and how
large one unit is: the gauge). So estimated cameras are compared with ground truth after the least-squares
similarity that maps the estimated camera centres onto the reference centres (Umeyama 1991, with scale).
Errors are then in the reference's units. numpy only: `benchmarks/sfm_accuracy.py` and the SfM tests use it.

Conventions: a camera is its centre C [3] (world) and its camera-to-world rotation [3, 3] (columns = camera
axes x right, y down, z forward, in world coordinates), COLMAP's convention and the Strecha ground truth's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

# Below this ratio of the second to the first singular value of the centred source points, the points lie
# (nearly) on a line: the rotation about that line is undetermined, and Umeyama's answer would be arbitrary.
# Real camera paths are far above it (herzjesu25: 0.33).
MIN_SPREAD_RATIO = 1e-9


class Similarity(NamedTuple):
    """x -> scale * rotation @ x + translation, from the source frame into the target frame.

    A NamedTuple, so `s, R, t = umeyama(src, dst)` also works."""

    scale: float
    rotation: np.ndarray  # [3, 3], det +1
    translation: np.ndarray  # [3], target units

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points [N, 3] (source frame) -> [N, 3] (target frame)."""
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation


def _check_points(name: str, points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape [N, 3], got {list(points.shape)}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} [N, 3] holds non-finite values (NaN or inf)")
    return points


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The similarity minimising sum_i |s R src_i + t - dst_i|^2 (Umeyama 1991, with scale).

    src, dst: [N, 3], row i of one matched to row i of the other, N >= 3 and src not collinear (else
    ValueError). R is a proper rotation (det +1) even when the best orthogonal fit would be a reflection.
    """
    src, dst = _check_points("src", src), _check_points("dst", dst)
    if src.shape != dst.shape:
        raise ValueError(f"src and dst must have the same shape [N, 3], got {list(src.shape)} and {list(dst.shape)}")
    if len(src) < 3:
        raise ValueError(f"src and dst need at least 3 points for a similarity, got shape {list(src.shape)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d  # [N, 3] each
    spread = np.linalg.svd(xs, compute_uv=False)  # [3], descending
    if spread[1] <= MIN_SPREAD_RATIO * spread[0]:
        raise ValueError(f"src [{len(src)}, 3] points are collinear or identical: a similarity is undetermined")
    cov = xd.T @ xs / len(src)  # [3, 3] cross-covariance, target x source
    U, S, Vt = np.linalg.svd(cov)
    D = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # the best orthogonal map is a reflection: flip the weakest axis
        D[2] = -1.0
    R = (U * D) @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float((S * D).sum() / var_s)
    return Similarity(s, R, mu_d - s * R @ mu_s)


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Rotation angle in degrees of each rotation matrix, [..., 3, 3] -> [...].

    Uses |R - I|_F = 2 sqrt(2) sin(angle / 2): accurate for small angles, where acos((trace R - 1) / 2)
    keeps only half the digits (1e-8 rad resolution), which matters for sub-millidegree errors.
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    if rotations.shape[-2:] != (3, 3):
        raise ValueError(f"rotations must have shape [..., 3, 3], got {list(rotations.shape)}")
    chord = np.linalg.norm(rotations - np.eye(3), axis=(-2, -1)) / np.sqrt(8.0)
    return np.degrees(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0)))


def rotation_vectors(rotations: np.ndarray) -> np.ndarray:
    """Axis * angle (radians) of each rotation matrix, [..., 3, 3] -> [..., 3] (the log map).

    Accurate below ~179 degrees; at a half turn the axis sign is undetermined (sin(angle) -> 0).
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    if rotations.shape[-2:] != (3, 3):
        raise ValueError(f"rotations must have shape [..., 3, 3], got {list(rotations.shape)}")
    skew = np.stack([rotations[..., 2, 1] - rotations[..., 1, 2], rotations[..., 0, 2] - rotations[..., 2, 0],
                     rotations[..., 1, 0] - rotations[..., 0, 1]], axis=-1) / 2  # [..., 3] = sin(angle) * axis
    angle = np.radians(rotation_angle_deg(rotations))[..., None]  # [..., 1]
    sin = np.sin(angle)
    return skew * np.where(sin > 1e-12, angle / np.where(sin > 1e-12, sin, 1.0), 1.0)


def camera_poses(viewmats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera matrices [C, 4, 4] (or [C, 3, 4]) -> centres [C, 3] and camera-to-world rotations [C, 3, 3]."""
    viewmats = np.asarray(viewmats, dtype=np.float64)
    if viewmats.ndim != 3 or viewmats.shape[1] not in (3, 4) or viewmats.shape[2] != 4:
        raise ValueError(f"viewmats must have shape [C, 4, 4] or [C, 3, 4], got {list(viewmats.shape)}")
    cam_to_world = np.transpose(viewmats[:, :3, :3], (0, 2, 1))  # [C, 3, 3]
    centers = -np.einsum("cij,cj->ci", cam_to_world, viewmats[:, :3, 3])  # [C, 3]: C = -R^T t
    return centers, cam_to_world


@dataclass(frozen=True)
class CameraAlignment:
    """Estimated cameras mapped into the reference frame, and their errors there (reference units)."""

    similarity: Similarity  # estimated world -> reference world
    center_errors: np.ndarray  # [C] |aligned estimated centre - reference centre|, reference units
    rotation_errors_deg: np.ndarray  # [C] angle between aligned estimated and reference orientation, degrees
    spread_radius: float  # max distance of a reference centre from the reference centroid, reference units
    spread_diameter: float  # max distance between two reference centres, reference units
    fitted: np.ndarray  # [C] bool: the cameras the similarity was fitted on (all of them unless robust)


# The robust fit: a camera whose centre error exceeds this many times the median error (and OUTLIER_FLOOR of the
# spread radius) is left out of the next fit; the fit is repeated until the set stops changing.
OUTLIER_FACTOR = 5.0
OUTLIER_FLOOR = 0.005
ROBUST_ROUNDS = 20


def align_cameras(est_centers: np.ndarray, est_cam_to_world: np.ndarray, ref_centers: np.ndarray,
                  ref_cam_to_world: np.ndarray, robust: bool = False) -> CameraAlignment:
    """Fit the similarity on the centres only (Umeyama), then measure centres and orientations.

    est_centers, ref_centers: [C, 3]; est_cam_to_world, ref_cam_to_world: [C, 3, 3]; row i is one camera
    in both. Orientations do not enter the fit, so the rotation errors are an independent check of it.

    robust: a least-squares fit lets one far-off camera pull the similarity, so that every other camera shows an
    error it does not have (playroom225: two cameras 16-23% off raised the median of the others from 0.09% to
    0.30%). With robust=True the fit is repeated on the cameras within OUTLIER_FACTOR times the median error (or
    OUTLIER_FLOOR of the spread radius, whichever is larger) until that set stops changing; every camera's error
    is still reported, measured with that fit, and `fitted` says which cameras it rests on.
    """
    est_centers, ref_centers = _check_points("est_centers", est_centers), _check_points("ref_centers", ref_centers)
    est_r, ref_r = np.asarray(est_cam_to_world, np.float64), np.asarray(ref_cam_to_world, np.float64)
    for name, rot, centers in (("est_cam_to_world", est_r, est_centers), ("ref_cam_to_world", ref_r, ref_centers)):
        if rot.shape != (len(centers), 3, 3):
            raise ValueError(f"{name} must have shape [C, 3, 3] with C = {len(centers)}, got {list(rot.shape)}")
    offsets = ref_centers - ref_centers.mean(0)
    radius = float(np.linalg.norm(offsets, axis=1).max())
    fitted = np.ones(len(est_centers), dtype=bool)
    sim = umeyama(est_centers, ref_centers)
    center_errors = np.linalg.norm(sim.apply(est_centers) - ref_centers, axis=1)  # [C]
    for _ in range(ROBUST_ROUNDS if robust else 0):
        keep = center_errors <= max(OUTLIER_FACTOR * float(np.median(center_errors)), OUTLIER_FLOOR * radius)
        if (keep == fitted).all() or keep.sum() < max(3, len(keep) // 2):
            break
        fitted = keep
        sim = umeyama(est_centers[fitted], ref_centers[fitted])
        center_errors = np.linalg.norm(sim.apply(est_centers) - ref_centers, axis=1)
    aligned_r = sim.rotation @ est_r  # [C, 3, 3]: camera axes in the reference world
    rotation_errors = rotation_angle_deg(np.transpose(ref_r, (0, 2, 1)) @ aligned_r)  # [C]
    pairwise = np.linalg.norm(ref_centers[:, None, :] - ref_centers[None, :, :], axis=-1)  # [C, C]
    return CameraAlignment(sim, center_errors, rotation_errors, radius, float(pairwise.max()), fitted)
