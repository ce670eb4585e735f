"""Structure from motion with pycolmap: images -> undistorted PINHOLE COLMAP scene.

Steps: SIFT extraction -> matching (every pair, or the pairs of a retrieval / sequential pairing for large
captures) -> incremental or global mapping -> undistortion -> image pyramid (images_2/4/8) -> report. Work
happens in a sibling folder `.NAME.sfm-work` with one marker per finished step, so an interrupted run resumes
where it stopped; the finished scene is then moved into SCENE_DIR in one rename (or entry by entry when
SCENE_DIR already exists, e.g. because it holds the input images), so SCENE_DIR is never half-written.

Each long pycolmap call runs in a child process (ctgs.scene.sfm_worker): COLMAP ends its process with a native
stack dump on a failed check (SQLite's "database or disk is full" among them); here that ends the child, and
`ctgs sfm` says what happened in one line. The parent meanwhile reports progress (photos extracted, pairs
matched, photos registered) from the database and the worker's progress file. pycolmap 4.x API.
"""

from __future__ import annotations

import ctypes
import dataclasses
import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields

from ctgs.errors import UserError
from ctgs.io import atomic, owner
from ctgs.io.images import image_info, list_images, read_image, resize_image, stderr_silenced, write_image
from ctgs.scene import sfm_pairs
from ctgs.scene.align import umeyama  # noqa: F401  (moved to ctgs.scene.align; kept importable from here)
from ctgs.scene.colmap import import_pycolmap

MIN_IMAGES = 3
# Fewer registered images than this fraction means SfM failed on this input (too little overlap or
# texture); training on the registered few would silently produce a bad model.
MIN_REGISTERED_FRACTION = 0.5
PYRAMID_FACTORS = (2, 4, 8)
REPORT_NAME = "sfm_report.json"
SCENE_KIND = "scene"  # the ownership marker's kind (ctgs.io.owner)
# what sfm installs in SCENE_DIR
SCENE_ENTRIES = ("images", "sparse", *(f"images_{f}" for f in PYRAMID_FACTORS), REPORT_NAME)
STEPS = ("features", "matches", "mapping", "undistort", "pyramid")
# What COLMAP's image reader decodes; float formats (EXR/HDR) must be tone-mapped to 8/16 bit first.
SFM_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

MATCHERS = ("auto", "exhaustive", "sequential", "retrieval")
MAPPERS = ("auto", "incremental", "global")
# --matcher auto: every pair up to this many photos, retrieval above. Measured on the 2-core VM
# (benchmarks/results/sfm/): retrieval pairs each photo with ~13 others (bonsai252: 3,344 pairs for 252 photos; its
# every-4th 63: 761), exhaustive with n - 1, and a pair costs about the same either way (0.08-0.09 CPU s at ~5,000
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
# The global mapper's photos with fewer 3D points than this are registered again (ctgs.scene.sfm_worker.map_global).
MIN_POINTS_PER_IMAGE = 20
# SIFT features per photo: COLMAP's default up to EXHAUSTIVE_MAX_IMAGES photos, fewer above, where matching and
# mapping cost grow with them (--max-features 0, the default: "auto"). bonsai252, retrieval + global mapper:
# 8192 -> 848 CPU s, centres within 0.29% (mean) / 0.57% (max) of the reference; 4096 -> 736 CPU s, 0.23 / 0.46%;
# 2048 -> 593 CPU s, 0.45 / 0.90% once its one lost photo is registered again. herzjesu25 keeps 8192 (4096 there:
# the same centres, focal -0.41% vs -0.39%).
DEFAULT_MAX_FEATURES = 8192
LARGE_CAPTURE_MAX_FEATURES = 4096
# Free space needed before starting, per photo feature (keypoint 24 B + descriptor 128 B) and per matched
# pair (matches and inlier matches, ~2,000 of 8 B each), plus the undistorted images and the pyramid (about
# 1.6x the input files).
BYTES_PER_FEATURE = 152
BYTES_PER_PAIR = 32_000
IMAGE_BYTES_FACTOR = 1.6
# Below this much free space a failed COLMAP call is taken for a full disk.
LOW_SPACE_BYTES = 64 << 20


