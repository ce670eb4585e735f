"""`ctgs sfm` pairing / mapper / feature-budget modes, run back to back on one capture, against reference cameras.

    .venv/bin/python benchmarks/sfm_modes.py IMAGES_DIR --scene NAME (--reference SPARSE_DIR | --gt-cameras DIR)
        --mode MATCHER/MAPPER[/MAX_FEATURES] [--mode ...] [--threads 2] [--work DIR] [--note TEXT ...]

Each mode is the user's command, `ctgs sfm IMAGES_DIR -o WORK/MODE --matcher M --mapper P --max-features F
--threads T --force`, run as a child process (its wall time and the machine's load average are recorded before and
after). Its cameras are then compared with the reference: the similarity (Umeyama, with scale) that best maps the
estimated camera centres onto the reference centres, each centre's error as a percentage of the reference camera
spread (radius: the largest distance of a reference centre from their centroid), the rotation error after that
similarity, and the focal length's relative error. The reference is either a COLMAP model (--reference: its
PINHOLE / SIMPLE_PINHOLE focal, in pixels of IMAGES_DIR) or Strecha-format ground-truth cameras (--gt-cameras, as
benchmarks/sfm_accuracy.py reads them; their K is scaled by the input width / the GT width).

Per mode it writes benchmarks/results/sfm_modes/<scene>_<matcher>-<mapper>-<features>_<commit>.json and .md (machine,
date, command, load average at start and end, per-step wall and CPU seconds, registered photos, reprojection
error, camera agreement) and, for the whole invocation, <scene>_modes_<commit>.md: the modes side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import shutil
import subprocess
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, "benchmarks"))

from measures.align import align_cameras, camera_poses  # noqa: E402
from ctgs.scene.sfm import read_report  # noqa: E402
from sfm_accuracy import machine_info, read_gt_dir, write_atomic  # noqa: E402

RESULTS = os.path.join(REPO, "benchmarks", "results", "sfm_modes")


def _commit() -> str:
    """The checkout's commit, "+" when ctgs's sfm code differs from it (others' uncommitted work elsewhere in the
    shared checkout does not count)."""
    out = subprocess.run(["git", "-C", REPO, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    sfm_code = ["ctgs/scene/sfm", "ctgs/stages/sfm.py"]
    changed = subprocess.run(["git", "-C", REPO, "status", "--porcelain", *sfm_code],
                             capture_output=True, text=True).stdout.strip()
    return (out.stdout.strip() or "unknown") + ("+" if changed else "")


def machine() -> dict:
    """sfm_accuracy's machine description (without its git, date and load: these records hold their own), and
    whether pycolmap has CUDA."""
    import pycolmap

    info = machine_info()
    for key in ("git", "date_utc", "load_average", "numpy"):
        info.pop(key, None)
    return {**info, "cuda": bool(pycolmap.has_cuda)}


def _poses(rec, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres [C, 3] and camera-to-world rotations [C, 3, 3] of the named images of a pycolmap model."""
    by_name = {im.name: im for im in rec.images.values()}
    viewmats = []
    for n in names:
        m = np.eye(4)
        m[:3, :] = by_name[n].cam_from_world().matrix()
        viewmats.append(m)
    return camera_poses(np.stack(viewmats))


def _focal(cam) -> float:
    p = [float(v) for v in cam.params]
    return p[0] if cam.model.name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else 0.5 * (p[0] + p[1])


def reference_cameras(args) -> tuple[dict, float, str]:
    """name -> (centre, camera-to-world), the reference focal in pixels of the input images, and its source."""
    import pycolmap

    if args.reference:
        rec = pycolmap.Reconstruction(args.reference)
        names = sorted(im.name for im in rec.images.values())
        centres, rotations = _poses(rec, names)
        focal = float(np.mean([_focal(c) for c in rec.cameras.values()]))
        return {n: (c, r) for n, c, r in zip(names, centres, rotations)}, focal, f"COLMAP model {args.reference}"
    from ctgs.io.images import image_info, list_images

    gt = read_gt_dir(args.gt_cameras)
    first = next(iter(gt.values()))
    width = image_info(os.path.join(args.images_dir, list_images(args.images_dir)[0])).width
    scale = width / first.width
    focal = float(np.mean([0.5 * (g.K[0, 0] + g.K[1, 1]) for g in gt.values()]) * scale)
    return ({n: (g.center, g.cam_to_world) for n, g in gt.items()}, focal,
            f"ground truth {args.gt_cameras} (K x {scale:g})")


