"""Reading COLMAP sparse models (binary or text) through pycolmap into plain numpy data.

Only the undistorted pinhole models are accepted for training (PINHOLE, SIMPLE_PINHOLE): the renderer
has no distortion. Everything else gets a UserError telling the user to run `ctgs sfm`, which undistorts.
"""

from __future__ import annotations

import math
import os
import signal
import struct
import threading
from dataclasses import dataclass

import numpy as np

from ctgs.errors import UserError

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_MODEL_FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class Intrinsics:
    """A COLMAP camera at its calibration size (pixels)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class ModelImage:
    name: str
    camera_id: int
    viewmat: np.ndarray  # [4, 4] float64 world -> camera (COLMAP cam_from_world)


@dataclass
class ColmapModel:
    path: str  # folder holding cameras/images/points3D (.bin or .txt)
    cameras: dict[int, Intrinsics]
    images: list[ModelImage]  # registered images only, sorted by name
    num_unregistered: int
    points: np.ndarray  # [P, 3] float64 world units
    colors: np.ndarray  # [P, 3] uint8
    point_errors: np.ndarray  # [P] mean reprojection error, pixels (-1 where unknown)


def find_model_dir(scene_dir: str) -> str:
    """scene_dir/sparse/0 (COLMAP layout), or scene_dir/sparse, or scene_dir itself if it holds a model."""
    for candidate in (os.path.join(scene_dir, "sparse", "0"), os.path.join(scene_dir, "sparse"), scene_dir):
        if _has_model(candidate):
            return candidate
    raise UserError(
        f"{os.path.join(scene_dir, 'sparse', '0')}: no COLMAP model (cameras/images/points3D .bin or .txt); "
        f"run `ctgs sfm IMAGES_DIR -o {scene_dir}` first"
    )


def _has_model(folder: str) -> bool:
    return any(
        all(os.path.isfile(os.path.join(folder, f"{name}{ext}")) for name in _MODEL_FILES) for ext in (".bin", ".txt")
    )


def model_file(model_dir: str, name: str) -> str:
    binary = os.path.join(model_dir, f"{name}.bin")
    return binary if os.path.isfile(binary) else os.path.join(model_dir, f"{name}.txt")


def import_pycolmap():
    """`import pycolmap`, keeping Python's SIGTERM handler.

    Importing pycolmap installs glog's failure-signal handler, which on SIGTERM (`kill`, `timeout`, a cluster's
    time limit) prints a native stack trace and ends the process before Python can clean up (a half-made run
    folder stays). SIGTERM gets back the handler Python had before the import (the CLI's: stop like Ctrl-C);
    the crash signals (SIGSEGV, SIGABRT, ...) keep glog's trace."""
    before = signal.getsignal(signal.SIGTERM)
    # here, between saving and putting back the SIGTERM handler its import replaces
    import pycolmap

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, signal.SIG_DFL if before is None else before)
    return pycolmap


# Parameters per COLMAP camera model id (colmap/sensor/models.h), for walking cameras.bin.
_CAMERA_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 6}
_CAMERA_MODEL_NAMES = {0: "SIMPLE_PINHOLE", 1: "PINHOLE"}


class _Corrupt(Exception):
    pass


