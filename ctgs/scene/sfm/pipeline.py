"""`run_sfm`: the checks before any step, the steps in order (resumed from the work folder's markers), and the
finished scene moved into SCENE_DIR in one rename (or entry by entry when SCENE_DIR already exists, e.g. because it
holds the input images), so SCENE_DIR is never half-written."""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict

from ctgs.errors import UserError
from ctgs.io import atomic, owner
from ctgs.io.images import image_info, list_images, read_image, stderr_silenced
from ctgs.scene.colmap import import_pycolmap
from ctgs.scene.sfm import steps
from ctgs.scene.sfm.markers import (inputs_digest, inputs_fingerprint, invalidate_from, mark_done, prepare_work,
                                    step_done, work_dir)
from ctgs.scene.sfm.options import (DEFAULT_MAX_FEATURES, EXHAUSTIVE_MAX_IMAGES, LARGE_CAPTURE_MAX_FEATURES, MAPPERS,
                                    MATCHERS, MIN_IMAGES, PYRAMID_FACTORS, RETRIEVAL_NEIGHBOURS, SEQUENTIAL_OVERLAP,
                                    SfmOptions, feature_extractor, resolve_modes)
from ctgs.scene.sfm.progress import ProgressFn, no_progress
from ctgs.scene.sfm.report import REPORT_NAME, SfmReport, read_report

SCENE_KIND = "scene"  # the ownership marker's kind (ctgs.io.owner)

# what sfm installs in SCENE_DIR
SCENE_ENTRIES = ("images", "sparse", *(f"images_{f}" for f in PYRAMID_FACTORS), REPORT_NAME)

# What COLMAP's image reader decodes; float formats (EXR/HDR) must be tone-mapped to 8/16 bit first.
SFM_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

# Free space needed before starting, per photo feature (keypoint 24 B + descriptor 128 B) and per matched
# pair (matches and inlier matches, ~2,000 of 8 B each), plus the undistorted images and the pyramid (about
# 1.6x the input files).
BYTES_PER_FEATURE = 152
BYTES_PER_PAIR = 32_000
IMAGE_BYTES_FACTOR = 1.6

StatusFn = Callable[[str], None]


def check_input_images(images_dir: str) -> list[str]:
    """Names of the input images; UserError for a missing/empty folder, < 3 images, unreadable or
    truncated files, or mixed sizes (SfM uses one shared camera)."""
    if not os.path.isdir(images_dir):
        raise UserError(f"{images_dir}: image folder not found; pass the folder that holds your photos")
    names = list_images(images_dir)
    if not names:
        raise UserError(f"{images_dir}: no images (.png/.jpg/.exr/.tif) in this folder; put your photos there")
    unsupported = [n for n in names if os.path.splitext(n)[1].lower() not in SFM_EXTENSIONS]
    if unsupported:
        raise UserError(f"{os.path.join(images_dir, unsupported[0])}: SfM reads PNG/JPEG/TIFF only; convert "
                        f"{len(unsupported)} float image(s) (EXR/HDR) to 8/16-bit PNG first")
    if len(names) < MIN_IMAGES:
        raise UserError(f"{images_dir}: only {len(names)} image(s); SfM needs at least {MIN_IMAGES} overlapping "
                        f"photos (30+ recommended)")
    sizes: dict[tuple[int, int], str] = {}
    with stderr_silenced():  # libpng prints its own line for a corrupt file; our UserError says it once
        for name in names:
            _check_one(images_dir, name, sizes)
    return names


