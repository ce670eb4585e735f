"""Camera conventions of the scene layouts, converted here and nowhere else.

ctgs (as COLMAP and OpenCV): a world -> camera `viewmat`, camera axes x right, y down, z forward (ctgs.render.camera).
transforms.json (nerfstudio, instant-ngp, NeRF's Blender scenes): a camera -> world `transform_matrix`, camera axes
x right, y up, z backward (OpenGL). The two differ by the sign of the camera's y and z axes.

World frames: nerfstudio's `ns-process-data` turns COLMAP's world (y down for the first photo) so that z is up, and
writes what it applied as `applied_transform` ([3, 4], world -> world; cameras and `ply_file_path` points both went
through it). A scene is read back in its source's frame (the inverse of `applied_transform`), so a capture converted
to nerfstudio and read again has the cameras, points and trained models of its COLMAP scene. instant-ngp and
Blender files carry no such transform: their world is the file's.
"""

from __future__ import annotations

import numpy as np

# Camera axes: OpenGL (x right, y up, z backward) <-> OpenCV (x right, y down, z forward); its own inverse.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
# What ns-process-data applies to a COLMAP world: (x, y, z) -> (x, z, -y) (nerfstudio's colmap_utils.colmap_to_json).
NERFSTUDIO_APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
# A rotation read from a file may be off orthonormal by float rounding (6-8 printed digits); beyond this it is not
# a rotation (a scaled or sheared matrix), which no pinhole camera has.
ROTATION_TOLERANCE = 1e-3


class BadMatrix(ValueError):
    """Why a matrix of a file is no camera pose or world transform (the reader names the file and the key)."""


def as_affine(matrix, rows: tuple[int, ...] = (4, 3)) -> np.ndarray:
    """[4, 4] float64 from a [4, 4] or [3, 4] nested list; BadMatrix when it has another shape or a non-finite
    entry."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise BadMatrix("is not a matrix of numbers") from None
    if m.ndim != 2 or m.shape[1] != 4 or m.shape[0] not in rows:
        raise BadMatrix(f"has shape {list(m.shape)}, not " + " or ".join(f"[{r}, 4]" for r in rows))
    if not np.isfinite(m).all():
        raise BadMatrix("holds a non-finite number (NaN or infinity)")
    out = np.eye(4)
    out[:m.shape[0]] = m
    if m.shape[0] == 4 and not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise BadMatrix(f"has bottom row {m[3].tolist()}, not [0, 0, 0, 1] (a projective matrix, not a pose)")
    return out


def rigid(matrix: np.ndarray) -> np.ndarray:
    """[4, 4] with its rotation block made exactly orthonormal (the nearest rotation); BadMatrix when the block is
    not invertible, a reflection, or scaled or sheared beyond float rounding."""
    r = matrix[:3, :3]
    det = float(np.linalg.det(r))
    if not abs(det) > 1e-9:
        raise BadMatrix(f"is not invertible (its rotation block has determinant {det:.3g})")
    if det < 0:
        raise BadMatrix("mirrors the camera (its rotation block has a negative determinant)")
    if np.abs(r.T @ r - np.eye(3)).max() > ROTATION_TOLERANCE:
        raise BadMatrix("is not a rigid transform (its rotation block is scaled or sheared)")
    u, _, vt = np.linalg.svd(r)
    out = matrix.copy()
    out[:3, :3] = u @ vt
    return out


def viewmat_from_opengl_c2w(c2w: np.ndarray) -> np.ndarray:
    """ctgs's world -> camera [4, 4] from a transforms.json camera -> world matrix [4, 4] (OpenGL camera axes)."""
    m = rigid(c2w) @ OPENGL_TO_OPENCV  # camera -> world with OpenCV camera axes
    viewmat = np.eye(4)
    viewmat[:3, :3] = m[:3, :3].T
    viewmat[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return viewmat


def opengl_c2w_from_viewmat(viewmat: np.ndarray) -> np.ndarray:
    """The transforms.json camera -> world matrix [4, 4] (OpenGL camera axes) of a world -> camera `viewmat`."""
    v = np.asarray(viewmat, dtype=np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = v[:3, :3].T
    c2w[:3, 3] = -v[:3, :3].T @ v[:3, 3]
    return c2w @ OPENGL_TO_OPENCV


def source_world(applied: np.ndarray | None) -> np.ndarray:
    """[4, 4] taking the file's world to its source's (the inverse of `applied_transform`; identity without one)."""
    if applied is None:
        return np.eye(4)
    return np.linalg.inv(rigid(applied))


def transform_points(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """points [P, 3] through the affine [4, 4] `m`."""
    p = np.asarray(points, dtype=np.float64)
    return p @ m[:3, :3].T + m[:3, 3]
