"""transforms.json scenes: nerfstudio's and instant-ngp's dialects, and NeRF's Blender synthetic layout.

One reader takes both dialects (they share their keys): intrinsics at the top level or per frame (`fl_x fl_y cx cy
w h`, or `camera_angle_x` / `camera_angle_y` in radians), OpenCV distortion `k1 k2 k3 p1 p2` (undistorted on
reading, ctgs.scene.photos), `camera_model` (PINHOLE, SIMPLE_PINHOLE or OPENCV), nerfstudio's `applied_transform`,
`ply_file_path` (initial points), `mask_path` per frame, `train_filenames` / `test_filenames` (nerfstudio's split),
instant-ngp's `aabb_scale` with its `scale` and `offset` (the box random initial points fill). The Blender layout is
`transforms_train.json` + `transforms_test.json` (+ `transforms_val.json`, unused), each frame's `file_path` without
its extension; its own split is kept. Camera conventions: ctgs.scene.conventions.

A scene folder holding a COLMAP model (sparse/0) is read as COLMAP even when it also holds a transforms.json.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from ctgs.errors import UserError
from ctgs.io.images import IMAGE_EXTENSIONS
from ctgs.scene import conventions
from ctgs.scene.colmap import find_model_dir
from ctgs.scene.photos import Distortion
from ctgs.scene.ply_points import read_points_ply

TRANSFORMS = "transforms.json"
BLENDER_SPLITS = (("train", "transforms_train.json"), ("test", "transforms_test.json"))
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
PINHOLE_CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
# instant-ngp's defaults for the transform from the file's world into its unit cube (nerf_matrix_to_ngp).
NGP_SCALE = 0.33
NGP_OFFSET = [0.5, 0.5, 0.5]


def scene_layout(scene_dir: str) -> str:
    """"colmap", "transforms" (transforms.json) or "blender" (transforms_train.json): how load_scene reads the folder;
    "colmap" also when it holds neither (the COLMAP reader's error then says what is missing)."""
    try:
        find_model_dir(scene_dir)
        return "colmap"
    except UserError:
        pass
    if os.path.isfile(os.path.join(scene_dir, TRANSFORMS)):
        return "transforms"
    if os.path.isfile(os.path.join(scene_dir, BLENDER_SPLITS[0][1])):
        return "blender"
    return "colmap"


@dataclass
class Intrinsics:
    """A frame's camera as its file gives it (pixels, radians); resolved for the image read by `pinhole`."""

    values: dict  # a subset of INTRINSIC_KEYS
    distortion: tuple | None  # DISTORTION_KEYS' values, None when all are zero
    shared: bool  # from the file's top level (one camera for every frame)
    where: str  # "FILE: frames[i]" for messages

    def calibration_size(self, full: tuple[int, int]) -> tuple[int, int]:
        """(w, h) the intrinsics are given at: the file's, else the size of the image file the frame names."""
        return int(self.values.get("w") or full[0]), int(self.values.get("h") or full[1])

    def pinhole(self, width: int, height: int, full: tuple[int, int]) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) for an image of this size (before undistortion), a level of the frame's image file of size
        `full`: the calibration rescaled to it."""
        cw, ch = self.calibration_size(full)
        v = self.values
        fx = v["fl_x"] if "fl_x" in v else 0.5 * cw / math.tan(0.5 * v["camera_angle_x"])
        fy = v.get("fl_y") or (0.5 * ch / math.tan(0.5 * v["camera_angle_y"]) if "camera_angle_y" in v else fx)
        cx, cy = v.get("cx", cw / 2.0), v.get("cy", ch / 2.0)
        sx, sy = width / cw, height / ch
        return fx * sx, fy * sy, cx * sx, cy * sy

    def lens(self, width: int, height: int, full: tuple[int, int]) -> Distortion | None:
        """The distortion for an image of this size, or None for a pinhole camera."""
        if self.distortion is None:
            return None
        return Distortion(*self.pinhole(width, height, full), self.distortion)


@dataclass
class Frame:
    name: str  # the view's name (its image's path below the frames' common folder, '/' as '_')
    path: str  # the image file, absolute (the extension found on disk when the file names none)
    viewmat: np.ndarray  # [4, 4] float64 world -> camera, in the source's world (ctgs.scene.conventions)
    intrinsics: Intrinsics
    mask_path: str | None  # absolute, from mask_path; None: looked up beside the image folder
    split: str | None  # "train" / "test" from the file (Blender, nerfstudio's filenames lists), else None
    where: str  # "FILE: frames[i]" for messages
    rel: str = ""  # the image's path relative to the scene folder, as the file names it (extension resolved)


@dataclass
class FrameSet:
    layout: str  # "nerfstudio", "instant-ngp" or "blender"
    files: list[str]
    frames: list[Frame]  # sorted by name
    points: np.ndarray | None  # [P, 3] float64 in the source's world, None without ply_file_path
    colors: np.ndarray | None  # [P, 3] uint8
    ply_path: str | None = None
    aabb: tuple[np.ndarray, np.ndarray] | None = None  # instant-ngp's box (lo, hi) in the source's world
    meta: dict = field(default_factory=dict)


def _load_json(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file; restore the capture's transforms file") from None
    except ValueError as exc:
        raise UserError(f"{path}: not valid JSON ({exc}); fix the file or export it again") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: holds a JSON {type(data).__name__}, not an object with 'frames'")
    return data


def _number(value, where: str, key: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or \
            (positive and value <= 0):
        raise UserError(f"{where}: '{key}' is {value!r}, not a {'positive ' if positive else ''}finite number; fix it "
                        "in the file")
    return float(value)


def _intrinsics(top: dict, frame: dict, where: str) -> Intrinsics:
    own = {k: frame[k] for k in INTRINSIC_KEYS + DISTORTION_KEYS + ("camera_model",) if k in frame}
    shared = not any(k in own for k in ("fl_x", "camera_angle_x"))
    merged = {**{k: top[k] for k in INTRINSIC_KEYS + DISTORTION_KEYS + ("camera_model",) if k in top}, **own}
    model = merged.get("camera_model", "OPENCV")
    if model not in PINHOLE_CAMERA_MODELS:
        raise UserError(f"{where}: 'camera_model' is {model!r}: ctgs reads pinhole cameras with OpenCV distortion "
                        f"({', '.join(PINHOLE_CAMERA_MODELS)}); undistort the images first (e.g. ns-process-data "
                        f"with --camera-type perspective)")
    values = {}
    for key in INTRINSIC_KEYS:
        if key in merged and merged[key] is not None:
            values[key] = _number(merged[key], where, key, positive=key != "cx" and key != "cy")
    for key in ("w", "h"):
        if key in values:
            values[key] = int(round(values[key]))
    if "fl_x" not in values and "camera_angle_x" not in values:
        raise UserError(f"{where}: no focal length; give 'fl_x' (pixels) or 'camera_angle_x' (radians), at the top "
                        "level for every frame or in each frame")
    if "camera_angle_x" in values and not values["camera_angle_x"] < math.pi:
        raise UserError(f"{where}: 'camera_angle_x' is {values['camera_angle_x']:g}, not an angle below pi radians")
    coeffs = tuple(_number(merged.get(k, 0.0), where, k) for k in DISTORTION_KEYS)
    return Intrinsics(values, coeffs if any(coeffs) else None, shared, where)


def _image_file(root: str, file_path: str, where: str) -> str:
    """The absolute image file a frame names (Blender's have no extension; instant-ngp's may lack it)."""
    path = os.path.normpath(os.path.join(root, file_path))
    if os.path.isfile(path):
        return path
    if not os.path.splitext(path)[1].lower() in IMAGE_EXTENSIONS:
        for ext in IMAGE_EXTENSIONS + tuple(e.upper() for e in IMAGE_EXTENSIONS):
            if os.path.isfile(path + ext):
                return path + ext
    raise UserError(f"{where}: 'file_path' names {file_path!r}, but {path} is not on disk; restore the image or "
                    "remove its frame")


def _to_source(path: str, data: dict) -> np.ndarray:
    """[4, 4] from the file's world to its source's: the inverse of nerfstudio's applied_transform, else identity."""
    if "applied_transform" not in data:
        return np.eye(4)
    try:
        return conventions.source_world(conventions.as_affine(data["applied_transform"], rows=(3, 4)))
    except conventions.BadMatrix as exc:
        raise UserError(f"{path}: 'applied_transform' {exc}; fix it or remove the key") from None


