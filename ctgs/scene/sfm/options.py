"""What `ctgs sfm` can be asked (SfmOptions) and what "auto" stands for with a given number of photos."""

from __future__ import annotations

from dataclasses import dataclass

MIN_IMAGES = 3
# Fewer registered images than this fraction means SfM failed on this input (too little overlap or
# texture); training on the registered few would silently produce a bad model.
MIN_REGISTERED_FRACTION = 0.5
PYRAMID_FACTORS = (2, 4, 8)

MATCHERS = ("auto", "exhaustive", "sequential", "retrieval")
MAPPERS = ("auto", "incremental", "global")

# --matcher auto: every pair up to this many photos, retrieval above. Measured on the 2-core VM
# (benchmarks/results/sfm_modes/): retrieval pairs each photo with ~13 others (bonsai252: 3,344 pairs for 252
# photos; its every-4th 63: 761), exhaustive with n - 1, and a pair costs about the same either way (0.08-0.09 CPU s at ~5,000
# features, 0.22 at 8,192); at 50 photos exhaustive matching costs ~1.8x retrieval's, at 63 2.4x (181 vs 75 CPU s)
# with no better cameras. herzjesu25 (25 photos) stays exhaustive: as accurate as before, no slower.
EXHAUSTIVE_MAX_IMAGES = 50

# --mapper auto: incremental mapping below this many photos (up to 50), the global mapper from it. herzjesu25 (25)
# maps in 24 CPU s incrementally vs 42 globally, the same cameras; bonsai252's every-4th 63 photos mapped
# incrementally came out wrong (focal -13% to -17%, from exhaustive or retrieval pairs), globally right (0.54% mean
# centre error) in 23 CPU s vs 91; bonsai252 maps globally in 172-311 CPU s (incrementally: 1,795 s wall before).
GLOBAL_MIN_IMAGES = 51

# Retrieval pairing: each photo with its most similar photos, and its next ones in name order.
RETRIEVAL_NEIGHBOURS = 20
RETRIEVAL_OVERLAP = 3

# Sequential pairing: COLMAP's default overlap (quadratic), and loop closure by retrieval.
SEQUENTIAL_OVERLAP = 10
LOOP_NEIGHBOURS = 5

# The global mapper's photos with fewer 3D points than this are registered again (ctgs.scene.sfm.worker.map_global).
MIN_POINTS_PER_IMAGE = 20
# ... and are registered again with this many 2D-3D inliers enough (COLMAP's default, 30, is more than such a photo
# has: playroom225's DSC05644, 14 points, was dropped by every repair at 30 and placed 0.29% from the reference at 15).
REPAIR_MIN_INLIERS = 15

# SIFT features per photo: COLMAP's default up to EXHAUSTIVE_MAX_IMAGES photos, fewer above, where matching and
# mapping cost grow with them (--max-features 0, the default: "auto"). bonsai252, retrieval + global mapper:
# 8192 -> 848 CPU s, centres within 0.29% (mean) / 0.57% (max) of the reference; 4096 -> 736 CPU s, 0.23 / 0.46%;
# 2048 -> 593 CPU s, 0.45 / 0.90% once its one lost photo is registered again. herzjesu25 keeps 8192 (4096 there:
# the same centres, focal -0.41% vs -0.39%).
DEFAULT_MAX_FEATURES = 8192
LARGE_CAPTURE_MAX_FEATURES = 4096


@dataclass
class SfmOptions:
    matcher: str = "auto"  # "auto" | "exhaustive" | "sequential" (video frames, in name order) | "retrieval"
    mapper: str = "auto"  # "auto" | "incremental" | "global"
    max_features: int = 0  # SIFT features per photo; 0: by the number of photos (resolve_modes)
    max_image_size: int = 3200  # pixels, longest side seen by SIFT (COLMAP's default)
    threads: int = -1  # -1: all cores
    force: bool = False  # redo every step even if finished
    seed: int = 0  # mapper RANSAC seed, for reproducible runs
    device: str = "auto"  # "auto": COLMAP's SIFT extraction and matching on the GPU when pycolmap has CUDA


def feature_extractor(device: str, has_cuda: bool, num_images: int) -> str:
    """Whose SIFT extracts the features: "colmap" (SiftGPU) where pycolmap runs it on a GPU, and on the CPU for a
    capture of up to EXHAUSTIVE_MAX_IMAGES photos; "opencv" on the CPU above that. COLMAP's CPU SIFT (VLFeat)
    computes every scale level whole and then drops the finest ones beyond the feature budget; OpenCV's keeps the
    strongest features over all scales and took a quarter of the CPU time (bonsai252: 38.7 vs 165.1 CPU s,
    playroom225: 14.9 vs 58.1), with cameras as close to the reference (benchmarks/results/sfm_profile/). On a
    small capture of small photos (the demo scene's 12 views at 128x96) it registered 8 of 12 where COLMAP's
    registers all, and there extraction takes seconds either way."""
    if has_cuda and device != "cpu":
        return "colmap"
    return "opencv" if num_images > EXHAUSTIVE_MAX_IMAGES else "colmap"


def resolve_modes(opts: SfmOptions, num_images: int) -> tuple[str, str, int]:
    """(matcher, mapper, max features) that "auto" (and max_features 0) stand for with this many photos."""
    matcher = opts.matcher if opts.matcher != "auto" else (
        "exhaustive" if num_images <= EXHAUSTIVE_MAX_IMAGES else "retrieval")
    mapper = opts.mapper if opts.mapper != "auto" else (
        "incremental" if num_images < GLOBAL_MIN_IMAGES else "global")
    features = opts.max_features or (
        DEFAULT_MAX_FEATURES if num_images <= EXHAUSTIVE_MAX_IMAGES else LARGE_CAPTURE_MAX_FEATURES)
    return matcher, mapper, features
