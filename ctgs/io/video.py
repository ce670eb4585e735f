"""Writing a video (`ctgs render RUN --path ... -o OUT.mp4`) with OpenCV's VideoWriter, through the FFmpeg its wheels
carry: no further dependency, no ffmpeg program on the PATH.

Codecs, both in an MP4 file:
- vp9 (the default): plays in every current browser (Chrome, Firefox, Edge, Safari 14+), VLC, mpv and ffmpeg, so a
  video can go on a web page as it is;
- mpeg4 (MPEG-4 Part 2): for players without VP9 (QuickTime on older macOS); browsers do not play it.
H.264 is not offered: the FFmpeg inside OpenCV's wheels has no H.264 encoder (x264 is GPL, OpenH264 not bundled), and
OpenImageIO reads videos but does not write them.

The encoders store colour at half resolution (4:2:0), so a frame's width and height must be even. The file is written
under a temporary name and renamed when every frame is in and it reads back with as many frames (ctgs.io.atomic).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from ctgs.errors import UserError
from ctgs.io import atomic

CODECS = {"vp9": "vp09", "mpeg4": "mp4v"}  # name -> FFmpeg's MP4 tag (fourcc)
EXTENSION = ".mp4"


def check_size(width: int, height: int, what: str) -> None:
    """UserError naming `what` (the option or file that asked for the size) unless width and height are even."""
    if width < 2 or height < 2 or width % 2 or height % 2:
        even = f"{max(2, width - width % 2)}x{max(2, height - height % 2)}"
        raise UserError(f"{what}: a video frame of {width}x{height} pixels; its sides must be even (the encoder "
                        f"stores colour at half resolution): pass {even}")


class VideoWriter:
    """The frames of one video: write(rgb) for each [H, W, 3] frame, in [0, 1] (clipped) or uint8. Made by
    `open_video`."""

    def __init__(self, writer, width: int, height: int):
        self._writer, self.size, self.frames = writer, (width, height), 0

    def write(self, rgb: np.ndarray) -> None:
        import cv2  # (loaded by open_video)

        frame = np.asarray(rgb)
        if frame.shape != (self.size[1], self.size[0], 3):
            raise ValueError(f"frame of shape {frame.shape}, the video is {self.size[0]}x{self.size[1]} RGB")
        if frame.dtype != np.uint8:
            frame = np.clip(np.rint(frame.astype(np.float32) * 255.0), 0, 255).astype(np.uint8)
        self._writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        self.frames += 1


def check_path(path: str, codec: str = "vp9") -> None:
    """UserError unless `path` names an MP4 file and `codec` is one of CODECS."""
    if os.path.splitext(path)[1].lower() != EXTENSION:
        raise UserError(f"{path}: a video is written as an {EXTENSION} file; name it OUT{EXTENSION}")
    if codec not in CODECS:
        raise UserError(f"codec {codec!r}: use one of {', '.join(CODECS)}")


@contextmanager
def open_video(path: str, fps: float, width: int, height: int, codec: str = "vp9") -> Iterator[VideoWriter]:
    """A VideoWriter for `path` (an .mp4 file); the file takes its name once the block ends and every frame reads back
    (a failure leaves nothing behind)."""
    # OpenCV: a dependency, loaded only where a video is written
    import cv2

    check_path(path, codec)
    check_size(width, height, path)
    with atomic.atomic_path(path) as tmp:
        writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*CODECS[codec]), float(fps), (int(width), int(height)))
        if not writer.isOpened():
            raise UserError(f"{path}: OpenCV's FFmpeg cannot write {codec} video on this machine; pass --codec "
                            f"{'mpeg4' if codec == 'vp9' else 'vp9'}")
        video = VideoWriter(writer, int(width), int(height))
        try:
            yield video
        finally:
            writer.release()
        cap = cv2.VideoCapture(tmp)
        got = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        cap.release()
        if got != video.frames:
            raise UserError(f"{path}: the video reads back with {got} of its {video.frames} frames (a full disk?); "
                            "free some space and render again")