def _check_one(images_dir: str, name: str, sizes: dict[tuple[int, int], str]) -> None:
    """Full decode (a truncated file must fail here, not inside COLMAP) and the one-size rule."""
    path = os.path.join(images_dir, name)
    read_image(path)
    info = image_info(path)
    sizes.setdefault((info.width, info.height), name)
    if len(sizes) > 1:
        (w0, h0), n0 = next(iter(sizes.items()))
        raise UserError(f"{path}: image is {info.width}x{info.height} but {n0} is {w0}x{h0}; all images must "
                        f"have one size (one camera): resize them or split them into separate folders")


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the workers)."""
    # Unix only
    import resource

    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def check_free_space(work: str, images_dir: str, names: list[str], opts: SfmOptions, pairs: int) -> None:
    """UserError when the disk that holds the work folder has clearly too little room for this capture."""
    features = len(names) * opts.max_features * BYTES_PER_FEATURE
    images = IMAGE_BYTES_FACTOR * sum(os.path.getsize(os.path.join(images_dir, n)) for n in names)
    need = int(features + pairs * BYTES_PER_PAIR + images)
    free = shutil.disk_usage(work).free
    if free < need:
        raise UserError(f"{os.path.dirname(work)}: {free / 1e9:.2f} GB free, but sfm needs about {need / 1e9:.2f} GB "
                        f"for {len(names)} photos (SIFT database, undistorted images, images_2/4/8); free space "
                        f"there or write the scene elsewhere (-o)")


def _install(built: str, scene_dir: str) -> None:
    """Move the finished scene into place: one rename if SCENE_DIR is new, else entry by entry
    (SCENE_DIR may hold the input images), with the report, the completion marker, last. The entries it replaces
    are sfm's own (_foreign_entries said so before any step ran); the folder is marked as holding them."""
    entries = sorted(os.listdir(built), key=lambda n: n == REPORT_NAME)
    if not os.path.exists(scene_dir):
        owner.mark(built, SCENE_KIND, entries)
        os.replace(built, scene_dir)
        return
    before = owner.read_marker(scene_dir) or {}
    for name in entries:
        target = os.path.join(scene_dir, name)
        if os.path.isdir(target) and not os.path.islink(target):
            shutil.rmtree(target)
        elif os.path.lexists(target):
            os.remove(target)
        os.replace(os.path.join(built, name), target)
    shutil.rmtree(built, ignore_errors=True)
    kept = before.get("entries") or [] if before.get("kind") == SCENE_KIND else []
    owner.mark(scene_dir, SCENE_KIND, sorted(set(kept) | set(entries)))


def _foreign_entries(scene_dir: str) -> list[str]:
    """The names sfm installs that SCENE_DIR holds and sfm did not write (the user's: never replaced)."""
    if not os.path.isdir(scene_dir):
        return []
    marker = owner.read_marker(scene_dir)
    if marker is not None:
        ours = set(marker.get("entries") or []) if marker["kind"] == SCENE_KIND else set()
    else:  # a scene written before folders were marked: its report says sfm made it
        ours = set(SCENE_ENTRIES) if os.path.isfile(os.path.join(scene_dir, REPORT_NAME)) else set()
    return [n for n in SCENE_ENTRIES if os.path.lexists(os.path.join(scene_dir, n)) and n not in ours]


def _check_same_photos(existing: SfmReport, images_dir: str, scene_dir: str) -> None:
    """A finished scene is reused only for the photos it was made from (UserError otherwise)."""
    if not os.path.isdir(images_dir):
        return  # check_input_images says so
    names = [n for n in list_images(images_dir) if os.path.splitext(n)[1].lower() in SFM_EXTENSIONS]
    same = existing.inputs_digest == inputs_digest(images_dir, names) if existing.inputs_digest else \
        existing.given == len(names)  # a report written before the digest was recorded: the count only
    if not same:
        raise UserError(f"{scene_dir}: holds a finished scene made from other photos ({existing.given} photos from "
                        f"{existing.images_dir}); write this one elsewhere (-o), or pass --force to replace it")


