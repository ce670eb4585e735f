"""OpenCV's SIFT as `ctgs sfm`'s feature extractor on the CPU, written into a COLMAP database as COLMAP's own.

COLMAP's CPU SIFT (VLFeat) computes every scale level whole and drops the finest ones beyond the feature budget;
OpenCV's keeps the strongest features by contrast over all scales and takes about 4x less CPU time for as many
features (bonsai252: benchmarks/results/sfm_profile/). Runs in the worker process (ctgs.scene.sfm.worker), which
passes pycolmap in, as for its other calls.

Conventions converted here (tests/scene/test_sift_cpu.py checks them against pycolmap's own SIFT):
- position: OpenCV puts a pixel's centre at integer coordinates, COLMAP its corner (a centre at +0.5);
- shape: COLMAP stores the affine frame [a11 a12; a21 a22] = sigma [cos t, -sin t; sin t, cos t], sigma the
  blob's scale (OpenCV's `size` is its diameter, 2 sigma) and t the orientation in the image's frame (y down),
  as OpenCV's `angle`, in degrees there;
- descriptors: RootSIFT (COLMAP's default L1_ROOT normalisation) stored as bytes round(512 x), at most 255;
  OpenCV's bins are laid out as COLMAP stores VLFeat's (Lowe's order), so the two extractors' descriptors of
  one keypoint agree within a few units of 255.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

# OpenCV divides its contrast threshold by the layers per octave (3): 0.02 is COLMAP's peak threshold, 0.02 / 3.
CONTRAST_THRESHOLD = 0.02


def colmap_keypoints(found, scale_x: float = 1.0, scale_y: float = 1.0) -> np.ndarray:
    """OpenCV keypoints -> COLMAP's [N, 6] float32 (x, y, a11, a12, a21, a22), in a photo `scale_x` x `scale_y`
    times the size of the one they were found in."""
    if not len(found):
        return np.zeros((0, 6), np.float32)
    xy = np.array([k.pt for k in found], np.float64) + 0.5
    sigma = np.array([k.size for k in found], np.float64) / 2
    t = np.deg2rad([k.angle for k in found])
    c, s = sigma * np.cos(t), sigma * np.sin(t)
    return np.stack([xy[:, 0] * scale_x, xy[:, 1] * scale_y, c * scale_x, -s * scale_x, s * scale_y, c * scale_y],
                    axis=1).astype(np.float32)


def colmap_descriptors(desc: np.ndarray) -> np.ndarray:
    """OpenCV's SIFT descriptors [N, 128] -> RootSIFT as COLMAP stores its own: uint8."""
    desc = np.asarray(desc, np.float64)
    root = np.sqrt(desc / np.maximum(desc.sum(1, keepdims=True), 1e-12))
    return np.minimum(np.round(512 * root), 255).astype(np.uint8)


def make_sift(max_features: int):
    return cv2.SIFT_create(nfeatures=max_features, contrastThreshold=CONTRAST_THRESHOLD, enable_precise_upscale=True)


def sift_grey(grey: np.ndarray, sift, max_features: int, max_image_size: int) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints [N, 6], descriptors [N, 128] uint8), COLMAP's, of one grey photo (uint8 [H, W]), shrunk first to
    `max_image_size` pixels on its longest side."""
    h, w = grey.shape
    scale_x = scale_y = 1.0
    if max(w, h) > max_image_size:
        f = max_image_size / max(w, h)
        small_w, small_h = max(1, round(w * f)), max(1, round(h * f))
        grey = cv2.resize(grey, (small_w, small_h), interpolation=cv2.INTER_AREA)
        scale_x, scale_y = w / small_w, h / small_h
    found, desc = sift.detectAndCompute(grey, None)
    if not found or desc is None:
        return np.zeros((0, 6), np.float32), np.zeros((0, 128), np.uint8)
    return colmap_keypoints(found[:max_features], scale_x, scale_y), colmap_descriptors(desc[:max_features])


def read_grey(path: str) -> np.ndarray:
    """A photo's grey pixels as COLMAP reads them: as stored, the EXIF orientation ignored."""
    grey = cv2.imread(path, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if grey is None:
        raise RuntimeError(f"{path}: OpenCV cannot read this image; convert it to JPEG or PNG")
    return grey


def extract(pycolmap, job: dict, reader) -> None:
    """Photos and their one camera into job["database"] as pycolmap.extract_features enters them (import_images
    with `reader`, pycolmap.ImageReaderOptions), then each photo's features: a photo per thread (OpenCV releases
    the GIL), written in name order."""
    cv2.setNumThreads(1)  # the photos are spread over the threads instead
    pycolmap.Database.open(job["database"]).close()  # made with COLMAP's tables
    pycolmap.import_images(job["database"], job["images_dir"], camera_mode=pycolmap.CameraMode.SINGLE,
                           image_names=job["names"], options=reader)
    local = threading.local()

    def one(name: str) -> tuple[np.ndarray, np.ndarray]:
        if not hasattr(local, "sift"):
            local.sift = make_sift(job["max_features"])
        grey = read_grey(os.path.join(job["images_dir"], name))
        return sift_grey(grey, local.sift, job["max_features"], job["max_image_size"])

    threads = job["threads"] if job["threads"] > 0 else (os.cpu_count() or 1)
    db = pycolmap.Database.open(job["database"])
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        with ThreadPoolExecutor(max_workers=threads) as pool:
            for name, (keypoints, descriptors) in zip(job["names"], pool.map(one, job["names"])):
                db.write_keypoints(ids[name], keypoints)
                db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                                            descriptors))
    finally:
        db.close()
