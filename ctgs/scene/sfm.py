"""Structure from motion with pycolmap (CPU): images -> undistorted PINHOLE COLMAP scene.

Steps: SIFT extraction -> exhaustive or sequential matching -> incremental mapping -> undistortion ->
image pyramid (images_2/4/8) -> report. Work happens in a sibling folder `.NAME.sfm-work` with one
marker per finished step, so an interrupted run resumes where it stopped; the finished scene is then
moved into SCENE_DIR in one rename (or entry by entry when SCENE_DIR already exists, e.g. because it
holds the input images), so SCENE_DIR is never half-written. pycolmap 4.x API.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.io.images import image_info, list_images, read_image, resize_image, stderr_silenced, write_image
from ctgs.scene.align import umeyama  # noqa: F401  (moved to ctgs.scene.align; kept importable from here)
from ctgs.scene.colmap import import_pycolmap

MIN_IMAGES = 3
# Fewer registered images than this fraction means SfM failed on this input (too little overlap or
# texture); training on the registered few would silently produce a bad model.
MIN_REGISTERED_FRACTION = 0.5
PYRAMID_FACTORS = (2, 4, 8)
REPORT_NAME = "sfm_report.json"
STEPS = ("features", "matches", "mapping", "undistort", "pyramid")
# What COLMAP's image reader decodes; float formats (EXR/HDR) must be tone-mapped to 8/16 bit first.
SFM_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


@dataclass
class SfmOptions:
    matcher: str = "exhaustive"  # "exhaustive" | "sequential" (video frames, in name order)
    max_image_size: int = 3200  # pixels, longest side seen by SIFT (COLMAP's default)
    threads: int = -1  # -1: all cores
    force: bool = False  # redo every step even if finished
    seed: int = 0  # mapper RANSAC seed, for reproducible runs


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


def _mark(work: str, step: str, seconds: float) -> None:
    atomic.write_text(os.path.join(work, f"{step}.done"), f"{seconds:.3f}\n")


def _invalidate_from(work: str, step: str) -> None:
    for later in STEPS[STEPS.index(step):]:
        marker = os.path.join(work, f"{later}.done")
        if os.path.exists(marker):
            os.remove(marker)


def _inputs_fingerprint(images_dir: str, names: list[str], opts: SfmOptions) -> dict:
    files = [[n, os.path.getsize(os.path.join(images_dir, n)), int(os.path.getmtime(os.path.join(images_dir, n)))]
             for n in names]
    return {"images_dir": images_dir, "files": files, "max_image_size": opts.max_image_size, "matcher": opts.matcher}


def _prepare_work(work: str, fingerprint: dict, force: bool) -> None:
    """Reuse a previous run's work folder only if it was made from the same inputs and options."""
    path = os.path.join(work, "inputs.json")
    if os.path.isdir(work) and not force and os.path.isfile(path):
        with open(path) as f:
            previous = json.load(f)
        if previous == fingerprint:
            return
        same_features = previous.get("files") == fingerprint["files"] and \
            previous.get("max_image_size") == fingerprint["max_image_size"]
        _invalidate_from(work, "matches" if same_features else "features")
        if not same_features and os.path.exists(os.path.join(work, "database.db")):
            os.remove(os.path.join(work, "database.db"))
    else:
        shutil.rmtree(work, ignore_errors=True)
        os.makedirs(work)
    atomic.write_json(path, fingerprint, indent=None)


def _extract(work: str, images_dir: str, names: list[str], opts: SfmOptions) -> None:
    pycolmap = import_pycolmap()

    db = os.path.join(work, "database.db")
    if os.path.exists(db):
        os.remove(db)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = opts.max_image_size
    extraction.num_threads = opts.threads
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"  # one radial term: enough for most lenses, undistorted later
    pycolmap.extract_features(db, images_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def _match(work: str, opts: SfmOptions) -> None:
    pycolmap = import_pycolmap()

    db = os.path.join(work, "database.db")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.threads
    database = pycolmap.Database.open(db)
    try:  # matching again (e.g. another --matcher) must not stack on old matches
        database.clear_matches()
        database.clear_two_view_geometries()
    finally:
        database.close()
    if opts.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.num_threads = opts.threads
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)