@dataclass
class SfmOptions:
    matcher: str = "auto"  # "auto" | "exhaustive" | "sequential" (video frames, in name order) | "retrieval"
    mapper: str = "auto"  # "auto" | "incremental" | "global"
    max_features: int = 0  # SIFT features per photo; 0: by the number of photos (resolve_modes)
    max_image_size: int = 3200  # pixels, longest side seen by SIFT (COLMAP's default)
    threads: int = -1  # -1: all cores
    force: bool = False  # redo every step even if finished
    seed: int = 0  # mapper RANSAC seed, for reproducible runs
    device: str = "auto"  # "auto": SIFT extraction and matching on the GPU when pycolmap was built with CUDA


def resolve_modes(opts: SfmOptions, num_images: int) -> tuple[str, str, int]:
    """(matcher, mapper, max features) that "auto" (and max_features 0) stand for with this many photos."""
    matcher = opts.matcher if opts.matcher != "auto" else (
        "exhaustive" if num_images <= EXHAUSTIVE_MAX_IMAGES else "retrieval")
    mapper = opts.mapper if opts.mapper != "auto" else (
        "incremental" if num_images < GLOBAL_MIN_IMAGES else "global")
    features = opts.max_features or (
        DEFAULT_MAX_FEATURES if num_images <= EXHAUSTIVE_MAX_IMAGES else LARGE_CAPTURE_MAX_FEATURES)
    return matcher, mapper, features


@dataclass
class SfmReport:
    images_dir: str
    scene_dir: str
    given: int
    registered: int
    points: int
    mean_reprojection_error_px: float
    mean_track_length: float
    camera_model: str  # after undistortion
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    matcher: str
    unregistered: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    pycolmap_version: str = ""
    cpu_seconds: dict[str, float] = field(default_factory=dict)  # this process and its workers, per step
    mapper: str = "incremental"
    max_features: int = DEFAULT_MAX_FEATURES
    pairs: int = 0  # image pairs matched
    reregistered: list[str] = field(default_factory=list)  # photos the global mapper left without points, redone
    inputs_digest: str = ""  # of the photos' names, sizes and first bytes: which photos made this scene


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


def _work_dir(scene_dir: str) -> str:
    return os.path.join(os.path.dirname(scene_dir), f".{os.path.basename(scene_dir)}.sfm-work")


def _done(work: str, step: str) -> bool:
    return os.path.isfile(os.path.join(work, f"{step}.done"))


def _mark(work: str, step: str, seconds: float, cpu_seconds: float = 0.0) -> None:
    atomic.write_text(os.path.join(work, f"{step}.done"), f"{seconds:.3f} {cpu_seconds:.3f}\n")


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the workers)."""
    # Unix only
    import resource

    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _step_figures(marker: str) -> tuple[float, float]:
    """(seconds, CPU seconds) a step's marker recorded; NaN for what a damaged marker no longer says (the step's
    result is checked by the steps after it, not by its marker's figures)."""
    try:
        with open(marker, encoding="utf-8") as f:
            figures = [float(x) for x in f.read().split()[:2]]
    except (ValueError, UnicodeDecodeError):
        figures = []
    figures += [float("nan")] * (2 - len(figures))
    return figures[0], figures[1]


def _invalidate_from(work: str, step: str) -> None:
    for later in STEPS[STEPS.index(step):]:
        marker = os.path.join(work, f"{later}.done")
        if os.path.exists(marker):
            os.remove(marker)


class SfmStopped(UserError):
    """A pycolmap step ended its process (a full disk, a failed COLMAP check): the work folder is kept, so that the
    same command resumes from the finished steps once the cause is fixed."""

    keep_work = True


def _inputs_digest(images_dir: str, names: list[str]) -> str:
    """Which photos these are: their names, byte sizes and first 64 KiB (not their dates: a copied folder is the
    same capture)."""
    h = hashlib.sha256()
    for name in names:
        path = os.path.join(images_dir, name)
        h.update(f"{name}\0{os.path.getsize(path)}\0".encode())
        with open(path, "rb") as f:
            h.update(f.read(1 << 16))
    return h.hexdigest()


