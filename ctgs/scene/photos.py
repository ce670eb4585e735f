"""A view's pixels as training and evaluation use them: transparency over the run's background, OpenCV undistortion,
a smaller level made in memory, and the mask of the pixels left out of the loss and the metrics.

Transparent photos (RGBA, such as NeRF's Blender scenes) are composited over the background the run renders over
(`background` of the config, `ctgs train --background`); their alpha is kept, so that a run that renders over a random
colour each step composites its photo over the same colour (ctgs.train.loop.trainer).

Masks: white (>= 0.5) pixels are used, black ones are left out, as nerfstudio reads them. A mask is found beside the
image folder (`masks/` for `images/`, `masks_4/` for `images_4/`, else `masks/` shrunk to the image's size) under the
image's name, its stem with another extension, or COLMAP's NAME.png; transforms.json may name one per frame
(`mask_path`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ctgs.errors import UserError
from ctgs.io.images import IMAGE_EXTENSIONS, read_image, resize_image, to_rgb

# Below this share of used pixels a mask leaves a view nothing to learn from.
MASK_MIN_SHARE = 1e-3


@dataclass(frozen=True)
class Distortion:
    """OpenCV's radial-tangential model at calibration size: the camera matrix and (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    coeffs: tuple[float, float, float, float, float]

    def scaled(self, sx: float, sy: float) -> Distortion:
        """The same lens for the image resized by (sx, sy) (the coefficients act on normalised coordinates)."""
        return Distortion(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.coeffs)

    def _matrices(self, width: int, height: int):
        # OpenCV: a dependency, loaded only where a distorted camera is read
        import cv2

        k = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        d = np.array(self.coeffs, dtype=np.float64)
        # alpha 0: every pixel of the undistorted image sees the scene (no black border), as COLMAP's undistorter
        new_k, _ = cv2.getOptimalNewCameraMatrix(k, d, (width, height), 0.0, (width, height))
        return cv2, k, d, new_k

    def pinhole(self, width: int, height: int) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the undistorted image of this size."""
        new_k = self._matrices(width, height)[3]
        return float(new_k[0, 0]), float(new_k[1, 1]), float(new_k[0, 2]), float(new_k[1, 2])

    def undistort(self, pixels: np.ndarray, nearest: bool = False) -> np.ndarray:
        """[H, W, C] float32 (C <= 4) resampled to the undistorted pinhole camera `pinhole` describes."""
        h, w = pixels.shape[:2]
        cv2, k, d, new_k = self._matrices(w, h)
        map1, map2 = cv2.initUndistortRectifyMap(k, d, None, new_k, (w, h), cv2.CV_32FC1)
        out = cv2.remap(np.ascontiguousarray(pixels, dtype=np.float32), map1, map2,
                        cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(h, w, -1)


@dataclass
class Photo:
    rgb: np.ndarray  # [H, W, 3] float32, composited over the background where the file has alpha
    alpha: np.ndarray | None  # [H, W, 1] float32 where the file has alpha below 1 somewhere, else None


def level_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """The size of a photo shrunk `factor` times, as `ctgs sfm` and ctgs.scene.levels make their levels."""
    return max(1, round(width / factor)), max(1, round(height / factor))


def read_photo(path: str, background=(0.0, 0.0, 0.0), factor: int = 1,
               lens: Callable[[int, int], Distortion | None] | None = None) -> Photo:
    """`path` shrunk `factor` times, undistorted when `lens(width, height)` gives its distortion at the shrunk size,
    composited over `background`."""
    pixels = read_image(path)
    if factor > 1:
        pixels = resize_image(pixels, *level_size(pixels.shape[1], pixels.shape[0], factor))
    distortion = None if lens is None else lens(pixels.shape[1], pixels.shape[0])
    if distortion is not None:
        pixels = distortion.undistort(pixels)
    alpha = None
    if pixels.shape[2] in (2, 4):
        a = np.clip(pixels[:, :, -1:], 0.0, 1.0)
        alpha = a if float(a.min()) < 1.0 else None
    return Photo(to_rgb(pixels, tuple(background)), alpha)


def find_mask(scene_dir: str, images: str, name: str) -> str | None:
    """The mask of image `name` (relative to the image folder `images`) beside it, or None: masks_N/ for images_N/
    first, then masks/."""
    folders = [images.replace("images", "masks", 1)] if images.startswith("images") else []
    folders += [] if "masks" in folders else ["masks"]
    stem = os.path.splitext(name)[0]
    for folder in folders:
        base = os.path.join(scene_dir, folder)
        if not os.path.isdir(base):
            continue
        for candidate in [name, name + ".png"] + [stem + e for e in IMAGE_EXTENSIONS + (".PNG", ".JPG")]:
            path = os.path.join(base, candidate)
            if os.path.isfile(path):
                return path
    return None


def read_mask(path: str, width: int, height: int, distortion: Distortion | None = None) -> np.ndarray:
    """[height, width] bool: True where the pixel is used. A mask of another size with the image's aspect is resized
    (a mask at full size for a smaller image level); UserError naming the file otherwise, or when it leaves (almost)
    nothing."""
    m = read_image(path)[:, :, :1]
    h, w = m.shape[:2]
    if (w, h) != (width, height):
        if abs(h * width / w - height) > 1.0 + 0.02 * height:
            raise UserError(f"{path}: mask is {w}x{h} but its image is {width}x{height} (another aspect ratio); "
                            "give each image a mask of its own size")
        m = resize_image(m, width, height)
    if distortion is not None:
        m = distortion.undistort(m, nearest=True)
    used = m[:, :, 0] >= 0.5
    if used.mean() < MASK_MIN_SHARE:
        raise UserError(f"{path}: the mask leaves no pixel of its image in use (white = used, black = left out); "
                        "fix the mask or remove it")
    return used
