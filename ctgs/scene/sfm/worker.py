"""One pycolmap call of `ctgs sfm`, in a process of its own: `python -m ctgs.scene.sfm.worker JOB.json`.

`ctgs.scene.sfm.supervise` runs each long pycolmap call here so that (1) a native abort (COLMAP ends the process
with a stack dump when SQLite reports "database or disk is full", or on any failed CHECK) ends this process only,
and the parent prints one line about it; (2) the parent stays free to draw progress bars while the call runs.

JOB.json holds {"call": NAME, "result": PATH, "progress": PATH, "log_level": N, ...the call's arguments}.
The call's figures go to `result` (JSON, written at the end); the incremental mapper's registered-image count
goes to `progress` as it grows. COLMAP's log goes to stderr (the parent points it at a file).
"""

from __future__ import annotations

import json
import os
import sys
from collections import Counter, defaultdict

import numpy as np


def _write_json(path: str, obj) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(obj, f)
    os.replace(tmp, path)


def _device(pycolmap, name: str):
    return {"auto": pycolmap.Device.auto, "cpu": pycolmap.Device.cpu, "cuda": pycolmap.Device.cuda}[name]


def extract(pycolmap, job: dict) -> dict:
    """SIFT features of every photo into the database: job["extractor"] "colmap" (COLMAP's SIFT, on a GPU) or
    "opencv" (OpenCV's, on the CPU: extract_cpu)."""
    if job["extractor"] == "opencv":
        return extract_cpu(pycolmap, job)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = job["max_image_size"]
    extraction.num_threads = job["threads"]
    extraction.sift.max_num_features = job["max_features"]
    pycolmap.extract_features(job["database"], job["images_dir"], image_names=job["names"],
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=_reader(pycolmap),
                              extraction_options=extraction, device=_device(pycolmap, job["device"]))
    return {"extractor": "colmap"}


def _reader(pycolmap):
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"  # one radial term: enough for most lenses, undistorted later
    return reader


def extract_cpu(pycolmap, job: dict) -> dict:
    """OpenCV's SIFT on the CPU (ctgs.scene.sfm.sift_cpu), a photo per thread."""
    # OpenCV loads only where it extracts (the other calls and a GPU machine's extraction never need it)
    from ctgs.scene.sfm import sift_cpu

    sift_cpu.extract(pycolmap, job, _reader(pycolmap))
    return {"extractor": "opencv"}


def match(pycolmap, job: dict) -> dict:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = job["threads"]
    device = _device(pycolmap, job["device"])
    if job["pairs_file"]:
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = job["pairs_file"]
        pycolmap.match_image_pairs(job["database"], matching_options=matching, pairing_options=pairing,
                                   device=device)
    else:
        pycolmap.match_exhaustive(job["database"], matching_options=matching, device=device)
    return {}


def map_incremental(pycolmap, job: dict) -> dict:
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = job["threads"]
    options.random_seed = job["seed"]
    registered = [0]

    def one_more(count: int = 1) -> None:
        registered[0] += count
        _write_json(job["progress"], {"registered": registered[0]})

    models = pycolmap.incremental_mapping(job["database"], job["images_dir"], job["output"], options=options,
                                          initial_image_pair_callback=lambda: one_more(2),
                                          next_image_callback=one_more)
    return _keep_best(models, job)


