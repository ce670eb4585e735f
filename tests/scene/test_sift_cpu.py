"""`ctgs sfm`'s CPU features (OpenCV's SIFT) in COLMAP's conventions: the same keypoints, orientations and
descriptors as pycolmap's own CPU SIFT on one synthetic image, and a shrunk photo's keypoints in its full-size
pixels."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from ctgs.scene.sfm import sift_cpu  # noqa: E402

FEATURES = 500


def _blobs(width: int = 320, height: int = 240, seed: int = 0) -> np.ndarray:
    """Grey uint8: a dozen blobs, each with a smaller one beside it (so that each has an orientation)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    img = np.full((height, width), 40.0)
    for _ in range(12):
        x0, y0 = rng.uniform(30, width - 30), rng.uniform(30, height - 30)
        s, a = rng.uniform(2.5, 5), rng.uniform(0, 2 * np.pi)
        x1, y1 = x0 + 2 * s * np.cos(a), y0 + 2 * s * np.sin(a)
        img += 150 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s))
        img += 60 * np.exp(-((xx - x1) ** 2 + (yy - y1) ** 2) / (2 * (0.6 * s) ** 2))
    return np.clip(img, 0, 255).astype(np.uint8)


def _shape(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(scale, orientation) of COLMAP keypoints [N, 6], as COLMAP's FeatureKeypoint computes them."""
    return np.hypot(k[:, 2], k[:, 4]), np.arctan2(k[:, 4], k[:, 2])


def test_keypoints_and_descriptors_as_colmaps_own_sift():
    grey = _blobs()
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = FEATURES
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # pycolmap.Sift: the shortest way to COLMAP's CPU SIFT
        ref_kp, ref_desc = pycolmap.Sift(options, pycolmap.Device.cpu).extract(grey.astype(np.float32) / 255)
    ref_desc = ref_desc * 512 if ref_desc.max() < 2 else ref_desc  # float RootSIFT -> COLMAP's stored bytes' scale
    kp, desc = sift_cpu.sift_grey(grey, sift_cpu.make_sift(FEATURES), FEATURES, 3200)
    assert kp.dtype == np.float32 and kp.shape[1] == 6 and desc.dtype == np.uint8 and desc.shape == (len(kp), 128)
    scale, angle = _shape(kp)
    turn, apart = [], []
    for (x, y, s, t), d in zip(ref_kp, ref_desc):
        near = np.flatnonzero(np.hypot(kp[:, 0] - x, kp[:, 1] - y) < 0.05)  # pixel corner at 0, as COLMAP's
        if not len(near):
            continue
        j = near[np.abs(desc[near].astype(float) - d).mean(1).argmin()]  # among a point's orientations
        turn.append(abs(np.rad2deg(np.angle(np.exp(1j * (angle[j] - t))))))
        assert abs(scale[j] / s - 1) < 0.02
        apart.append(np.abs(desc[j].astype(float) - d).mean())
    assert len(turn) >= 0.8 * len(ref_kp) and len(ref_kp) >= 20
    # orientation histograms smoothed a little differently: a few degrees apart (turned the wrong way: up to 180);
    # a point's second orientation, kept by one extractor only, is the odd one out
    assert np.median(turn) < 5 and np.mean(np.array(turn) < 20) > 0.85, turn
    # descriptors: the same bin layout, a few units of 0..255 apart (where the orientations agree)
    assert np.median(apart) < 5, apart


def test_a_shrunk_photo_gives_keypoints_in_its_full_size_pixels():
    small = _blobs(seed=1)
    big = cv2.resize(small, (small.shape[1] * 2, small.shape[0] * 2), interpolation=cv2.INTER_CUBIC)
    sift = sift_cpu.make_sift(FEATURES)
    whole, _ = sift_cpu.sift_grey(big, sift, FEATURES, 10_000)
    shrunk, _ = sift_cpu.sift_grey(big, sift, FEATURES, small.shape[1])  # seen at half size
    assert len(shrunk) >= 10
    dist = np.hypot(whole[:, None, 0] - shrunk[None, :, 0], whole[:, None, 1] - shrunk[None, :, 1]).min(0)
    assert np.median(dist) < 0.3  # full-size pixels (half a pixel off at half size would be 1.0)
    ratio = _shape(shrunk)[0] / _shape(whole)[0][np.hypot(whole[:, None, 0] - shrunk[None, :, 0],
                                                          whole[:, None, 1] - shrunk[None, :, 1]).argmin(0)]
    assert abs(np.median(ratio) - 1) < 0.1


def test_no_features_and_an_unreadable_photo(tmp_path):
    kp, desc = sift_cpu.sift_grey(np.full((64, 64), 128, np.uint8), sift_cpu.make_sift(FEATURES), FEATURES, 3200)
    assert kp.shape == (0, 6) and desc.shape == (0, 128)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not a jpeg")
    with pytest.raises(RuntimeError, match="bad.jpg: OpenCV cannot read this image"):
        sift_cpu.read_grey(str(bad))