def _map(work: str, images_dir: str, names: list[str], opts: SfmOptions) -> None:
    pycolmap = import_pycolmap()

    out = os.path.join(work, "distorted")
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = opts.threads
    options.random_seed = opts.seed
    models = pycolmap.incremental_mapping(os.path.join(work, "database.db"), images_dir, out, options=options)
    if not models:
        raise UserError(f"{images_dir}: SfM could not register any image pair (too little overlap or texture); "
                        f"take more overlapping photos, or try --matcher exhaustive")
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    registered = best.num_reg_images()
    if registered < max(MIN_IMAGES, MIN_REGISTERED_FRACTION * len(names)):
        raise UserError(f"{images_dir}: SfM registered only {registered} of {len(names)} images; take more "
                        f"overlapping, textured photos (or try --matcher exhaustive / a larger --max-image-size)")
    final = os.path.join(work, "distorted", "best")
    os.makedirs(final, exist_ok=True)
    best.write_binary(final)


def _undistort(work: str, images_dir: str, opts: SfmOptions) -> None:
    pycolmap = import_pycolmap()

    out = os.path.join(work, "scene")
    shutil.rmtree(out, ignore_errors=True)
    pycolmap.undistort_images(out, os.path.join(work, "distorted", "best"), images_dir, output_type="COLMAP",
                              num_threads=opts.threads)
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


def build_pyramid(scene_dir: str, factors=PYRAMID_FACTORS) -> None:
    """scene_dir/images_F for each factor F: every image shrunk by F (antialiased, OpenImageIO)."""
    src = os.path.join(scene_dir, "images")
    for name in list_images(src):
        path = os.path.join(src, name)
        bits = 16 if image_info(path).format == "uint16" else 8
        pixels = read_image(path)
        h, w = pixels.shape[:2]
        for f in factors:
            small = resize_image(pixels, max(1, round(w / f)), max(1, round(h / f)))
            write_image(os.path.join(scene_dir, f"images_{f}", name), small, bits=bits)


def _report(work: str, images_dir: str, scene_dir: str, names: list[str], opts: SfmOptions) -> SfmReport:
    pycolmap = import_pycolmap()

    rec = pycolmap.Reconstruction(os.path.join(work, "scene", "sparse", "0"))
    registered = {rec.images[i].name for i in rec.reg_image_ids()}
    cam = next(iter(rec.cameras.values()))
    p = [float(v) for v in cam.params]
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model.name == "SIMPLE_PINHOLE" else p[:4]
    seconds = {}
    for step in STEPS:
        with open(os.path.join(work, f"{step}.done")) as f:
            seconds[step] = float(f.read())
    return SfmReport(
        images_dir=images_dir, scene_dir=scene_dir, given=len(names), registered=len(registered),
        points=int(rec.num_points3D()), mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        mean_track_length=float(rec.compute_mean_track_length()), camera_model=cam.model.name,
        width=int(cam.width), height=int(cam.height), fx=fx, fy=fy, cx=cx, cy=cy, matcher=opts.matcher,
        unregistered=sorted(set(names) - registered), seconds=seconds, pycolmap_version=pycolmap.__version__,
    )


def _install(built: str, scene_dir: str) -> None:
    """Move the finished scene into place: one rename if SCENE_DIR is new, else entry by entry
    (SCENE_DIR may hold the input images), with the report, the completion marker, last."""
    if not os.path.exists(scene_dir):
        os.replace(built, scene_dir)
        return
    entries = sorted(os.listdir(built), key=lambda n: n == REPORT_NAME)
    for name in entries:
        target = os.path.join(scene_dir, name)
        if os.path.isdir(target) and not os.path.islink(target):
            shutil.rmtree(target)
        elif os.path.exists(target):
            os.remove(target)
        os.replace(os.path.join(built, name), target)
    shutil.rmtree(built, ignore_errors=True)


def read_report(scene_dir: str) -> SfmReport | None:
    path = os.path.join(scene_dir, REPORT_NAME)
    if not os.path.isfile(path):
        return None
    with open(path) as f:
        return SfmReport(**json.load(f))


