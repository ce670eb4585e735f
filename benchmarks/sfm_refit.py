"""One-off: the kept playroom225 scenes' cameras against the reference with the least-squares and the robust fit.

    .venv/bin/python benchmarks/sfm_refit.py --reference REF_SPARSE --images-dir IMAGES NAME=SCENE_DIR ...
"""
from __future__ import annotations

import argparse
import os
import shlex
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402
from sfm_modes import machine, reference_cameras  # noqa: E402
from sfm_profile import REPO, camera_errors, camera_table  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--reference", required=True)
    ap.add_argument("--images-dir", required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--note", default="")
    args = ap.parse_args()
    reference, _, source = reference_cameras(argparse.Namespace(reference=args.reference, gt_cameras=None,
                                                                images_dir=args.images_dir))
    runs = []
    for spec in args.scenes:
        name, _, scene = spec.partition("=")
        variant, _, round_ = name.rpartition("_r")
        runs.append({"variant": variant, "round": round_, "scene": scene, "agreement": camera_errors(scene, reference)})
    result = {"machine": machine(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "benchmark_command": shlex.join([os.path.relpath(sys.executable, REPO), *sys.argv]),
              "reference": source, "note": args.note, "runs": runs}

    def markdown(res: dict) -> str:
        lines = [f"# playroom225's kept SfM scenes, both camera fits ({res['date_utc'][:10]})", "",
                 f"Benchmark: `{res['benchmark_command']}`. Reference: {res['reference']}.", "", res["note"]]
        return "\n".join(lines + camera_table(res["runs"])) + "\n"

    record.write_record(record.stem("sfm_profile", args.name), result, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