def agreement(scene_dir: str, reference: dict, ref_focal: float) -> dict:
    import pycolmap

    rec = pycolmap.Reconstruction(os.path.join(scene_dir, "sparse", "0"))
    names = sorted(im.name for im in rec.images.values() if im.name in reference)
    est_c, est_r = _poses(rec, names)
    ref_c = np.stack([reference[n][0] for n in names])
    ref_r = np.stack([reference[n][1] for n in names])
    result = align_cameras(est_c, est_r, ref_c, ref_r)
    ce = result.center_errors / result.spread_radius * 100
    focals = [_focal(c) for c in rec.cameras.values()]
    return {"compared": len(names), "reference_images": len(reference),
            "center_error_mean_pct": float(ce.mean()), "center_error_max_pct": float(ce.max()),
            "rotation_error_mean_deg": float(result.rotation_errors_deg.mean()),
            "rotation_error_max_deg": float(result.rotation_errors_deg.max()),
            "focal_px": float(np.mean(focals)), "reference_focal_px": ref_focal,
            "focal_error_pct": float(100 * (np.mean(focals) / ref_focal - 1))}


def run_in_tmux(cmd: list[str], args) -> subprocess.CompletedProcess:
    """Run `cmd` in a detached tmux terminal (so that ctgs draws its progress bars) and append what the terminal
    shows every --capture-every seconds to the --capture file."""
    session = f"sfm_modes_{os.getpid()}"
    done = os.path.join(args.work, f".{session}.exit")
    if os.path.exists(done):
        os.remove(done)
    shell = f"cd {shlex.quote(args.work)} && {shlex.join(cmd)}; echo $? > {shlex.quote(done)}; sleep 3600"
    subprocess.run(["tmux", "new-session", "-d", "-s", session, "-x", "120", "-y", "24", shell], check=True)
    start = time.perf_counter()
    with open(args.capture, "a") as log:
        log.write(f"$ {shlex.join(cmd)}\n")
        while True:
            finished = os.path.exists(done)
            time.sleep(0.5 if finished else args.capture_every)
            pane = subprocess.run(["tmux", "capture-pane", "-p", "-t", session], capture_output=True, text=True).stdout
            log.write(f"--- {time.perf_counter() - start:.0f} s, {time.strftime('%H:%M:%S', time.gmtime())} UTC, load "
                      f"average {os.getloadavg()[0]:.1f} ---\n{pane.rstrip()}\n")
            log.flush()
            if finished:
                break
    subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
    with open(done) as f:
        code = int(f.read().strip() or 1)
    os.remove(done)
    return subprocess.CompletedProcess(cmd, code, "", pane)


def run_mode(args, mode: str, reference: dict, ref_focal: float, ref_source: str, commit: str) -> dict:
    ctgs = shlex.split(args.ctgs) if args.ctgs else [os.path.join(os.path.dirname(sys.executable), "ctgs")]
    if mode == "default":  # the command's own defaults (e.g. an older ctgs without these options)
        matcher = mapper = features = "default"
        options = []
    else:
        parts = mode.split("/")
        matcher, mapper = parts[0], parts[1] if len(parts) > 1 else "auto"
        features = parts[2] if len(parts) > 2 else "auto"
        options = ["--matcher", matcher, "--mapper", mapper, "--max-features", "0" if features == "auto" else features]
    out = os.path.join(args.work, f"{args.scene}_{matcher}-{mapper}-{features}")
    cmd = [*ctgs, "sfm", args.images_dir, "-o", out, *options, "--threads", str(args.threads), "--force"]
    load_start, date = list(os.getloadavg()), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    start, cpu = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    # Run from the work folder: `python -m ctgs` would otherwise import the checkout's ctgs from the current folder.
    if args.capture:
        proc = run_in_tmux(cmd, args)
    else:
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=args.work)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime + after.ru_stime) - (cpu.ru_utime + cpu.ru_stime)
    load_end = list(os.getloadavg())
    record = {"scene": args.scene, "mode": {"matcher": matcher, "mapper": mapper, "max_features": features},
              "machine": machine(), "commit": commit, "date_utc": date, "command": shlex.join(cmd),
              "benchmark_command": shlex.join([os.path.relpath(sys.executable, REPO), *sys.argv]),
              "load_average_start": load_start, "load_average_end": load_end, "wall_s": wall,
              "cpu_s": cpu_s,
              "exit_code": proc.returncode, "stderr_tail": proc.stderr[-2000:] if proc.returncode else "",
              "reference": ref_source, "notes": args.note}
    if proc.returncode == 0:
        report = read_report(out)
        if args.capture:  # the tmux server, not this process, was the command's parent
            record["cpu_s"] = sum(report.cpu_seconds.values())
        record["report"] = vars(report)
        record["agreement"] = agreement(out, reference, ref_focal)
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)
    return record