class _Reader:
    """Bounds-checked little-endian reads over a file's bytes."""

    def __init__(self, data: bytes):
        self.data, self.at = data, 0

    def take(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise _Corrupt(f"ends at byte {len(self.data)} inside a record (truncated)")
        values = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return values

    def skip(self, count: int, size: int) -> None:
        if count < 0 or self.at + count * size > len(self.data):
            raise _Corrupt(f"a record claims {count} entries of {size} bytes past the end of the file "
                           f"({len(self.data)} bytes): truncated or not a COLMAP file")
        self.at += count * size

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.take("<Q")
        if n * min_record > len(self.data) - self.at:
            raise _Corrupt(f"claims {n} {what}, more than its {len(self.data)} bytes can hold")
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise _Corrupt("an image name runs past the end of the file (truncated)")
        raw = self.data[self.at:end]
        self.at = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise _Corrupt("an image name is not UTF-8 text") from None

    def done(self) -> None:
        if self.at != len(self.data):
            raise _Corrupt(f"{len(self.data) - self.at} bytes after the last record")


def _check_cameras(r: _Reader) -> None:
    for _ in range(r.count(24, "cameras")):
        _cid, model, width, height = r.take("<iiQQ")
        if model not in _CAMERA_PARAMS:
            raise _Corrupt(f"camera model id {model} is not a COLMAP camera model")
        params = r.take(f"<{_CAMERA_PARAMS[model]}d")
        if not (1 <= width < 2**20 and 1 <= height < 2**20):
            raise _Corrupt(f"camera size {width}x{height}")
        if model in _CAMERA_MODEL_NAMES:
            _check_pinhole(_CAMERA_MODEL_NAMES[model], width, height, params)


def _check_pinhole(model: str, width: int, height: int, params) -> None:
    fx, fy, cx, cy = (params[0], params[0], params[1], params[2]) if model == "SIMPLE_PINHOLE" else params[:4]
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise _Corrupt(f"{model} camera with focal length ({fx:g}, {fy:g}): not finite and positive")
    # a principal point far outside the image is a cut or overwritten file, not a camera
    if not (-width <= cx <= 2 * width and -height <= cy <= 2 * height):
        raise _Corrupt(f"{model} camera {width}x{height} with principal point ({cx:g}, {cy:g}) far outside it")


def _check_images(r: _Reader) -> None:
    for _ in range(r.count(73, "images")):
        r.take("<I7dI")
        r.name()
        (points2d,) = r.take("<Q")
        r.skip(points2d, 24)


def _check_points(r: _Reader) -> None:
    for _ in range(r.count(51, "points")):
        r.skip(1, 43)
        (track,) = r.take("<Q")
        r.skip(track, 8)


def _check_rigs(r: _Reader) -> None:
    # rigs.bin and frames.bin (COLMAP 3.12+): only their counts are checked against the file size, which keeps a
    # corrupt count from making pycolmap allocate without bound; pycolmap reads the rest
    r.count(8, "rigs")


def _check_frames(r: _Reader) -> None:
    r.count(68, "frames")


_BINARY_CHECKS = (("cameras", _check_cameras, True), ("images", _check_images, True),
                  ("points3D", _check_points, True), ("rigs", _check_rigs, False), ("frames", _check_frames, False))


def check_binary_model(model_dir: str) -> None:
    """UserError naming the file when a binary COLMAP model file is cut short or is not one: its records are walked
    (no values decoded but the cameras'), so that pycolmap never sees a count it would allocate without bound (a
    points3D.bin of random bytes took 12 GB) and a cut cameras.bin (focal length 0) is caught here, not in training."""
    for name, check, whole in _BINARY_CHECKS:
        path = os.path.join(model_dir, f"{name}.bin")
        if not os.path.isfile(path):
            continue
        with open(path, "rb") as f:
            data = f.read()
        r = _Reader(data)
        try:
            check(r)
            if whole:
                r.done()
        except (_Corrupt, struct.error) as exc:
            raise UserError(f"{path}: corrupt COLMAP {name} file ({exc}); restore it from a backup or run "
                            f"`ctgs sfm` again") from None


def _floats(fields: list[str], what: str) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError:
        raise _Corrupt(f"{what}: {' '.join(fields)[:60]!r} is not a list of numbers") from None


def _ints(fields: list[str], what: str) -> list[int]:
    try:
        return [int(f) for f in fields]
    except ValueError:
        raise _Corrupt(f"{what}: {' '.join(fields)[:60]!r} is not a list of whole numbers") from None


def _check_cameras_text(lines: list[str]) -> None:
    for n, line in lines:
        f = line.split()
        if len(f) < 5:
            raise _Corrupt(f"line {n} has {len(f)} fields, a camera needs id, model, width, height and parameters")
        _ints(f[:1] + f[2:4], f"line {n}")
        params = _floats(f[4:], f"line {n}")
        width, height = int(f[2]), int(f[3])
        if not (1 <= width < 2**20 and 1 <= height < 2**20):
            raise _Corrupt(f"line {n}: camera size {width}x{height}")
        if f[1] in _CAMERA_MODEL_NAMES.values():
            if len(params) != _CAMERA_PARAMS[{v: k for k, v in _CAMERA_MODEL_NAMES.items()}[f[1]]]:
                raise _Corrupt(f"line {n}: {f[1]} with {len(params)} parameters")
            _check_pinhole(f[1], width, height, params)


def _check_images_text(raw_lines: list[str]) -> None:
    # COLMAP's own reading: a data line, then the next line whatever it holds (the image's 2D points, maybe none)
    i = 0
    while i < len(raw_lines):
        line = raw_lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        f = line.split()
        if len(f) < 10:
            raise _Corrupt(f"line {i} has {len(f)} fields, an image needs id, pose (7 numbers), camera id and name")
        _ints([f[0], f[8]], f"line {i}")
        _floats(f[1:8], f"line {i}")
        points = raw_lines[i].split() if i < len(raw_lines) else []
        if len(points) % 3:
            raise _Corrupt(f"line {i + 1}: {len(points)} numbers, not (x, y, point id) triples")
        i += 1


def _check_points_text(lines: list[str]) -> None:
    for n, line in lines:
        f = line.split()
        if len(f) < 8 or (len(f) - 8) % 2:
            raise _Corrupt(f"line {n} has {len(f)} fields, a point needs id, x y z, r g b, error and "
                           "(image id, point index) pairs")
        _ints(f[:1] + f[4:7], f"line {n}")
        _floats(f[1:4] + f[7:8], f"line {n}")


_TEXT_CHECKS = (("cameras", _check_cameras_text), ("images", None), ("points3D", _check_points_text))


def check_text_model(model_dir: str) -> None:
    """UserError naming the file when a text COLMAP model file (read where no .bin file is) is not one: each
    line's fields are counted and parsed, as COLMAP reads them. pycolmap's own message names only the folder."""
    for name, check in _TEXT_CHECKS:
        if os.path.isfile(os.path.join(model_dir, f"{name}.bin")):
            continue
        path = os.path.join(model_dir, f"{name}.txt")
        if not os.path.isfile(path):
            continue
        try:
            with open(path, "rb") as f:
                text = f.read().decode("utf-8")
        except UnicodeDecodeError:
            raise UserError(f"{path}: corrupt COLMAP {name} file (not text); restore it from a backup or run "
                            "`ctgs sfm` again") from None
        raw = text.splitlines()
        try:
            if check is None:
                _check_images_text(raw)
            else:
                check([(n, line.strip()) for n, line in enumerate(raw, 1)
                       if line.strip() and not line.lstrip().startswith("#")])
        except _Corrupt as exc:
            raise UserError(f"{path}: corrupt COLMAP {name} file ({exc}); restore it from a backup or run "
                            f"`ctgs sfm` again") from None
    # COLMAP 3.12+ text models: every image belongs to a frame of a rig; none at all is a cut or emptied file. COLMAP
    # writes its header comments into points3D.txt even without points: a file of no bytes was emptied (a model
    # without points, written whole, starts training from random points: ctgs.scene.loader)
    if _has_records(os.path.join(model_dir, "images.txt")):
        points = os.path.join(model_dir, "points3D.txt")
        if not os.path.isfile(os.path.join(model_dir, "points3D.bin")) and os.path.isfile(points) \
                and os.path.getsize(points) == 0:
            raise UserError(f"{points}: corrupt COLMAP points3D file (empty, but images.txt holds images); restore "
                            "it from a backup or run `ctgs sfm` again")
        for name in ("rigs", "frames"):
            path = os.path.join(model_dir, f"{name}.txt")
            if not os.path.isfile(os.path.join(model_dir, f"{name}.bin")) and os.path.isfile(path) \
                    and not _has_records(path):
                raise UserError(f"{path}: corrupt COLMAP {name} file (no {name}, but images.txt holds images); "
                                "restore it from a backup or run `ctgs sfm` again")


def _has_records(path: str) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return any(line.strip() and not line.lstrip().startswith("#") for line in f)
    except OSError:
        return False


def _check_model_values(model_dir: str, cameras: dict, images: list, points: np.ndarray) -> None:
    """Values every reader of a model relies on: finite positive focal lengths, finite poses and points."""
    for camera_id, c in cameras.items():
        try:
            _check_pinhole(c.model, c.width, c.height, (c.fx, c.fy, c.cx, c.cy))
        except _Corrupt as exc:
            raise UserError(f"{model_file(model_dir, 'cameras')}: camera {camera_id}: {exc}; fix the file or run "
                            "`ctgs sfm` again") from None
    for im in images:
        if im.camera_id not in cameras:
            raise UserError(f"{model_file(model_dir, 'images')}: image {im.name} refers to camera {im.camera_id}, "
                            f"which {model_file(model_dir, 'cameras')} does not hold; run `ctgs sfm` again")
        if not np.isfinite(im.viewmat).all():
            raise UserError(f"{model_file(model_dir, 'images')}: image {im.name} has a non-finite pose; fix the file "
                            "or run `ctgs sfm` again")
    if points.size and not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(1)).sum())
        raise UserError(f"{model_file(model_dir, 'points3D')}: {bad} points with non-finite coordinates; fix the file "
                        "or run `ctgs sfm` again")


