"""resize_image shrinks with OpenImageIO's own filter, applied per axis: the values OIIO's 2D resize gives."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest

from ctgs.io.images import resize_image

# Largest difference from OIIO's resize (values in [0, 1]): float32 sums in another order. Observed worst 1.0e-5 on a
# 798x531 photo shrunk 2x (29 of 318k 8-bit values then round the other way), 3e-6 on the random images below.
MAX_DIFFERENCE = 3e-5


def _oiio_resize(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    h, w, c = pixels.shape
    src = oiio.ImageBuf(oiio.ImageSpec(w, h, c, "float"))
    src.set_pixels(oiio.ROI(0, w, 0, h, 0, 1, 0, c), pixels)
    dst = oiio.ImageBuf(oiio.ImageSpec(width, height, c, "float"))
    assert oiio.ImageBufAlgo.resize(dst, src)
    return np.asarray(dst.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(height, width, c)


@pytest.mark.parametrize("shape, size", [
    ((531, 798, 3), (399, 266)),  # a photo's pyramid: 2x, 4x, 8x with rounded sizes (ratios 7.98 and 8.05)
    ((531, 798, 3), (200, 133)),
    ((531, 798, 3), (100, 66)),
    ((37, 53, 4), (11, 7)),  # alpha is filtered like any channel
    ((37, 53, 1), (26, 19)),  # a mask
    ((64, 48, 2), (47, 32)),  # one side barely shrinks
    ((10, 10, 3), (10, 3)),  # one side keeps its size
    ((5, 9, 3), (1, 1)),
])
def test_shrinking_matches_openimageio(shape, size):
    rng = np.random.default_rng(0)
    pixels = rng.random(shape, dtype=np.float32)
    pixels[:, :2] = 1.0  # a bright edge column: the filter reaches past the border there
    out = resize_image(pixels, *size)
    assert out.shape == (size[1], size[0], shape[2]) and out.dtype == np.float32
    assert np.abs(out - _oiio_resize(pixels, *size)).max() < MAX_DIFFERENCE


def test_growing_is_left_to_openimageio():
    pixels = np.random.default_rng(1).random((6, 8, 3), dtype=np.float32)
    assert np.array_equal(resize_image(pixels, 16, 12), _oiio_resize(pixels, 16, 12))
