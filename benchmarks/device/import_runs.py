"""Runs trained on the device (benchmarks/device/paired_many.sh: one run_NAME.tgz each) made into
benchmarks/paired.py's finished runs on this machine: unpacked into WORK/NAME, exported and evaluated here against
this machine's copy of the scene (`ctgs eval --scene`; LPIPS included where the VGG weights are), with the
paired_record.json that paired.py reuses. NAME is LABEL_sSEED (the jobs file's names, e.g. balanced_s0).

    .venv/bin/python benchmarks/device/import_runs.py FILES_DIR --work WORK --scene /work/scenes/herzjesu25 \\
        --commit ab12cd3
    .venv/bin/python benchmarks/paired.py --scene /work/scenes/herzjesu25 --images images_4 --a balanced --b fast \\
        --seeds 0 1 2 --work WORK --tag NAME --trained-on "an NVIDIA H200 (...)"

FILES_DIR holds the call's files (run_*.tgz, and checks.tgz whose status.json gives each run's wall seconds and
command). --commit: the checkout the device call sent (the device's own git may be stale).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import tarfile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from paired import finish  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files")
    ap.add_argument("--work", required=True)
    ap.add_argument("--scene", required=True, help="this machine's copy of the scene the runs trained on")
    ap.add_argument("--commit", required=True, help="the checkout the device call sent")
    args = ap.parse_args()
    from ctgs.metrics.vgg_weights import find_vgg16

    lpips = find_vgg16().state is not None
    status = {}
    checks = os.path.join(args.files, "checks.tgz")
    if os.path.exists(checks):
        with tarfile.open(checks) as tf:
            member = next((m for m in tf.getmembers() if os.path.basename(m.name) == "status.json"), None)
            if member is not None:
                status = json.load(tf.extractfile(member))["jobs"]
    tgzs = sorted(glob.glob(os.path.join(args.files, "run_*.tgz")))
    if not tgzs:
        raise SystemExit(f"import_runs.py: no run_*.tgz in {args.files}; fetch the device call's files first")
    scene = os.path.abspath(args.scene)
    for tgz in tgzs:
        name = os.path.basename(tgz)[len("run_"):-len(".tgz")]
        m = re.fullmatch(r"(.+)_s(\d+)", name)
        if m is None:
            raise SystemExit(f"import_runs.py: {tgz}: name the job LABEL_sSEED (e.g. balanced_s0)")
        label, seed = m.group(1), int(m.group(2))
        run = os.path.join(args.work, name)
        if os.path.exists(os.path.join(run, "paired_record.json")):
            print(f"{name}: already imported")
            continue
        os.makedirs(run, exist_ok=True)
        with tarfile.open(tgz) as tf:
            tf.extractall(run, filter="data")
        job = status.get(name, {})
        command = "-m ctgs train " + " ".join(job.get("args", ["?"]))
        rec = finish(run, label, seed, args.commit, command, float(job.get("wall_s") or "nan"), lpips, run + ".log",
                     scene=scene)
        rec["trained_on"] = "device (benchmarks/device/paired_many.sh)"
        with open(os.path.join(run, "paired_record.json"), "w") as fh:
            json.dump(rec, fh, indent=1)
        print(f"{name}: {rec['psnr']:.2f} dB, SSIM {rec['ssim']:.3f}, LPIPS {rec['lpips']}, {rec['params']} params")


if __name__ == "__main__":
    main()