def _frames(path: str, data: dict, split: str | None) -> list[Frame]:
    root = os.path.dirname(path)
    frames = data.get("frames")
    if frames is None:
        raise UserError(f"{path}: no 'frames' key; a transforms file lists its images and camera poses under "
                        "'frames'")
    if not isinstance(frames, list) or not frames:
        raise UserError(f"{path}: 'frames' is {'empty' if frames == [] else 'not a list'}; it must list the images "
                        "and their poses")
    to_source = _to_source(path, data)
    out = []
    for i, frame in enumerate(frames):
        where = f"{path}: frames[{i}]"
        if not isinstance(frame, dict):
            raise UserError(f"{where} is not an object with 'file_path' and 'transform_matrix'")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise UserError(f"{where} has no '{key}'; every frame needs 'file_path' and 'transform_matrix'")
        if not isinstance(frame["file_path"], str):
            raise UserError(f"{where}: 'file_path' is not a string")
        try:
            c2w = to_source @ conventions.as_affine(frame["transform_matrix"])
            viewmat = conventions.viewmat_from_opengl_c2w(c2w)
        except conventions.BadMatrix as exc:
            raise UserError(f"{where}: 'transform_matrix' {exc}; fix the pose or remove the frame") from None
        image = _image_file(root, frame["file_path"], where)
        mask = frame.get("mask_path")
        if mask is not None:
            mask = os.path.normpath(os.path.join(root, str(mask)))
            if not os.path.isfile(mask):
                raise UserError(f"{where}: 'mask_path' names {frame['mask_path']!r}, but {mask} is not on disk; "
                                "restore the mask or remove the key")
        out.append(Frame(name="", path=image, viewmat=viewmat, intrinsics=_intrinsics(data, frame, where),
                         mask_path=mask, split=split, where=where))
    return out