def _fmt_load(load: list[float]) -> str:
    return ", ".join(f"{x:.1f}" for x in load)


def _steps(r: dict, key: str) -> str:
    values = r["report"].get(key) or {}
    return " / ".join(f"{v:.0f}" for v in values.values()) + f" = {sum(values.values()):.0f}"


def markdown(r: dict) -> str:
    m = r["machine"]
    lines = [f"# sfm {r['scene']}: --matcher {r['mode']['matcher']} --mapper {r['mode']['mapper']} --max-features "
             f"{r['mode']['max_features']} ({r['date_utc'][:10]}, {r['commit']})", "",
             f"Machine: {m['cpu_model']}, {m['logical_cores']} logical cores ({m['hostname']}, {m['platform']}), "
             f"python {m['python']}, pycolmap {m['pycolmap']} (CUDA: {m['cuda']}).",
             f"Date: {r['date_utc']}. Load average (1, 5, 15 min) at the start {_fmt_load(r['load_average_start'])}, "
             f"at the end {_fmt_load(r['load_average_end'])}.",
             f"Command: `{r['command']}` (exit {r['exit_code']}, {r['wall_s']:.0f} s wall, {r['cpu_s']:.0f} s CPU).",
             f"Benchmark: `{r['benchmark_command']}`. Reference: {r['reference']}.", ""]
    lines += [f"Note: {n}" for n in r["notes"]] + ([""] if r["notes"] else [])
    if r["exit_code"] != 0:
        return "\n".join(lines + ["Failed:", "", "```", r["stderr_tail"], "```", ""])
    rep, a = r["report"], r["agreement"]
    steps = list(rep["seconds"])
    lines += ["| | " + " | ".join(steps) + " | total |", "|---|" + "---:|" * (len(steps) + 1),
              "| wall s | " + " | ".join(f"{rep['seconds'][s]:.1f}" for s in steps)
              + f" | {sum(rep['seconds'].values()):.1f} |",
              "| CPU s | " + " | ".join(f"{rep['cpu_seconds'].get(s, float('nan')):.1f}" for s in steps)
              + f" | {sum(rep['cpu_seconds'].values()):.1f} |", "",
              f"Registered {rep['registered']} / {rep['given']} photos; {rep['pairs']} pairs matched; {rep['points']} "
              f"points; mean reprojection error {rep['mean_reprojection_error_px']:.3f} px; mean track length "
              f"{rep['mean_track_length']:.2f}.", "",
              f"Cameras vs the reference ({a['compared']} of {a['reference_images']} reference photos compared, after "
              f"a similarity fit on the centres): centre error mean {a['center_error_mean_pct']:.3f}%, max "
              f"{a['center_error_max_pct']:.3f}% of the camera spread radius; rotation error mean "
              f"{a['rotation_error_mean_deg']:.3f} deg, max {a['rotation_error_max_deg']:.3f} deg; focal "
              f"{a['focal_px']:.2f} px vs {a['reference_focal_px']:.2f} px ({a['focal_error_pct']:+.3f}%).", ""]
    return "\n".join(lines)


