"""Camera paths for videos (`ctgs render RUN --path ...`): fitted to a capture's training cameras, or read from a
camera path file in nerfstudio's layout (`camera_path.json`, which `ctgs view` saves).

Fitted paths (`fit_path`), all in the model's frame, all looking with the scene's up (the mean of the cameras' up
directions) kept up:

- the cameras look inward from around the scene (a 360 capture: the mean of their unit viewing directions is shorter
  than OBJECT_CENTRIC_MAX): `orbit` is an ellipse about the point nearest every optical axis, in the plane through
  the cameras' mean height, its axes the cameras' own spread about that point (the second moments of their
  positions in that plane), its frames evenly spaced along it; `spiral` the same ellipse with the height going once up and down between the cameras'
  10th and 90th height percentiles. Both are closed loops: frame N would be frame 0.
- they look one way (a forward capture): `orbit` is a circle in the mean camera's image plane, `spiral` adds a
  motion along its axis (the spiral of LLFF and 2DGS's render.py), both looking at a focus point at the depth
  LLFF picks from the SfM points (FOCUS_WEIGHT), radii the 90th percentile of the cameras' offsets.
- `interpolate`, either kind: a Catmull-Rom spline through evenly picked training views in name order (a capture's
  order), its frames evenly spaced along the path; positions, viewing directions and up directions are interpolated
  alike, then made a rotation again.

A camera path file: nerfstudio's layout (`camera_path`: one entry per frame with `camera_to_world`, a 4x4 camera ->
world matrix flattened row by row, OpenGL camera axes: x right, y up, z backward; `fov`: vertical field of view in
degrees; `aspect`), with `render_width`, `render_height`, `fps` and `seconds`, and the keyframes it was made from.
Poses are in the model's frame (the scene's own unless it was recentred: ctgs.scene.loader.world_origin).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.render.camera import Camera
from ctgs.scene.conventions import BadMatrix, as_affine, opengl_c2w_from_viewmat, viewmat_from_opengl_c2w

PATH_KINDS = ("orbit", "spiral", "interpolate")
# |mean unit viewing direction| of the training cameras below which they look inward from around the scene: a full
# circle gives ~0, a half circle 2/pi = 0.64, a forward capture over 0.9.
OBJECT_CENTRIC_MAX = 0.8
# LLFF's focus depth: 1 / ((1 - w) / near + w / far) of the SfM points' depth range (its render_path_spiral)
FOCUS_WEIGHT = 0.75
# Points an orbit's ellipse is measured at, to space its frames evenly along it.
ELLIPSE_SAMPLES = 4096
# Frames per keyframe of `interpolate` (at least 2 keyframes, at most every training view).
FRAMES_PER_KEYFRAME = 15
CAMERA_PATH_FORMAT = "nerfstudio camera_path"


@dataclass
class Rig:
    """The training cameras a path is fitted to: centres, unit viewing directions (+z), up directions (-y), world."""

    centers: np.ndarray  # [C, 3]
    forward: np.ndarray  # [C, 3]
    up: np.ndarray  # [C, 3]

    @classmethod
    def of(cls, viewmats) -> "Rig":
        v = np.asarray([np.asarray(m, dtype=np.float64).reshape(4, 4) for m in viewmats])
        rot = v[:, :3, :3]  # world -> camera: rows are the camera axes in world coordinates
        centers = -np.einsum("cji,cj->ci", rot, v[:, :3, 3])
        return cls(centers=centers, forward=rot[:, 2], up=-rot[:, 1])

    def scene_up(self) -> np.ndarray:
        up = self.up.mean(0)
        n = np.linalg.norm(up)
        return up / n if n > 1e-9 else np.array([0.0, -1.0, 0.0])

    def object_centric(self) -> bool:
        return len(self.centers) > 2 and float(np.linalg.norm(self.forward.mean(0))) < OBJECT_CENTRIC_MAX

    def focus(self) -> np.ndarray:
        """The point nearest every optical axis (least squares); the mean centre when the axes are (near) parallel."""
        eye = np.eye(3)
        proj = eye[None] - self.forward[:, :, None] * self.forward[:, None, :]  # [C, 3, 3]
        a, b = proj.sum(0), np.einsum("cij,cj->i", proj, self.centers)
        if np.linalg.cond(a) > 1e6:
            return self.centers.mean(0)
        return np.linalg.solve(a, b)


def look_at(eye, target, up) -> np.ndarray:
    """[4, 4] float64 world -> camera (OpenCV axes) of a camera at `eye` looking at `target` with `up` kept up."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    return _viewmat(eye, target - eye, up)