def _named(frames: list[Frame], scene_dir: str) -> list[Frame]:
    """Names below the frames' common folder ('/' as '_': the name is also a render's file name), sorted; a clash of
    names is an error naming both frames."""
    common = os.path.commonpath([os.path.dirname(f.path) for f in frames])
    seen: dict[str, Frame] = {}
    for f in frames:
        f.name = os.path.relpath(f.path, common).replace(os.sep, "_")
        f.rel = os.path.relpath(f.path, scene_dir)
        if f.name in seen and seen[f.name].split == f.split:
            raise UserError(f"{f.where}: names the image of {seen[f.name].where} again ({f.name}); remove one frame")
        seen[f.name] = f
    return sorted(frames, key=lambda f: (f.name, f.split or ""))


def _check_sizes(frames: list[Frame], sizes: dict[str, tuple[int, int]]) -> None:
    """Frames sharing the file's camera without its w and h must show images of one size (else the focal length in
    pixels is ambiguous)."""
    first = None
    for f in frames:
        if not f.intrinsics.shared or "w" in f.intrinsics.values:
            continue
        size = sizes[f.path]
        if first is None:
            first = (f, size)
        elif size != first[1]:
            raise UserError(f"{f.where}: image {f.rel} is {size[0]}x{size[1]} but {first[0].rel} is "
                            f"{first[1][0]}x{first[1][1]}, and they share the file's camera, which gives no 'w', "
                            "'h'; give 'w' and 'h' with the shared camera, or each frame its own 'fl_x', 'fl_y', "
                            "'cx', 'cy', 'w', 'h'")


