"""The steps of `ctgs sfm`, each in the work folder: SIFT extraction, matching, mapping, undistortion (each a worker
call, its progress polled meanwhile), the image pyramid, and the report of the finished scene."""

from __future__ import annotations

import os
import shutil
from concurrent.futures import ThreadPoolExecutor

from ctgs.errors import UserError
from ctgs.io.images import image_info, list_images, read_image, resize_image, write_image
from ctgs.scene.colmap import import_pycolmap
from ctgs.scene.sfm.markers import STEPS, inputs_digest, step_figures
from ctgs.scene.sfm.options import (LOOP_NEIGHBOURS, MIN_IMAGES, MIN_POINTS_PER_IMAGE, MIN_REGISTERED_FRACTION,
                                    PYRAMID_FACTORS, REPAIR_MIN_INLIERS, RETRIEVAL_NEIGHBOURS, RETRIEVAL_OVERLAP,
                                    SEQUENTIAL_OVERLAP, SfmOptions)
from ctgs.scene.sfm.pairs import make_pairs, write_pairs
from ctgs.scene.sfm.progress import ProgressFn, count_rows, global_phase, mean_rows, no_progress, read_json
from ctgs.scene.sfm.report import SfmReport
from ctgs.scene.sfm.supervise import run_worker

# COLMAP's two-view geometry keeps a pair with this many inlier matches or more (TwoViewGeometryOptions.min_num_inliers)
MIN_PAIR_INLIERS = 15


def extract_features(work: str, images_dir: str, names: list[str], opts: SfmOptions,
                     progress: ProgressFn = no_progress, verbose: bool = False, extractor: str = "opencv") -> None:
    """SIFT features of every photo into the work folder's database; `extractor` "opencv" (on the CPU) or "colmap"
    (pycolmap's, on a GPU): options.feature_extractor."""
    db = os.path.join(work, "database.db")
    if os.path.exists(db):
        os.remove(db)
    total = len(names)

    def poll() -> None:
        done = count_rows(db, "keypoints")
        if done is not None:
            progress("features", done, total, "photos")

    run_worker(work, "extract", {"database": db, "images_dir": images_dir, "names": names,
                                 "max_image_size": opts.max_image_size, "max_features": opts.max_features,
                                 "threads": opts.threads, "device": opts.device, "extractor": extractor}, poll, verbose)
    progress("features", total, total, "photos")


def match_pairs(work: str, opts: SfmOptions, matcher: str = "exhaustive", progress: ProgressFn = no_progress,
                verbose: bool = False) -> int:
    """Match the pairs of `matcher`; returns the number of pairs."""
    pycolmap = import_pycolmap()

    db = os.path.join(work, "database.db")
    database = pycolmap.Database.open(db)
    try:  # matching again (e.g. another --matcher) must not stack on old matches
        database.clear_matches()
        database.clear_two_view_geometries()
        n = database.num_images()
    finally:
        database.close()
    pairs_file = ""
    if matcher == "exhaustive":
        total = n * (n - 1) // 2
    else:
        progress("matches", 0, None, f"choosing pairs ({matcher})")
        names, pairs, _ = make_pairs(db, matcher, neighbours=RETRIEVAL_NEIGHBOURS,
                                     overlap=RETRIEVAL_OVERLAP if matcher == "retrieval" else SEQUENTIAL_OVERLAP,
                                     loop_neighbours=LOOP_NEIGHBOURS, seed=opts.seed)
        pairs_file = os.path.join(work, "pairs.txt")
        write_pairs(pairs_file, names, pairs)
        total = len(pairs)

    def poll() -> None:
        done = count_rows(db, "two_view_geometries")
        if done is not None:
            progress("matches", min(done, total), total, "pairs")

    run_worker(work, "match", {"database": db, "pairs_file": pairs_file, "threads": opts.threads,
                               "device": opts.device}, poll, verbose)
    progress("matches", total, total, "pairs")
    return total


def map_photos(work: str, images_dir: str, names: list[str], opts: SfmOptions, mapper: str = "incremental",
               progress: ProgressFn = no_progress, verbose: bool = False) -> None:
    out = os.path.join(work, "distorted")
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    total = len(names)
    call = "map_global" if mapper == "global" else "map_incremental"
    log = os.path.join(work, f"{call}.log")

    def poll() -> None:
        if mapper == "global":
            progress("mapping", 0, None, global_phase(log))
        else:
            done = read_json(os.path.join(work, f"{call}.progress.json")).get("registered")
            if done is not None:
                progress("mapping", min(int(done), total), total, "photos registered")

    result = run_worker(work, call, {"database": os.path.join(work, "database.db"), "images_dir": images_dir,
                                     "output": out, "threads": opts.threads, "seed": opts.seed,
                                     "min_points": MIN_POINTS_PER_IMAGE,
                                     "repair_min_inliers": REPAIR_MIN_INLIERS}, poll, verbose)
    registered = int(result.get("registered", 0))
    if not result.get("models"):
        raise UserError(f"{images_dir}: SfM could not register any image pair (too little overlap or texture); "
                        f"take more overlapping photos, or try --matcher exhaustive")
    if registered < max(MIN_IMAGES, MIN_REGISTERED_FRACTION * len(names)):
        raise UserError(f"{images_dir}: SfM registered only {registered} of {len(names)} images; take more "
                        f"overlapping, textured photos (or try --matcher exhaustive / a larger --max-image-size)")
    progress("mapping", registered, total, "photos registered")