def run_sfm(images_dir: str, scene_dir: str, opts: SfmOptions | None = None,
            status: StatusFn = lambda message: None, quiet: bool = True) -> tuple[SfmReport, bool]:
    """Run (or resume) SfM; returns (report, True) or (existing report, False) when already done.
    `quiet` hides COLMAP's INFO/WARNING log lines (errors still show)."""
    opts = opts or SfmOptions()
    if opts.matcher not in ("exhaustive", "sequential"):
        raise UserError(f"--matcher {opts.matcher}: unknown matcher; use exhaustive or sequential")
    images_dir, scene_dir = os.path.abspath(images_dir), os.path.abspath(scene_dir)
    if scene_dir == images_dir:
        raise UserError(f"{scene_dir}: SCENE_DIR must differ from IMAGES_DIR (it gets its own images/ folder)")
    if images_dir == os.path.join(scene_dir, "images"):
        raise UserError(f"{images_dir}: the input folder would be replaced by the undistorted images; move your "
                        f"photos to {os.path.join(scene_dir, 'input')} (3DGS layout) and pass that folder")
    existing = read_report(scene_dir)
    if existing is not None and not opts.force:
        return existing, False
    if os.path.isdir(scene_dir) and os.listdir(scene_dir) and not opts.force and \
            not images_dir.startswith(scene_dir + os.sep):
        raise UserError(f"{scene_dir}: folder exists and is not a finished `ctgs sfm` scene; pass --force to "
                        f"replace its images/ and sparse/ or choose another -o")

    status("checking images")
    names = check_input_images(images_dir)
    pycolmap = import_pycolmap()

    # COLMAP's glog lines (one per image and step, and its own failure lines) would bury the spinner, the
    # report and our one-line errors.
    # logtostderr: glog would otherwise also leave log files in /tmp on every run.
    previous = pycolmap.logging.minloglevel, pycolmap.logging.logtostderr
    pycolmap.logging.minloglevel = 3 if quiet else previous[0]  # 3: FATAL only; our errors explain
    pycolmap.logging.logtostderr = True
    # SIGTERM ends `ctgs sfm` at once, even inside a long pycolmap call (a Python handler would wait for the call to
    # return): every step is resumable from the work folder and the scene is installed only at the end.
    main = threading.current_thread() is threading.main_thread()
    term = signal.signal(signal.SIGTERM, signal.SIG_DFL) if main else None
    try:
        return _run_steps(images_dir, scene_dir, names, opts, status)
    finally:
        pycolmap.logging.minloglevel, pycolmap.logging.logtostderr = previous
        if main:
            signal.signal(signal.SIGTERM, term)


def _run_steps(images_dir: str, scene_dir: str, names: list[str], opts: SfmOptions,
               status: StatusFn) -> tuple[SfmReport, bool]:
    work = _work_dir(scene_dir)
    os.makedirs(os.path.dirname(work), exist_ok=True)
    _prepare_work(work, _inputs_fingerprint(images_dir, names, opts), opts.force)
    try:
        for step, message, fn in (
            ("features", f"extracting SIFT features ({len(names)} images)", lambda: _extract(work, images_dir,
                                                                                              names, opts)),
            ("matches", f"{opts.matcher} matching", lambda: _match(work, opts)),
            ("mapping", "incremental mapping", lambda: _map(work, images_dir, names, opts)),
            ("undistort", "undistorting to PINHOLE", lambda: _undistort(work, images_dir, opts)),
            ("pyramid", "writing images_2/4/8", lambda: build_pyramid(os.path.join(work, "scene"))),
        ):
            if _done(work, step):
                continue
            _invalidate_from(work, step)
            status(message)
            start = time.perf_counter()
            fn()
            _mark(work, step, time.perf_counter() - start)
        report = _report(work, images_dir, scene_dir, names, opts)
        atomic.write_json(os.path.join(work, "scene", REPORT_NAME), asdict(report), indent=1)
        _install(os.path.join(work, "scene"), scene_dir)
    except UserError:
        shutil.rmtree(work, ignore_errors=True)  # the same input would fail the same way: nothing to resume
        raise
    shutil.rmtree(work, ignore_errors=True)
    return report, True