def _inputs_fingerprint(images_dir: str, names: list[str], opts: SfmOptions, matcher: str, mapper: str) -> dict:
    """What each step's result depends on; a step is redone when its part (or an earlier one) changed."""
    files = [[n, os.path.getsize(os.path.join(images_dir, n)), int(os.path.getmtime(os.path.join(images_dir, n)))]
             for n in names]
    return {"images_dir": images_dir, "files": files, "max_image_size": opts.max_image_size,
            "max_features": opts.max_features, "matcher": matcher, "mapper": mapper}


# The fingerprint keys each step depends on first (later steps depend on everything before them).
_STEP_KEYS = (("features", ("images_dir", "files", "max_image_size", "max_features")),
              ("matches", ("matcher",)), ("mapping", ("mapper",)))


def _read_fingerprint(path: str) -> dict | None:
    """The inputs a previous run recorded, or None when there is none or it cannot be read (a damaged file means the
    previous work cannot be trusted: every step is redone)."""
    try:
        with open(path, encoding="utf-8") as f:
            previous = json.load(f)
    except FileNotFoundError:
        return None
    except (ValueError, UnicodeDecodeError, RecursionError, IsADirectoryError):  # cut, garbled, nested, a folder
        print(f"ctgs: {path}: unreadable (damaged); the SfM steps are redone from the photos", file=sys.stderr)
        return None
    return previous if isinstance(previous, dict) else None


def _prepare_work(work: str, fingerprint: dict, force: bool) -> None:
    """Reuse a previous run's work folder only for the steps whose inputs and options are unchanged."""
    path = os.path.join(work, "inputs.json")
    previous = _read_fingerprint(path) if os.path.isdir(work) and not force else None
    if previous is not None:
        if previous == fingerprint:
            return
        for step, keys in _STEP_KEYS:
            if any(previous.get(k) != fingerprint[k] for k in keys):
                _invalidate_from(work, step)
                if step == "features" and os.path.exists(os.path.join(work, "database.db")):
                    os.remove(os.path.join(work, "database.db"))
                break
    else:
        shutil.rmtree(work, ignore_errors=True)
        os.makedirs(work)
    atomic.write_json(path, fingerprint, indent=None)


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


ProgressFn = Callable[[str, int, "int | None", str], None]  # (step, done, total or None, note)


def _no_progress(step: str, done: int, total: int | None, note: str) -> None:
    pass


def _count_rows(database: str, table: str) -> int | None:
    """Rows of a table of the (WAL-mode) database a worker is writing, or None while it cannot be read."""
    try:
        con = sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=0.05)
        try:
            return int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
        finally:
            con.close()
    except sqlite3.Error:
        return None