def _viewmat(eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    z = forward / max(np.linalg.norm(forward), 1e-12)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight up or down: any right direction
        x = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])  # rows: camera axes
    v = np.eye(4)
    v[:3, :3] = rot
    v[:3, 3] = -rot @ eye
    return v


def fit_path(kind: str, viewmats, frames: int, points: np.ndarray | None = None) -> list[np.ndarray]:
    """`frames` world -> camera matrices [4, 4] float64 of the path `kind` (PATH_KINDS) fitted to the training cameras
    `viewmats` (world -> camera, in name order); `points` [P, 3]: the SfM points (a forward capture's focus depth)."""
    if kind not in PATH_KINDS:
        raise ValueError(f"path kind must be one of {PATH_KINDS}, got {kind!r}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rig = Rig.of(viewmats)
    if len(rig.centers) == 0:
        raise UserError("the scene has no training cameras to fit a camera path to")
    if kind == "interpolate":
        return _interpolated(rig, frames)
    if rig.object_centric():
        return _around(rig, frames, spiral=kind == "spiral")
    return _forward(rig, frames, points, spiral=kind == "spiral")


def _around(rig: Rig, frames: int, spiral: bool) -> list[np.ndarray]:
    up, focus = rig.scene_up(), rig.focus()
    d = rig.centers - focus
    h = d @ up
    flat = d - h[:, None] * up
    second = flat.T @ flat / len(flat)  # second moments about the focus, in the plane (up is a null direction)
    vals, vecs = np.linalg.eigh(second)
    e1, e2 = vecs[:, 2], vecs[:, 1]  # the two largest: the plane's axes
    e2 = np.cross(up, e1)  # a right-handed frame about up, whatever eigh's signs
    a, b = math.sqrt(2.0 * max(vals[2], 1e-12)), math.sqrt(2.0 * max(vals[1], 1e-12))  # a circle: its radius
    start = math.atan2(float(flat[0] @ e2) / b, float(flat[0] @ e1) / a)  # from the first training camera
    lo, hi = np.percentile(h, [10, 90]) if spiral else (h.mean(), h.mean())
    # frames evenly spaced along the ellipse (not in angle: the camera keeps one speed on an elongated one)
    t = start + np.linspace(0.0, 2 * math.pi, ELLIPSE_SAMPLES + 1)
    pts = np.stack([a * np.cos(t), b * np.sin(t)], 1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    out = []
    for k in range(frames):
        theta = float(np.interp(arc[-1] * k / frames, arc, t))
        height = 0.5 * (lo + hi) + 0.5 * (hi - lo) * math.sin(2 * math.pi * k / frames)
        eye = focus + a * math.cos(theta) * e1 + b * math.sin(theta) * e2 + height * up
        out.append(look_at(eye, focus, up))
    return out


def _forward(rig: Rig, frames: int, points: np.ndarray | None, spiral: bool) -> list[np.ndarray]:
    up = rig.scene_up()
    center = rig.centers.mean(0)
    fwd = rig.forward.mean(0)
    fwd /= np.linalg.norm(fwd)
    mean_pose = _viewmat(center, fwd, up)
    rot = mean_pose[:3, :3]  # rows: the mean camera's axes
    offsets = (rig.centers - center) @ rot.T  # in the mean camera's frame
    rx, ry, rz = (np.percentile(np.abs(offsets), 90, axis=0) + 1e-9).tolist()
    depth = _focus_depth(points, center, fwd) or 2.0 * max(rx, ry, 1e-3) / math.tan(math.radians(30))
    target = center + depth * fwd
    out = []
    for k in range(frames):
        t = 2 * math.pi * k / frames
        local = np.array([rx * math.cos(t), ry * math.sin(t), rz * math.sin(t) if spiral else 0.0])
        eye = center + local @ rot
        out.append(look_at(eye, target, up))
    return out


def _focus_depth(points: np.ndarray | None, center: np.ndarray, fwd: np.ndarray) -> float | None:
    if points is None or len(points) < 8:
        return None
    z = (np.asarray(points, dtype=np.float64) - center) @ fwd
    z = z[z > 0]
    if len(z) < 8:
        return None
    near, far = 0.9 * np.percentile(z, 10), 5.0 * np.percentile(z, 99)
    return float(1.0 / ((1.0 - FOCUS_WEIGHT) / near + FOCUS_WEIGHT / far))


def _interpolated(rig: Rig, frames: int) -> list[np.ndarray]:
    n = len(rig.centers)
    keys = max(2, min(n, frames // FRAMES_PER_KEYFRAME))
    if n == 1:
        return [_viewmat(rig.centers[0], rig.forward[0], rig.up[0])] * frames
    pick = np.unique(np.round(np.linspace(0, n - 1, keys)).astype(int))
    return spline_poses(rig.centers[pick], rig.forward[pick], rig.up[pick], frames)


def catmull_rom(p0, p1, p2, p3, u: float):
    """Uniform Catmull-Rom between p1 (u = 0) and p2 (u = 1)."""
    u2, u3 = u * u, u * u * u
    return 0.5 * (2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (3 * p1 - p0 - 3 * p2 + p3) * u3)


def spline_poses(centers: np.ndarray, forward: np.ndarray, up: np.ndarray, frames: int) -> list[np.ndarray]:
    """`frames` poses along Catmull-Rom splines through the keyframes (centres, viewing and up directions [K, 3]),
    evenly spaced by the length of the straight segments between keyframes (the first and last frames are the first
    and last keyframes). The viewer's path (static/camera_path.js) is the same spline."""
    k = len(centers)
    seg = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    if not seg.sum() > 1e-12:  # keyframes in one place (turning on the spot): space them by index
        seg = np.ones(k - 1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    out = []
    for f in range(frames):
        s = cum[-1] * (f / (frames - 1) if frames > 1 else 0.0)
        i = int(min(np.searchsorted(cum, s, side="right") - 1, k - 2))
        u = float((s - cum[i]) / seg[i]) if seg[i] > 0 else 0.0
        idx = [max(i - 1, 0), i, i + 1, min(i + 2, k - 1)]
        eye = catmull_rom(*centers[idx], u)
        fwd = catmull_rom(*forward[idx], u)
        upv = catmull_rom(*up[idx], u)
        out.append(_viewmat(eye, fwd, upv))
    return out


def path_cameras(viewmats, fov_y: float | list[float], width: int, height: int, near: float) -> list[Camera]:
    """Pinhole cameras (principal point at the image centre, square pixels) of `width` x `height` pixels along a path;
    fov_y: the vertical field of view in radians, one or one per pose."""
    fovs = fov_y if isinstance(fov_y, (list, tuple)) else [fov_y] * len(viewmats)
    cams = []
    for v, fov in zip(viewmats, fovs):
        f = 0.5 * height / math.tan(0.5 * fov)
        cams.append(Camera(fx=f, fy=f, cx=0.5 * width, cy=0.5 * height, width=int(width), height=int(height),
                           viewmat=torch.tensor(np.asarray(v, dtype=np.float64), dtype=torch.float32), near=near))
    return cams


def vertical_fov(camera: Camera) -> float:
    """Radians."""
    return 2.0 * math.atan(0.5 * camera.height / camera.fy)


# ---- camera path files (nerfstudio's layout) ------------------------------------------------------------------------
def camera_path_json(viewmats, fov_y: float, width: int, height: int, fps: float, *, keyframes=None) -> dict:
    """A camera path file's content: the frames `viewmats` (world -> camera) as `camera_path`, and `keyframes` (world
    -> camera matrices, default none) as its keyframes; fov_y in radians."""
    fov = math.degrees(fov_y)

    def entry(v):
        return [float(x) for x in opengl_c2w_from_viewmat(np.asarray(v, dtype=np.float64)).reshape(-1)]

    return {
        "camera_type": "perspective", "render_width": int(width), "render_height": int(height), "fps": float(fps),
        "seconds": len(viewmats) / float(fps), "is_cycle": False, "smoothness_value": 0.0, "default_fov": fov,
        "keyframes": [{"matrix": entry(v), "fov": fov, "aspect": width / height} for v in (keyframes or [])],
        "camera_path": [{"camera_to_world": entry(v), "fov": fov, "aspect": width / height} for v in viewmats],
    }


@dataclass
class CameraPathFile:
    viewmats: list  # [4, 4] float64 world -> camera per frame
    fov_y: list  # radians per frame
    width: int
    height: int
    fps: float


def read_camera_path(path: str) -> CameraPathFile:
    """A camera path file (nerfstudio's layout); UserError naming the file, the entry and the fix when it is not one."""
    fix = "save one from `ctgs view` (Camera path, Save) or use --path orbit|spiral|interpolate"
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        raise UserError(f"{path}: camera path file not found; {fix}") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise UserError(f"{path}: not a JSON camera path ({' '.join(str(exc).split())[:120]}); {fix}") from None

    def bad(what: str) -> UserError:
        return UserError(f"{path}: {what}; a {CAMERA_PATH_FORMAT} file needs camera_path entries with camera_to_world "
                         f"and fov, and render_width, render_height, fps; {fix}")

    if not isinstance(data, dict) or not isinstance(data.get("camera_path"), list) or not data["camera_path"]:
        raise bad("no camera_path entries")
    if data.get("camera_type", "perspective") != "perspective":
        raise bad(f"camera_type {data.get('camera_type')!r}: only perspective paths are rendered")
    size = []
    for key in ("render_width", "render_height"):
        v = data.get(key)
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 1 and float(v).is_integer()):
            raise bad(f"{key} is {v!r}, not a whole number of pixels >= 1")
        size.append(int(v))
    fps = data.get("fps")
    if not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and 0 < fps <= 1000):
        raise bad(f"fps is {fps!r}, not a number of frames per second in (0, 1000]")
    viewmats, fovs = [], []
    for i, entry in enumerate(data["camera_path"]):
        if not isinstance(entry, dict):
            raise bad(f"camera_path[{i}] is not an object")
        fov = entry.get("fov")
        if not (isinstance(fov, (int, float)) and not isinstance(fov, bool) and 0 < fov < 180):
            raise bad(f"camera_path[{i}].fov is {fov!r}, not a vertical field of view in degrees in (0, 180)")
        m = entry.get("camera_to_world")
        try:
            flat = np.asarray(m, dtype=np.float64).reshape(-1)
            if flat.size not in (12, 16):
                raise BadMatrix(f"has {flat.size} numbers, not 16 (a 4x4 matrix row by row) or 12")
            c2w = as_affine(flat.reshape(-1, 4))
            viewmats.append(viewmat_from_opengl_c2w(c2w))
        except BadMatrix as exc:
            raise bad(f"camera_path[{i}].camera_to_world {exc}") from None
        except (TypeError, ValueError):
            raise bad(f"camera_path[{i}].camera_to_world is not a matrix of numbers") from None
        fovs.append(math.radians(fov))
    return CameraPathFile(viewmats=viewmats, fov_y=fovs, width=size[0], height=size[1], fps=float(fps))