def undistort(work: str, images_dir: str, opts: SfmOptions, progress: ProgressFn = no_progress,
              verbose: bool = False) -> None:
    out = os.path.join(work, "scene")
    shutil.rmtree(out, ignore_errors=True)
    total = len(list_images(images_dir))

    def poll() -> None:
        folder = os.path.join(out, "images")
        done = len(os.listdir(folder)) if os.path.isdir(folder) else 0
        progress("undistort", min(done, total), total, "photos")

    run_worker(work, "undistort", {"output": out, "model": os.path.join(work, "distorted", "best"),
                                   "images_dir": images_dir, "threads": opts.threads}, poll, verbose)
    poll()
    # pycolmap writes the model straight into sparse/; training and 3DGS tools expect sparse/0/.
    sparse, sparse0 = os.path.join(out, "sparse"), os.path.join(out, "sparse", "0")
    os.makedirs(sparse0, exist_ok=True)
    for name in os.listdir(sparse):
        if os.path.isfile(os.path.join(sparse, name)):
            os.replace(os.path.join(sparse, name), os.path.join(sparse0, name))
    for extra in os.listdir(out):  # stereo/, run-colmap-*.sh: dense MVS leftovers we do not use
        if extra not in ("images", "sparse"):
            path = os.path.join(out, extra)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)


def _shrink_one(src: str, scene_dir: str, name: str, factors) -> None:
    """One photo's levels from one decode."""
    path = os.path.join(src, name)
    bits = 16 if image_info(path).format == "uint16" else 8
    pixels = read_image(path)
    h, w = pixels.shape[:2]
    for f in factors:
        small = resize_image(pixels, max(1, round(w / f)), max(1, round(h / f)))
        write_image(os.path.join(scene_dir, f"images_{f}", name), small, bits=bits)


def build_pyramid(scene_dir: str, factors=PYRAMID_FACTORS, progress: ProgressFn = no_progress,
                  threads: int = -1) -> None:
    """scene_dir/images_F for each factor F: every image shrunk by F (antialiased: ctgs.io.images.resize_image), each
    photo decoded once for all its levels, `threads` photos at a time (-1: one per core). The decoding, the filter's
    matrix products and the encoding let go of Python's lock, so the threads share the cores."""
    src = os.path.join(scene_dir, "images")
    names = list_images(src)
    workers = max(1, min(len(names), (os.cpu_count() or 1) if threads <= 0 else threads))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for done, _ in enumerate(pool.map(lambda name: _shrink_one(src, scene_dir, name, factors), names), 1):
            progress("pyramid", done, len(names), "photos")


def make_report(work: str, images_dir: str, scene_dir: str, names: list[str], opts: SfmOptions, matcher: str,
                mapper: str) -> SfmReport:
    pycolmap = import_pycolmap()

    rec = pycolmap.Reconstruction(os.path.join(work, "scene", "sparse", "0"))
    registered = {rec.images[i].name for i in rec.reg_image_ids()}
    cam = next(iter(rec.cameras.values()))
    p = [float(v) for v in cam.params]
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model.name == "SIMPLE_PINHOLE" else p[:4]
    seconds, cpu_seconds = {}, {}
    for step in STEPS:
        figures = step_figures(os.path.join(work, f"{step}.done"))
        seconds[step], cpu_seconds[step] = figures[0], figures[1]
    database = os.path.join(work, "database.db")
    pairs = count_rows(database, "two_view_geometries") or 0
    features = mean_rows(database, "keypoints")
    verified = count_rows(database, "two_view_geometries", f"rows >= {MIN_PAIR_INLIERS}") or 0
    reregistered = read_json(os.path.join(work, "map_global.result.json")).get("reregistered", [])
    return SfmReport(
        images_dir=images_dir, scene_dir=scene_dir, given=len(names), registered=len(registered),
        points=int(rec.num_points3D()), mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        mean_track_length=float(rec.compute_mean_track_length()), camera_model=cam.model.name,
        width=int(cam.width), height=int(cam.height), fx=fx, fy=fy, cx=cx, cy=cy, matcher=matcher,
        unregistered=sorted(set(names) - registered), seconds=seconds, pycolmap_version=pycolmap.__version__,
        cpu_seconds=cpu_seconds, mapper=mapper, max_features=opts.max_features, pairs=pairs, reregistered=reregistered,
        features_per_photo=features, pairs_verified=verified,
        extractor=read_json(os.path.join(work, "extract.result.json")).get("extractor", ""),
        inputs_digest=inputs_digest(images_dir, names),
    )