def _die_with_parent() -> None:  # pragma: no cover (runs in the child between fork and exec)
    """The worker ends when `ctgs sfm` does (SIGTERM ends the parent at once, see run_sfm)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _worker_command(job_path: str) -> list[str]:
    return [sys.executable, "-m", "ctgs.scene.sfm_worker", job_path]


def _tail(path: str, size: int = 1 << 16) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(max(0, os.path.getsize(path) - size))
            return f.read().decode(errors="replace")
    except OSError:
        return ""


_CALL_NAMES = {"extract": "SIFT extraction", "match": "matching", "map_incremental": "incremental mapping",
               "map_global": "global mapping", "undistort": "undistortion"}


def _worker_failure(call: str, log: str, work: str, code: int) -> SfmStopped:
    step = _CALL_NAMES.get(call, call)
    text = _tail(log)
    try:
        free = shutil.disk_usage(work).free
    except OSError:
        free = 0
    if "disk is full" in text or "No space left" in text or free < LOW_SPACE_BYTES:
        return SfmStopped(f"{work}: the disk is full ({free / 1e6:.0f} MB free) during {step}; free space on it "
                          f"and run the same command again: it resumes after the finished steps")
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    marks = ("Check failed", "FATAL", "Error", "error", "Exception", "exception")
    cause = next((line for line in reversed(lines) if any(m in line for m in marks)), lines[-1] if lines else "")
    cause = " ".join(cause.split())[-200:]
    how = f"signal {-code}" if code < 0 else f"exit {code}"
    return SfmStopped(f"{log}: COLMAP stopped during {step} ({how}: {cause or 'no message'}); see this log, fix "
                      f"the cause and run the same command again (it resumes after the finished steps)")


def _run_worker(work: str, call: str, job: dict, poll: Callable[[], None] | None = None,
                verbose: bool = False) -> dict:
    """Run one pycolmap call in a child process (ctgs.scene.sfm_worker), calling `poll` twice a second; its
    result dict, or SfmStopped when the child failed (a native abort included)."""
    job = {**job, "call": call, "result": os.path.join(work, f"{call}.result.json"),
           "progress": os.path.join(work, f"{call}.progress.json"), "log_level": 0}
    for stale in (job["result"], job["progress"]):
        if os.path.exists(stale):
            os.remove(stale)
    job_path = os.path.join(work, f"{call}.job.json")
    atomic.write_json(job_path, job, indent=None)
    log = os.path.join(work, f"{call}.log")
    with open(log, "wb") as out:
        proc = subprocess.Popen(_worker_command(job_path), stdin=subprocess.DEVNULL, stdout=None if verbose else out,
                                stderr=None if verbose else out, preexec_fn=_die_with_parent)
        try:
            while proc.poll() is None:
                if poll is not None:
                    poll()
                try:
                    proc.wait(0.5)
                except subprocess.TimeoutExpired:
                    pass
        except BaseException:
            proc.kill()
            proc.wait()
            raise
    if proc.returncode != 0 or not os.path.isfile(job["result"]):
        raise _worker_failure(call, log, work, proc.returncode)
    with open(job["result"]) as f:
        return json.load(f)


def _read_json(path: str) -> dict:
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def _extract(work: str, images_dir: str, names: list[str], opts: SfmOptions, progress: ProgressFn = _no_progress,
             verbose: bool = False) -> None:
    db = os.path.join(work, "database.db")
    if os.path.exists(db):
        os.remove(db)
    total = len(names)

    def poll() -> None:
        done = _count_rows(db, "keypoints")
        if done is not None:
            progress("features", done, total, "photos")

    _run_worker(work, "extract", {"database": db, "images_dir": images_dir, "names": names,
                                  "max_image_size": opts.max_image_size, "max_features": opts.max_features,
                                  "threads": opts.threads, "device": opts.device}, poll, verbose)
    progress("features", total, total, "photos")


def _match(work: str, opts: SfmOptions, matcher: str = "exhaustive", progress: ProgressFn = _no_progress,
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
        names, pairs, _ = sfm_pairs.make_pairs(db, matcher, neighbours=RETRIEVAL_NEIGHBOURS,
                                               overlap=RETRIEVAL_OVERLAP if matcher == "retrieval" else
                                               SEQUENTIAL_OVERLAP, loop_neighbours=LOOP_NEIGHBOURS, seed=opts.seed)
        pairs_file = os.path.join(work, "pairs.txt")
        sfm_pairs.write_pairs(pairs_file, names, pairs)
        total = len(pairs)

    def poll() -> None:
        done = _count_rows(db, "two_view_geometries")
        if done is not None:
            progress("matches", min(done, total), total, "pairs")

    _run_worker(work, "match", {"database": db, "pairs_file": pairs_file, "threads": opts.threads,
                                "device": opts.device}, poll, verbose)
    progress("matches", total, total, "pairs")
    return total


# Phases of the global mapper, as its log's "=== Running ... ===" lines name them (the last one seen is shown while
# it runs; other lines name phases too, e.g. a warning about bundle adjustment on the GPU during positioning).
GLOBAL_PHASES = (("running rotation averaging", "rotation averaging"), ("running track establishment", "tracks"),
                 ("running global positioning", "global positioning"),
                 ("running iterative bundle adjustment", "bundle adjustment"),
                 ("running iterative retriangulation", "retriangulation"))


def _global_phase(log: str) -> str:
    text = _tail(log, 1 << 14).lower()
    best, where = "", -1
    for needle, label in GLOBAL_PHASES:
        at = text.rfind(needle)
        if at > where:
            best, where = label, at
    return best


def _map(work: str, images_dir: str, names: list[str], opts: SfmOptions, mapper: str = "incremental",
         progress: ProgressFn = _no_progress, verbose: bool = False) -> None:
    out = os.path.join(work, "distorted")
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    total = len(names)
    call = "map_global" if mapper == "global" else "map_incremental"
    log = os.path.join(work, f"{call}.log")

    def poll() -> None:
        if mapper == "global":
            progress("mapping", 0, None, _global_phase(log))
        else:
            done = _read_json(os.path.join(work, f"{call}.progress.json")).get("registered")
            if done is not None:
                progress("mapping", min(int(done), total), total, "photos registered")

    result = _run_worker(work, call, {"database": os.path.join(work, "database.db"), "images_dir": images_dir,
                                      "output": out, "threads": opts.threads, "seed": opts.seed,
                                      "min_points": MIN_POINTS_PER_IMAGE}, poll, verbose)
    registered = int(result.get("registered", 0))
    if not result.get("models"):
        raise UserError(f"{images_dir}: SfM could not register any image pair (too little overlap or texture); "
                        f"take more overlapping photos, or try --matcher exhaustive")
    if registered < max(MIN_IMAGES, MIN_REGISTERED_FRACTION * len(names)):
        raise UserError(f"{images_dir}: SfM registered only {registered} of {len(names)} images; take more "
                        f"overlapping, textured photos (or try --matcher exhaustive / a larger --max-image-size)")
    progress("mapping", registered, total, "photos registered")


def _undistort(work: str, images_dir: str, opts: SfmOptions, progress: ProgressFn = _no_progress,
               verbose: bool = False) -> None:
    out = os.path.join(work, "scene")
    shutil.rmtree(out, ignore_errors=True)
    total = len(list_images(images_dir))

    def poll() -> None:
        folder = os.path.join(out, "images")
        done = len(os.listdir(folder)) if os.path.isdir(folder) else 0
        progress("undistort", min(done, total), total, "photos")

    _run_worker(work, "undistort", {"output": out, "model": os.path.join(work, "distorted", "best"),
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
    path = os.path.join(src, name)
    bits = 16 if image_info(path).format == "uint16" else 8
    pixels = read_image(path)
    h, w = pixels.shape[:2]
    for f in factors:
        small = resize_image(pixels, max(1, round(w / f)), max(1, round(h / f)))
        write_image(os.path.join(scene_dir, f"images_{f}", name), small, bits=bits)


def build_pyramid(scene_dir: str, factors=PYRAMID_FACTORS, progress: ProgressFn = _no_progress) -> None:
    """scene_dir/images_F for each factor F: every image shrunk by F (antialiased, OpenImageIO). One image at a
    time: write_image points file descriptor 2 at /dev/null while it reads a file back, process-wide, so writes
    from two threads can leave stderr (and the progress display) silenced."""
    src = os.path.join(scene_dir, "images")
    names = list_images(src)
    for done, name in enumerate(names, 1):
        _shrink_one(src, scene_dir, name, factors)
        progress("pyramid", done, len(names), "photos")


def _report(work: str, images_dir: str, scene_dir: str, names: list[str], opts: SfmOptions, matcher: str,
            mapper: str) -> SfmReport:
    pycolmap = import_pycolmap()

    rec = pycolmap.Reconstruction(os.path.join(work, "scene", "sparse", "0"))
    registered = {rec.images[i].name for i in rec.reg_image_ids()}
    cam = next(iter(rec.cameras.values()))
    p = [float(v) for v in cam.params]
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model.name == "SIMPLE_PINHOLE" else p[:4]
    seconds, cpu_seconds = {}, {}
    for step in STEPS:
        figures = _step_figures(os.path.join(work, f"{step}.done"))
        seconds[step], cpu_seconds[step] = figures[0], figures[1]
    pairs = _count_rows(os.path.join(work, "database.db"), "two_view_geometries") or 0
    reregistered = _read_json(os.path.join(work, "map_global.result.json")).get("reregistered", [])
    return SfmReport(
        images_dir=images_dir, scene_dir=scene_dir, given=len(names), registered=len(registered),
        points=int(rec.num_points3D()), mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        mean_track_length=float(rec.compute_mean_track_length()), camera_model=cam.model.name,
        width=int(cam.width), height=int(cam.height), fx=fx, fy=fy, cx=cx, cy=cy, matcher=matcher,
        unregistered=sorted(set(names) - registered), seconds=seconds, pycolmap_version=pycolmap.__version__,
        cpu_seconds=cpu_seconds, mapper=mapper, max_features=opts.max_features, pairs=pairs, reregistered=reregistered,
        inputs_digest=_inputs_digest(images_dir, names),
    )


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


def read_report(scene_dir: str) -> SfmReport | None:
    path = os.path.join(scene_dir, REPORT_NAME)
    if not os.path.isfile(path):
        return None
    with open(path) as f:
        data = json.load(f)
    known = {f.name for f in fields(SfmReport)}
    return SfmReport(**{k: v for k, v in data.items() if k in known})


def _check_same_photos(existing: SfmReport, images_dir: str, scene_dir: str) -> None:
    """A finished scene is reused only for the photos it was made from (UserError otherwise)."""
    if not os.path.isdir(images_dir):
        return  # check_input_images says so
    names = [n for n in list_images(images_dir) if os.path.splitext(n)[1].lower() in SFM_EXTENSIONS]
    same = existing.inputs_digest == _inputs_digest(images_dir, names) if existing.inputs_digest else \
        existing.given == len(names)  # a report written before the digest was recorded: the count only
    if not same:
        raise UserError(f"{scene_dir}: holds a finished scene made from other photos ({existing.given} photos from "
                        f"{existing.images_dir}); write this one elsewhere (-o), or pass --force to replace it")


def run_sfm(images_dir: str, scene_dir: str, opts: SfmOptions | None = None,
            status: StatusFn = lambda message: None, quiet: bool = True,
            progress: ProgressFn = _no_progress) -> tuple[SfmReport, bool]:
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
    work = _work_dir(scene_dir)
    os.makedirs(os.path.dirname(work), exist_ok=True)
    _prepare_work(work, _inputs_fingerprint(images_dir, names, opts, matcher, mapper), opts.force)
    n = len(names)
    pairs = n * (n - 1) // 2 if matcher == "exhaustive" else n * (RETRIEVAL_NEIGHBOURS + SEQUENTIAL_OVERLAP)
    try:
        if not _done(work, "pyramid"):
            check_free_space(work, images_dir, names, opts, pairs)
        for step, message, fn in (
            ("features", "SIFT features",
             lambda: _extract(work, images_dir, names, opts, progress, verbose)),
            ("matches", f"matching: {matcher}", lambda: _match(work, opts, matcher, progress, verbose)),
            ("mapping", f"mapping: {mapper}", lambda: _map(work, images_dir, names, opts, mapper, progress, verbose)),
            ("undistort", "undistorting", lambda: _undistort(work, images_dir, opts, progress, verbose)),
            ("pyramid", "images_2/4/8",
             lambda: build_pyramid(os.path.join(work, "scene"), progress=progress)),
        ):
            if _done(work, step):
                continue
            _invalidate_from(work, step)
            status(message)
            start, cpu = time.perf_counter(), _cpu_seconds()
            fn()
            _mark(work, step, time.perf_counter() - start, _cpu_seconds() - cpu)
        report = _report(work, images_dir, scene_dir, names, opts, matcher, mapper)
        atomic.write_json(os.path.join(work, "scene", REPORT_NAME), asdict(report), indent=1)
        _install(os.path.join(work, "scene"), scene_dir)
    except UserError as exc:
        if not getattr(exc, "keep_work", False):
            shutil.rmtree(work, ignore_errors=True)  # the same input would fail the same way: nothing to resume
        raise
    shutil.rmtree(work, ignore_errors=True)
    return report, True
