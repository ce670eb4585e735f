"""The report a finished scene holds (SCENE_DIR/sfm_report.json): what was given, registered and measured."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, fields

from ctgs.scene.sfm.options import DEFAULT_MAX_FEATURES

REPORT_NAME = "sfm_report.json"


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
    features_per_photo: float = 0.0  # SIFT features, mean over the photos
    pairs_verified: int = 0  # matched pairs whose two-view geometry kept 15+ inlier matches
    extractor: str = ""  # whose SIFT: "opencv" (CPU) or "colmap" (GPU)


def read_report(scene_dir: str) -> SfmReport | None:
    path = os.path.join(scene_dir, REPORT_NAME)
    if not os.path.isfile(path):
        return None
    with open(path) as f:
        data = json.load(f)
    known = {f.name for f in fields(SfmReport)}
    return SfmReport(**{k: v for k, v in data.items() if k in known})