def run_sfm(images_dir: str, scene_dir: str, opts: SfmOptions | None = None,
            status: StatusFn = lambda message: None, quiet: bool = True,
            progress: ProgressFn = no_progress) -> tuple[SfmReport, bool]:
    """Run (or resume) SfM; returns (report, True) or (existing report, False) when already done.
    `quiet` hides COLMAP's log lines (they go to a log file in the work folder); `progress(step, done, total,
    note)` is called as each step advances (total None while unknown)."""
    opts = opts or SfmOptions()
    if opts.matcher not in MATCHERS:
        raise UserError(f"--matcher {opts.matcher}: unknown matcher; use one of {', '.join(MATCHERS)}")
    if opts.mapper not in MAPPERS:
        raise UserError(f"--mapper {opts.mapper}: unknown mapper; use one of {', '.join(MAPPERS)}")
    if opts.max_features and opts.max_features < 64:
        raise UserError(f"--max-features {opts.max_features}: too few for SfM; use 1024 or more (or 0: "
                        f"{DEFAULT_MAX_FEATURES} up to {EXHAUSTIVE_MAX_IMAGES} photos, {LARGE_CAPTURE_MAX_FEATURES} "
                        f"above)")
    images_dir, scene_dir = os.path.abspath(images_dir), os.path.abspath(scene_dir)
    if scene_dir == images_dir:
        raise UserError(f"{scene_dir}: SCENE_DIR must differ from IMAGES_DIR (it gets its own images/ folder)")
    if images_dir == os.path.join(scene_dir, "images"):
        raise UserError(f"{images_dir}: the input folder would be replaced by the undistorted images; move your "
                        f"photos to {os.path.join(scene_dir, 'input')} (3DGS layout) and pass that folder")
    existing = read_report(scene_dir)
    if existing is not None and not opts.force:
        _check_same_photos(existing, images_dir, scene_dir)
        return existing, False
    if os.path.isdir(scene_dir) and os.listdir(scene_dir) and not opts.force and \
            not images_dir.startswith(scene_dir + os.sep):
        raise UserError(f"{scene_dir}: folder exists and is not a finished `ctgs sfm` scene; pass --force to "
                        f"replace its images/ and sparse/ or choose another -o")
    foreign = _foreign_entries(scene_dir)
    if foreign:
        raise UserError(f"{scene_dir}: holds {', '.join(foreign)} that `ctgs sfm` did not write; nothing was changed: "
                        "choose another -o folder")

    status("checking images")
    names = check_input_images(images_dir)
    # SIGTERM ends `ctgs sfm` at once, even inside a long pycolmap call (a Python handler would wait for the call to
    # return): every step is resumable from the work folder, the scene is installed only at the end, and the
    # worker process ends with its parent (PR_SET_PDEATHSIG).
    main = threading.current_thread() is threading.main_thread()
    term = signal.signal(signal.SIGTERM, signal.SIG_DFL) if main else None
    try:
        return _run_steps(images_dir, scene_dir, names, opts, status, progress, not quiet)
    finally:
        if main:
            signal.signal(signal.SIGTERM, term)


def _run_steps(images_dir: str, scene_dir: str, names: list[str], opts: SfmOptions, status: StatusFn,
               progress: ProgressFn, verbose: bool) -> tuple[SfmReport, bool]:
    matcher, mapper, features = resolve_modes(opts, len(names))
    opts = dataclasses.replace(opts, max_features=features)
    extractor = feature_extractor(opts.device, bool(import_pycolmap().has_cuda), len(names))
    work = work_dir(scene_dir)
    os.makedirs(os.path.dirname(work), exist_ok=True)
    prepare_work(work, inputs_fingerprint(images_dir, names, opts, matcher, mapper, extractor), opts.force)
    n = len(names)
    pairs = n * (n - 1) // 2 if matcher == "exhaustive" else n * (RETRIEVAL_NEIGHBOURS + SEQUENTIAL_OVERLAP)
    try:
        if not step_done(work, "pyramid"):
            check_free_space(work, images_dir, names, opts, pairs)
        for step, message, fn in (
            ("features", "SIFT features",
             lambda: steps.extract_features(work, images_dir, names, opts, progress, verbose, extractor)),
            ("matches", f"matching: {matcher}", lambda: steps.match_pairs(work, opts, matcher, progress, verbose)),
            ("mapping", f"mapping: {mapper}",
             lambda: steps.map_photos(work, images_dir, names, opts, mapper, progress, verbose)),
            ("undistort", "undistorting", lambda: steps.undistort(work, images_dir, opts, progress, verbose)),
            ("pyramid", "images_2/4/8",
             lambda: steps.build_pyramid(os.path.join(work, "scene"), progress=progress, threads=opts.threads)),
        ):
            if step_done(work, step):
                continue
            invalidate_from(work, step)
            status(message)
            start, cpu = time.perf_counter(), _cpu_seconds()
            fn()
            mark_done(work, step, time.perf_counter() - start, _cpu_seconds() - cpu)
        report = steps.make_report(work, images_dir, scene_dir, names, opts, matcher, mapper)
        atomic.write_json(os.path.join(work, "scene", REPORT_NAME), asdict(report), indent=1)
        _install(os.path.join(work, "scene"), scene_dir)
    except UserError as exc:
        if not getattr(exc, "keep_work", False):
            shutil.rmtree(work, ignore_errors=True)  # the same input would fail the same way: nothing to resume
        raise
    shutil.rmtree(work, ignore_errors=True)
    return report, True