def _blamed_file(model_dir: str, detail: str) -> str:
    """The model file a pycolmap error message points at (its checks name records, not files), else the folder."""
    d = detail.lower()
    for name, words in (("frames", ("frame", "rig_from_world")), ("cameras", ("camera",)), ("rigs", ("rig",)),
                        ("images", ("image",)), ("points3D", ("point3d",))):
        if any(w in d for w in words):
            path = model_file(model_dir, name)
            if os.path.isfile(path):
                return path
    return model_dir


def read_colmap_model(model_dir: str, *, require_pinhole: bool = True) -> ColmapModel:
    """Read a COLMAP model folder. Raises UserError naming the file on unreadable or corrupt files (cut short,
    focal lengths not finite and positive, non-finite poses or points) or non-pinhole cameras."""
    check_binary_model(model_dir)
    check_text_model(model_dir)
    pycolmap = import_pycolmap()  # heavy import, only where needed

    try:
        rec = pycolmap.Reconstruction(model_dir)
    except Exception as exc:  # pycolmap raises plain ValueError/RuntimeError on corrupt files
        detail = " ".join(str(exc).split())[:200]
        where = _blamed_file(model_dir, detail)
        raise UserError(
            f"{where}: cannot read the COLMAP model ({detail}); restore the file from a backup or run `ctgs sfm` again"
        ) from None

    cameras: dict[int, Intrinsics] = {}
    for camera_id, cam in rec.cameras.items():
        model = cam.model.name
        if model not in PINHOLE_MODELS:
            if require_pinhole:
                raise UserError(
                    f"{model_file(model_dir, 'cameras')}: camera {camera_id} uses the {model} model, but training "
                    f"needs undistorted PINHOLE/SIMPLE_PINHOLE cameras; run `ctgs sfm` (it undistorts the images)"
                )
            continue
        p = [float(v) for v in cam.params]
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if model == "SIMPLE_PINHOLE" else (p[0], p[1], p[2], p[3])
        cameras[int(camera_id)] = Intrinsics(model, int(cam.width), int(cam.height), fx, fy, cx, cy)

    images: list[ModelImage] = []
    unregistered = 0
    for image in rec.images.values():
        if not image.has_pose:
            unregistered += 1
            continue
        viewmat = np.eye(4)
        viewmat[:3, :] = image.cam_from_world().matrix()  # [3, 4] = [R | t]
        images.append(ModelImage(image.name, int(image.camera_id), viewmat))
    images.sort(key=lambda im: im.name)

    point_ids = sorted(rec.points3D.keys())
    points = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
    errors = np.array([rec.points3D[i].error for i in point_ids], dtype=np.float64).reshape(-1)
    _check_model_values(model_dir, cameras, images if require_pinhole else [], points)
    return ColmapModel(model_dir, cameras, images, unregistered, points, colors, errors)
