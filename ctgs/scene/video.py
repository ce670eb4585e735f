"""Photos from a video for `ctgs sfm VIDEO -o SCENE`: frames picked by sharpness and spacing, then the usual SfM.

The video is cut into N spans of equal length (`--frames N`) and the sharpest frame of each span is kept: the
variance of the Laplacian of its grey image (at most SHARPNESS_SIDE pixels wide), the usual focus measure, which is
lowest on frames smeared by motion blur. Frames go to SCENE/input/ (3DGS's folder of input photos) as
frame_NNNNN.jpg in time order, and SCENE/video_frames.json records the video, each frame's index, time and
sharpness. Decoding is OpenCV's (a dependency).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable

import numpy as np

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.io.images import write_image

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".wmv")
FRAMES_DIR = "input"
RECORD = "video_frames.json"
SHARPNESS_SIDE = 640  # pixels: the focus measure is taken on frames shrunk to at most this width
MIN_FRAMES = 3


def is_video(path: str) -> bool:
    return os.path.isfile(path) and os.path.splitext(path)[1].lower() in VIDEO_EXTENSIONS


def _open(path: str):
    # OpenCV: a dependency, loaded only where a video is read
    import cv2

    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        raise UserError(f"{path}: cannot be decoded as a video (OpenCV/FFmpeg); convert it to H.264 MP4 or extract "
                        "its frames into a folder and pass that folder")
    return cv2, cap


def sharpness(cv2, frame: np.ndarray) -> float:
    """Variance of the Laplacian of the grey frame, shrunk to at most SHARPNESS_SIDE pixels wide."""
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if grey.shape[1] > SHARPNESS_SIDE:
        scale = SHARPNESS_SIDE / grey.shape[1]
        grey = cv2.resize(grey, (SHARPNESS_SIDE, max(1, round(grey.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def pick(scores: list[float], count: int) -> list[int]:
    """Indices of the sharpest frame of each of `count` equal spans of the frames (all of them when fewer)."""
    n = len(scores)
    if n <= count:
        return list(range(n))
    edges = np.linspace(0, n, count + 1)
    chosen = []
    for a, b in zip(edges[:-1], edges[1:]):
        lo, hi = int(round(a)), max(int(round(b)), int(round(a)) + 1)
        chosen.append(lo + int(np.argmax(scores[lo:hi])))
    return chosen


def _fingerprint(video: str) -> dict:
    st = os.stat(video)
    return {"video": os.path.abspath(video), "bytes": st.st_size, "mtime": int(st.st_mtime)}


def extract_frames(video: str, scene_dir: str, count: int, force: bool = False,
                   progress: Callable[[str, int, int | None, str], None] = lambda *a: None) -> tuple[str, dict]:
    """(SCENE/input, the record) with `count` frames of `video` written there, or the ones an earlier call wrote for
    the same video and count."""
    if count < MIN_FRAMES:
        raise UserError(f"--frames {count}: SfM needs at least {MIN_FRAMES} frames (100-300 for a walk-around video)")
    frames_dir, record_path = os.path.join(scene_dir, FRAMES_DIR), os.path.join(scene_dir, RECORD)
    fingerprint = {**_fingerprint(video), "requested": count}
    if os.path.isfile(record_path) and os.path.isdir(frames_dir) and not force:
        with open(record_path, encoding="utf-8") as f:
            try:
                old = json.load(f)
            except ValueError:
                old = {}
        if {k: old.get(k) for k in fingerprint} == fingerprint:
            return frames_dir, old
        raise UserError(f"{scene_dir}: holds frames of another video or another --frames ({old.get('video')}, "
                        f"{old.get('requested')} frames); write this one elsewhere (-o) or pass --force")
    if os.path.isdir(scene_dir) and os.listdir(scene_dir) and not force and not os.path.isfile(record_path):
        raise UserError(f"{scene_dir}: folder exists and is not a scene made from a video; choose another -o or "
                        "pass --force")

    cv2, cap = _open(video)
    fps = float(cap.get(cv2.CAP_PROP_FPS)) or 0.0
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
    scores, times = [], []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            times.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0)
            scores.append(sharpness(cv2, frame))
            if len(scores) % 25 == 0:
                progress("frames", len(scores), total, "frames scored")
    finally:
        cap.release()
    if len(scores) < MIN_FRAMES:
        raise UserError(f"{video}: {len(scores)} frame(s) decoded; SfM needs at least {MIN_FRAMES}")
    chosen = pick(scores, count)
    if fps > 0 and all(t == 0.0 for t in times[1:]):  # containers without timestamps
        times = [i / fps for i in range(len(times))]

    wanted = set(chosen)
    frames = []
    cv2, cap = _open(video)
    try:
        with atomic.atomic_dir(frames_dir) as tmp:
            index = 0
            while len(frames) < len(chosen):
                ok, frame = cap.read()
                if not ok:
                    raise UserError(f"{video}: ended at frame {index} on the second reading (it held "
                                    f"{len(scores)} before); the file changed or is damaged")
                if index in wanted:
                    name = f"frame_{len(frames) + 1:05d}.jpg"
                    write_image(os.path.join(tmp, name), cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
                    frames.append({"name": name, "index": index, "time_s": round(times[index], 4),
                                   "sharpness": round(scores[index], 3)})
                    progress("frames", len(frames), len(chosen), "frames written")
                index += 1
    finally:
        cap.release()
    record = {**fingerprint, "fps": fps, "frames_in_video": len(scores),
              "duration_s": round(times[-1], 4) if times else 0.0,
              "method": f"sharpest frame (variance of the Laplacian) of each of {len(chosen)} equal spans",
              "frames": frames}
    atomic.write_json(record_path, record, indent=1)
    return frames_dir, record