def map_global(pycolmap, job: dict) -> dict:
    """GLOMAP's global mapper, then a repair: a photo it keeps with (nearly) no 3D points has a pose nothing
    constrains (on bonsai252 with 2,048 features one such photo sat 3,900 units from the others, which are 5
    apart), and a photo far from the photos it shares its points with is misplaced (far_from_partners), so each is
    taken out and registered again by the incremental mapper's absolute pose step, with the global model's photos
    held fixed (pycolmap.incremental_mapping from that model) and job["repair_min_inliers"] 2D-3D inliers enough
    (such photos have few points: COLMAP's 30 would drop them)."""
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = job["threads"]
    options.random_seed = job["seed"]
    models = pycolmap.global_mapping(job["database"], job["images_dir"], job["output"], options=options)
    if not models:
        return {"registered": 0, "models": 0}
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    far = set(far_from_partners(*_covisibility(best)))
    weak = [im for im in best.images.values()
            if im.has_pose and (im.num_points3D < job["min_points"] or im.image_id in far)]
    if weak:
        for im in weak:
            best.deregister_frame(im.frame_id)
        start = os.path.join(job["output"], "global")
        os.makedirs(start, exist_ok=True)
        best.write_binary(start)
        completed = os.path.join(job["output"], "completed")
        os.makedirs(completed, exist_ok=True)
        more = pycolmap.IncrementalPipelineOptions()
        more.num_threads = job["threads"]
        more.random_seed = job["seed"]
        more.fix_existing_frames = True
        more.mapper.abs_pose_min_num_inliers = job["repair_min_inliers"]
        redone = pycolmap.incremental_mapping(job["database"], job["images_dir"], completed, options=more,
                                              input_path=start)
        if redone:
            candidate = max(redone.values(), key=lambda rec: rec.num_reg_images())
            if candidate.num_reg_images() >= best.num_reg_images():
                best = candidate
    result = _keep_best({0: best}, job)
    return {**result, "models": len(models), "reregistered": [im.name for im in weak]}


# A photo placed farther from the photos it shares the most points with than this many times the typical such
# distance is misplaced (playroom225: healthy photos up to 2.5x; the misplaced ones 2,000x, or 100% of the cameras'
# spread away): it is taken out and registered again as a weak photo is.
FAR_FROM_PARTNERS = 10.0
PARTNERS = 5


def _covisibility(rec) -> tuple[dict, dict]:
    """({image id: camera centre}, {image id: Counter of the image ids it shares 3D points with}) of a model."""
    shared = defaultdict(Counter)
    for point in rec.points3D.values():
        ids = {el.image_id for el in point.track.elements}
        for a in ids:
            shared[a].update(ids - {a})
    centres = {i: im.projection_center() for i, im in rec.images.items() if im.has_pose}
    return centres, shared


def far_from_partners(centres: dict, shared: dict, partners: int = PARTNERS,
                      factor: float = FAR_FROM_PARTNERS) -> list:
    """Ids of the photos whose median distance to the `partners` photos they share the most points with exceeds
    `factor` times the median of that distance over all photos."""
    spacing = {}
    for i, centre in centres.items():
        near = [j for j, _ in shared.get(i, Counter()).most_common(partners) if j in centres]
        if near:
            spacing[i] = float(np.median([np.linalg.norm(np.asarray(centre) - np.asarray(centres[j])) for j in near]))
    if not spacing:
        return []
    typical = float(np.median(list(spacing.values())))
    return sorted(i for i, d in spacing.items() if d > factor * typical)


def _keep_best(models: dict, job: dict) -> dict:
    """The model with the most registered images goes to OUTPUT/best."""
    if not models:
        return {"registered": 0, "models": 0}
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    final = os.path.join(job["output"], "best")
    os.makedirs(final, exist_ok=True)
    best.write_binary(final)
    return {"registered": int(best.num_reg_images()), "models": len(models)}


def undistort(pycolmap, job: dict) -> dict:
    pycolmap.undistort_images(job["output"], job["model"], job["images_dir"], output_type="COLMAP",
                              num_threads=job["threads"])
    return {}


CALLS = {"extract": extract, "match": match, "map_incremental": map_incremental, "map_global": map_global,
         "undistort": undistort}


def main(argv: list[str]) -> int:
    with open(argv[1]) as f:
        job = json.load(f)
    # in the worker process only, once its job is read (pycolmap is heavy to import)
    import pycolmap

    pycolmap.logging.logtostderr = True  # no glog files in /tmp
    pycolmap.logging.minloglevel = job["log_level"]
    result = CALLS[job["call"]](pycolmap, job)
    _write_json(job["result"], result)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