def check_image_sizes(frames: list[Frame], sizes: dict[str, tuple[int, int]]) -> None:
    """UserError naming the frame and the keys: mixed sizes under one camera without w/h, or an image whose aspect
    ratio is not its calibration's (`sizes`: path -> (width, height) of the file)."""
    _check_sizes(frames, sizes)
    for f in frames:
        width, height = sizes[f.path]
        cw, ch = f.intrinsics.calibration_size((width, height))
        expected = ch * width / cw
        if abs(height - expected) > 1.0 + 0.02 * expected:
            raise UserError(f"{f.where}: image {f.rel} is {width}x{height} but its camera's 'w', 'h' say {cw}x{ch} "
                            "(another aspect ratio); fix 'w' and 'h' or use the images the file was made for")


def _points(path: str, data: dict, to_source: np.ndarray):
    if not data.get("ply_file_path"):
        return None, None, None
    ply = os.path.normpath(os.path.join(os.path.dirname(path), str(data["ply_file_path"])))
    if not os.path.isfile(ply):
        raise UserError(f"{path}: 'ply_file_path' names {data['ply_file_path']!r}, but {ply} is not on disk; restore "
                        "it or remove the key (training then starts from random points)")
    points, colors = read_points_ply(ply)
    return conventions.transform_points(to_source, points), colors, ply


def _aabb(path: str, data: dict, to_source: np.ndarray):
    """instant-ngp's box of the scene in the source's world: its unit cube grown aabb_scale times about its centre,
    taken back through its scale and offset and its axis order (ngp x, y, z = the file's y, z, x)."""
    if "aabb_scale" not in data:
        return None
    aabb = _number(data["aabb_scale"], path, "aabb_scale", positive=True)
    scale = _number(data.get("scale", NGP_SCALE), path, "scale", positive=True)
    offset = data.get("offset", NGP_OFFSET)
    if not isinstance(offset, list) or len(offset) != 3:
        raise UserError(f"{path}: 'offset' is {offset!r}, not a list of 3 numbers; fix it or remove the key")
    off = np.array([_number(o, path, "offset") for o in offset])
    centre = (0.5 - off[[2, 0, 1]]) / scale  # the file's x, y, z from ngp's z, x, y
    half = 0.5 * aabb / scale
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half + centre
    moved = conventions.transform_points(to_source, corners)
    return moved.min(0), moved.max(0)


def read_transforms(scene_dir: str) -> FrameSet:
    """The frames, points and bounds of a transforms.json or Blender scene folder (see the module docstring)."""
    layout = scene_layout(scene_dir)
    if layout == "blender":
        files, frames = [], []
        for split, name in BLENDER_SPLITS:
            path = os.path.join(scene_dir, name)
            if not os.path.isfile(path):
                raise UserError(f"{path}: missing; a Blender synthetic scene has transforms_train.json and "
                                "transforms_test.json")
            data = _load_json(path)
            frames += _frames(path, data, split)
            files.append(path)
        first = _load_json(files[0])
        to_source = np.eye(4)
    else:
        path = os.path.join(scene_dir, TRANSFORMS)
        first = _load_json(path)
        files, frames = [path], _frames(path, first, None)
        to_source = _to_source(path, first)
        layout = "nerfstudio" if any(k in first for k in ("camera_model", "applied_transform")) or \
            any(isinstance(f, dict) and "fl_x" in f for f in first["frames"]) else "instant-ngp"
        _split_by_lists(path, first, frames)
    points, colors, ply = _points(files[0], first, to_source)
    return FrameSet(layout=layout, files=files, frames=_named(frames, scene_dir), points=points, colors=colors,
                    ply_path=ply, aabb=_aabb(files[0], first, to_source),
                    meta={"aabb_scale": first.get("aabb_scale")} if "aabb_scale" in first else {})


def _split_by_lists(path: str, data: dict, frames: list[Frame]) -> None:
    """nerfstudio's own split: `test_filenames` (or `val_filenames`) are test views, the rest training views."""
    listed = data.get("test_filenames") or data.get("val_filenames")
    if not listed:
        return
    root = os.path.dirname(path)
    test = {os.path.normpath(os.path.join(root, str(p))) for p in listed}
    for f in frames:
        f.split = "test" if f.path in test or os.path.splitext(f.path)[0] in test else "train"