def summary(records: list[dict], args) -> str:
    r0 = records[0]
    lines = [f"# sfm modes on {args.scene}, back to back ({r0['date_utc'][:10]}, {r0['commit']})", "",
             f"Machine: {r0['machine']['cpu_model']}, {r0['machine']['logical_cores']} logical cores. Benchmark: "
             f"`{r0['benchmark_command']}`. Reference: {r0['reference']}. Steps: features / matches / mapping / "
             "undistort / pyramid.", ""]
    lines += [f"Note: {n}" for n in args.note] + ([""] if args.note else [])
    lines += ["| mode | start | load avg start / end | wall s per step | CPU s per step | whole command wall / CPU s "
              "| registered | pairs | reproj px | centre err mean / max % | rot err mean deg | focal err % |",
              "|---|---|---|---|---|---|---:|---:|---:|---|---:|---:|"]
    for r in records:
        mode = "/".join(dict.fromkeys(str(v) for v in r["mode"].values()))
        load = f"{r['load_average_start'][0]:.1f} / {r['load_average_end'][0]:.1f}"
        if r["exit_code"] != 0:
            lines.append(f"| {mode} | {r['date_utc'][11:19]} | {load} | failed (exit {r['exit_code']}) "
                         "| | | | | | | | |")
            continue
        rep, a = r["report"], r["agreement"]
        lines.append(f"| {mode} | {r['date_utc'][11:19]} | {load} | {_steps(r, 'seconds')} | "
                     f"{_steps(r, 'cpu_seconds')} | {r['wall_s']:.0f} / {r['cpu_s']:.0f} | {rep['registered']}/"
                     f"{rep['given']} | {rep['pairs']} | {rep['mean_reprojection_error_px']:.3f} "
                     f"| {a['center_error_mean_pct']:.3f} / {a['center_error_max_pct']:.3f} | "
                     f"{a['rotation_error_mean_deg']:.3f} | {a['focal_error_pct']:+.3f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("images_dir", help="the photos")
    ap.add_argument("--scene", required=True, help="scene name used in the record names (e.g. bonsai252)")
    ref = ap.add_mutually_exclusive_group(required=True)
    ref.add_argument("--reference", help="a COLMAP model folder (sparse/0) with the reference cameras")
    ref.add_argument("--gt-cameras", help="a folder of Strecha-format NAME.camera ground-truth files")
    ap.add_argument("--mode", action="append", required=True,
                    help="MATCHER/MAPPER[/MAX_FEATURES], e.g. retrieval/global/4096 (repeatable; run in this order)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ctgs", default="", help="the command that runs ctgs (default: this venv's ctgs), e.g. "
                    "'env PYTHONPATH=/tmp/old python -m ctgs' for an older checkout; mode 'default' passes none of "
                    "--matcher/--mapper/--max-features")
    ap.add_argument("--work", default="/tmp/sfm_modes", help="where the scenes are made (removed unless --keep)")
    ap.add_argument("--keep", action="store_true", help="keep the scenes made")
    ap.add_argument("--note", action="append", default=[], help="a line recorded in the results (repeatable)")
    ap.add_argument("--capture", help="run each command in a tmux terminal and append its screen to this file every "
                    "--capture-every seconds (the progress display); CPU seconds then come from sfm_report.json")
    ap.add_argument("--capture-every", type=float, default=30.0)
    ap.add_argument("--tag", default="", help="appended to the record names (e.g. a subset's name)")
    args = ap.parse_args()
    os.makedirs(args.work, exist_ok=True)
    os.makedirs(RESULTS, exist_ok=True)
    commit = _commit()
    reference, ref_focal, ref_source = reference_cameras(args)
    records = []
    for mode in args.mode:
        record = run_mode(args, mode, reference, ref_focal, ref_source, commit)
        records.append(record)
        m = record["mode"]
        stem = os.path.join(RESULTS, f"{args.scene}{args.tag}_{m['matcher']}-{m['mapper']}-{m['max_features']}_"
                                     f"{commit}")
        write_atomic(stem + ".json", json.dumps(record, indent=1) + "\n")
        write_atomic(stem + ".md", markdown(record))
        print(markdown(record), flush=True)
    text = summary(records, args)
    write_atomic(os.path.join(RESULTS, f"{args.scene}{args.tag}_modes_{commit}.md"), text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
