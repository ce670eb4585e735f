"""SfM accuracy against ground-truth cameras: a `ctgs sfm` scene vs Strecha-format `.camera` files.

    .venv/bin/python benchmarks/sfm_accuracy.py SCENE_DIR GT_DIR [--sfm-command TEXT] [--time-log FILE]
        [--gt-scale S] [--out PREFIX] [--note TEXT ...]

SCENE_DIR: a `ctgs sfm` output (sparse/0 read with ctgs.scene.colmap; sfm_report.json for the step times and
the input image folder). GT_DIR: one `NAME.camera` per input image NAME (K 3x3, 3 radial distortion terms,
camera-to-world R 3x3, centre C, width height; /work/shared/data/README.md). Images and GT files are matched
by name.

What it reports (written to PREFIX.json and PREFIX.md; default benchmarks/results/sfm_accuracy/<scene>_<commit>):
- registered / given images, and images with no GT file;
- camera centres: the similarity (Umeyama, with scale) that best maps the estimated centres onto the GT
  centres, then each camera's centre error in GT units, mean and max, also as a percentage of the camera
  spread: spread radius = the largest distance of a GT centre from the GT centroid (and of the spread
  diameter = the largest distance between two GT centres);
- rotation error after the same similarity (the angle between the aligned estimated and the GT camera
  orientation, degrees; orientations do not enter the fit, so this checks it independently);
- intrinsics in pixels of the input images (the GT K scaled by input size / GT size, --gt-scale):
  COLMAP's undistortion keeps the focal length and the pixel pitch and only crops the image (1536x1024 ->
  1535x1023 here) and scales the principal point with the size, so the estimated f compares directly with
  the scaled GT fx, fy, and the estimated principal point is mapped back by input size / undistorted size;
- the time of each sfm step (sfm_report.json), and with --time-log the wall / CPU time and peak memory of
  the whole `ctgs sfm` run from a `/usr/bin/time -v` log.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shlex
import socket
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, "benchmarks"))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

from ctgs.errors import UserError  # noqa: E402
from measures.align import align_cameras, camera_poses, rotation_vectors  # noqa: E402
from ctgs.scene.colmap import find_model_dir, read_colmap_model  # noqa: E402
from ctgs.scene.sfm import read_report  # noqa: E402

GT_SUFFIX = ".camera"
GT_NUMBERS = 9 + 3 + 9 + 3 + 2  # K, distortion, R, C, width height
# The GT rotations are printed with 6 decimals: |R R^T - I| is ~1e-6 there; 1e-3 catches a wrong file
# (or a world-to-camera matrix with a flipped axis, det -1) without rejecting the rounding.
ROTATION_TOLERANCE = 1e-3


@dataclass(frozen=True)
class GtCamera:
    K: np.ndarray  # [3, 3] pixels of the GT image size
    distortion: np.ndarray  # [3]
    cam_to_world: np.ndarray  # [3, 3], columns = camera axes in world
    center: np.ndarray  # [3] world (GT units)
    width: int
    height: int


def read_gt_camera(path: str) -> GtCamera:
    try:
        with open(path) as f:
            values = [float(v) for v in f.read().split()]
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read a ground-truth camera ({exc}); expected {GT_NUMBERS} numbers") from None
    if len(values) != GT_NUMBERS:
        raise UserError(f"{path}: {len(values)} numbers, expected {GT_NUMBERS} (K 3x3, 3 distortion, R 3x3, C, "
                        f"width height)")
    v = np.array(values)
    R = v[12:21].reshape(3, 3)
    if np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        raise UserError(f"{path}: R (numbers 13-21) is not a rotation (det {np.linalg.det(R):.4f}); expected the "
                        f"camera-to-world rotation")
    return GtCamera(v[:9].reshape(3, 3), v[9:12], R, v[21:24], int(v[24]), int(v[25]))


def read_gt_dir(gt_dir: str) -> dict[str, GtCamera]:
    """Image name -> GT camera, from GT_DIR/<image name>.camera."""
    if not os.path.isdir(gt_dir):
        raise UserError(f"{gt_dir}: ground-truth folder not found; pass the folder of NAME.camera files")
    files = sorted(n for n in os.listdir(gt_dir) if n.endswith(GT_SUFFIX))
    if not files:
        raise UserError(f"{gt_dir}: no *{GT_SUFFIX} files; pass the folder of NAME.camera files")
    return {n[: -len(GT_SUFFIX)]: read_gt_camera(os.path.join(gt_dir, n)) for n in files}


def input_image_size(report, names: list[str]) -> tuple[int, int] | None:
    """(width, height) of the photos `ctgs sfm` read, or None when they are gone."""
    from ctgs.io.images import image_info

    if report is None:
        return None
    for name in names:
        path = os.path.join(report.images_dir, name)
        if os.path.isfile(path):
            info = image_info(path)
            return info.width, info.height
    return None


def gt_scale(args, report, gt: dict[str, GtCamera], names: list[str]) -> tuple[float, str]:
    """Input pixels per GT pixel, and how it was found."""
    if args.gt_scale is not None:
        return args.gt_scale, "--gt-scale"
    size = input_image_size(report, names)
    if size is None:
        raise UserError(f"{args.scene_dir}: the input images named in sfm_report.json are not readable, so the GT "
                        f"intrinsics cannot be scaled to them; pass --gt-scale (input width / GT width)")
    g = gt[names[0]]
    sx, sy = size[0] / g.width, size[1] / g.height
    if abs(sx - sy) > 1e-3 * sx:
        raise UserError(f"{report.images_dir}: input images are {size[0]}x{size[1]} but the GT is for "
                        f"{g.width}x{g.height} (not one scale); pass --gt-scale")
    return sx, f"input images {size[0]}x{size[1]} / GT {g.width}x{g.height}"


def parse_time_log(path: str) -> dict:
    """Wall / CPU seconds, peak memory and the command from a `/usr/bin/time -v` log."""
    with open(path) as f:
        text = f.read()

    def field(label: str) -> str | None:
        m = re.search(rf"^\s*{re.escape(label)}: (.*)$", text, re.MULTILINE)
        return m.group(1).strip() if m else None

    wall = field("Elapsed (wall clock) time (h:mm:ss or m:ss)")
    if wall is None:
        raise UserError(f"{path}: not a `/usr/bin/time -v` log (no 'Elapsed (wall clock) time' line)")
    seconds = 0.0
    for part in wall.split(":"):
        seconds = seconds * 60 + float(part)
    user, system = float(field("User time (seconds)") or "nan"), float(field("System time (seconds)") or "nan")
    return {"command": (field("Command being timed") or "").strip('"'), "wall_s": seconds, "user_s": user,
            "system_s": system, "cpu_s": user + system, "max_rss_mb": float(field("Maximum resident set size "
                                                                                   "(kbytes)") or "nan") / 1024,
            "exit_status": field("Exit status")}


def machine_info() -> dict:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    import pycolmap

    try:
        commit = subprocess.run(["git", "-C", REPO, "describe", "--always", "--dirty"], capture_output=True,
                                text=True).stdout.strip()
    except OSError:
        commit = ""
    return {"hostname": socket.gethostname(), "cpu_model": cpu, "logical_cores": os.cpu_count(),
            "platform": platform.platform(), "python": platform.python_version(), "numpy": np.__version__,
            "pycolmap": pycolmap.__version__, "git": commit, "load_average": list(os.getloadavg()),
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def intrinsics(model, names: list[str], gt: dict[str, GtCamera], scale: float, input_size) -> dict:
    """Estimated vs GT intrinsics, both in pixels of the input images."""
    by_name = {im.name: im for im in model.images}
    camera_ids = sorted({by_name[n].camera_id for n in names})
    gt_k = np.stack([gt[n].K for n in names]) * scale  # [C, 3, 3]; row 2 is [0 0 1] * scale: unused
    gt_fx, gt_fy = float(gt_k[:, 0, 0].mean()), float(gt_k[:, 1, 1].mean())
    gt_cx, gt_cy = float(gt_k[:, 0, 2].mean()), float(gt_k[:, 1, 2].mean())
    rows = []
    for cid in camera_ids:
        cam = model.cameras[cid]
        # Undistortion scaled the principal point by undistorted size / input size; undo that.
        sx, sy = (input_size[0] / cam.width, input_size[1] / cam.height) if input_size else (1.0, 1.0)
        rows.append({
            "camera_id": cid, "model": cam.model, "undistorted_size": [cam.width, cam.height],
            "fx": cam.fx, "fy": cam.fy, "cx_input_px": cam.cx * sx, "cy_input_px": cam.cy * sy,
            "fx_rel_error_pct": 100 * (cam.fx / gt_fx - 1), "fy_rel_error_pct": 100 * (cam.fy / gt_fy - 1),
            "f_rel_error_vs_gt_mean_pct": 100 * ((cam.fx + cam.fy) / (gt_fx + gt_fy) - 1),
            "principal_point_offset_px": [cam.cx * sx - gt_cx, cam.cy * sy - gt_cy],
            # The estimated optical axis (through its principal point) is the GT ray through that pixel:
            # off by the offset d, i.e. a rotation of (-atan(d_y / f), atan(d_x / f), 0) about camera x, y, z.
            "tilt_predicted_by_principal_point_deg": [float(-np.degrees(np.arctan((cam.cy * sy - gt_cy) / gt_fy))),
                                                      float(np.degrees(np.arctan((cam.cx * sx - gt_cx) / gt_fx))),
                                                      0.0],
        })
    return {"gt_scale": scale, "gt_fx": gt_fx, "gt_fy": gt_fy, "gt_cx": gt_cx, "gt_cy": gt_cy,
            "gt_k_max_spread_px": float(np.abs(gt_k - gt_k.mean(0)).max()),
            "gt_distortion_max_abs": float(max(np.abs(gt[n].distortion).max() for n in names)),
            "estimated": rows}


def evaluate(args) -> dict:
    model = read_colmap_model(find_model_dir(args.scene_dir))
    report = read_report(args.scene_dir)
    gt = read_gt_dir(args.gt_dir)
    names = [im.name for im in model.images if im.name in gt]  # sorted by name (read_colmap_model)
    no_gt = [im.name for im in model.images if im.name not in gt]
    if len(names) < 3:
        raise UserError(f"{args.gt_dir}: only {len(names)} registered image(s) of {args.scene_dir} have a GT file "
                        f"(NAME{GT_SUFFIX}); at least 3 are needed for the alignment")
    by_name = {im.name: im for im in model.images}
    est_c, est_r = camera_poses(np.stack([by_name[n].viewmat for n in names]))  # [C, 3], [C, 3, 3]
    ref_c = np.stack([gt[n].center for n in names])  # [C, 3]
    ref_r = np.stack([gt[n].cam_to_world for n in names])  # [C, 3, 3]
    result = align_cameras(est_c, est_r, ref_c, ref_r)
    scale, scale_source = gt_scale(args, report, gt, names)
    input_size = input_image_size(report, names)
    ce, re_ = result.center_errors, result.rotation_errors_deg
    # Each camera's rotation error as a rotation vector in its own GT camera frame (x right, y down, z forward):
    # a tilt shared by all cameras there is what a principal point offset produces (see the markdown).
    tilts = np.degrees(rotation_vectors(np.transpose(ref_r, (0, 2, 1)) @ result.similarity.rotation @ est_r))
    common = tilts.mean(0)  # [3] degrees
    about_common = np.linalg.norm(tilts - common, axis=1)  # [C] degrees, small-angle difference
    seconds = dict(report.seconds) if report else {}
    out = {
        "machine": machine_info(),
        "command": shlex.join([os.path.relpath(sys.executable, REPO) if sys.executable.startswith(REPO)
                               else sys.executable, *sys.argv]),
        "scene_dir": os.path.abspath(args.scene_dir), "gt_dir": os.path.abspath(args.gt_dir),
        "sfm_command": args.sfm_command, "notes": args.note,
        "given": report.given if report else len(gt), "gt_files": len(gt), "registered": len(model.images),
        "registered_with_gt": len(names), "not_registered": sorted(set(gt) - set(by_name)), "no_gt": no_gt,
        "sfm_report": {k: v for k, v in vars(report).items()} if report else None,
        "alignment": {
            "method": "Umeyama similarity (with scale) on camera centres, estimated -> GT (benchmarks/measures/align.py)",
            "scale_est_to_gt": result.similarity.scale,
            "spread_radius_gt": result.spread_radius, "spread_diameter_gt": result.spread_diameter,
            "center_error_mean_gt": float(ce.mean()), "center_error_median_gt": float(np.median(ce)),
            "center_error_max_gt": float(ce.max()),
            "center_error_mean_pct_radius": float(100 * ce.mean() / result.spread_radius),
            "center_error_max_pct_radius": float(100 * ce.max() / result.spread_radius),
            "center_error_mean_pct_diameter": float(100 * ce.mean() / result.spread_diameter),
            "center_error_max_pct_diameter": float(100 * ce.max() / result.spread_diameter),
            "rotation_error_mean_deg": float(re_.mean()), "rotation_error_median_deg": float(np.median(re_)),
            "rotation_error_max_deg": float(re_.max()),
            "rotation_error_common_tilt_deg": common.tolist(),
            "rotation_error_about_common_tilt_mean_deg": float(about_common.mean()),
            "rotation_error_about_common_tilt_max_deg": float(about_common.max()),
        },
        "per_camera": [{"name": n, "center_error_gt": float(c), "rotation_error_deg": float(r)}
                       for n, c, r in zip(names, ce, re_)],
        "intrinsics": {"gt_scale_source": scale_source, "input_size": list(input_size) if input_size else None,
                       **intrinsics(model, names, gt, scale, input_size)},
        "sfm_seconds": {**seconds, "total": sum(seconds.values())} if seconds else None,
        "sfm_time_log": parse_time_log(args.time_log) if args.time_log else None,
    }
    return out


def markdown(r: dict) -> str:
    a, k, m = r["alignment"], r["intrinsics"], r["machine"]
    rep = r["sfm_report"] or {}
    lines = [
        f"# SfM accuracy: {os.path.basename(r['scene_dir'])} vs ground truth ({m['date_utc'][:10]})", "",
        f"Machine: {m['hostname']}, {m['cpu_model']}, {m['logical_cores']} logical cores, {m['platform']}, python "
        f"{m['python']}, pycolmap {m['pycolmap']}, numpy {m['numpy']}, ctgs {m['git']}; load average "
        f"{', '.join(f'{x:.1f}' for x in m['load_average'])} at {m['date_utc']}.",
        f"Evaluation: `{r['command']}`.",
        f"Scene: `{r['scene_dir']}`, made with: `{r['sfm_command'] or 'not recorded (pass --sfm-command)'}`.",
        f"Ground truth: `{r['gt_dir']}`.", "",
    ]
    lines += [f"Note: {n}" for n in r["notes"]] + ([""] if r["notes"] else [])
    lines += [
        "## Cameras", "",
        f"Registered {r['registered']}/{r['given']} images ({r['registered_with_gt']} with a GT camera"
        + (f"; not registered: {', '.join(r['not_registered'])}" if r["not_registered"] else "")
        + (f"; no GT file: {', '.join(r['no_gt'])}" if r["no_gt"] else "") + "); "
        f"{rep.get('points', '?')} points, mean reprojection error "
        f"{rep.get('mean_reprojection_error_px', float('nan')):.3f} px, mean track length "
        f"{rep.get('mean_track_length', float('nan')):.2f}.", "",
        "Alignment: the similarity (Umeyama, with scale) that best maps the estimated camera centres onto the GT "
        "centres (least squares); errors are in GT units (the ground truth's own frame; the Strecha data are "
        "described as metric, i.e. metres, which this script does not check). Camera spread: radius = "
        f"largest distance of a GT centre from the GT centroid ({a['spread_radius_gt']:.3f}); diameter = largest "
        f"distance between two GT centres ({a['spread_diameter_gt']:.3f}). Rotation error: angle between the "
        "aligned estimated and the GT camera orientation (orientations are not used by the fit).", "",
        "| measure | mean | median | max |", "| --- | ---: | ---: | ---: |",
        f"| centre error (GT units) | {a['center_error_mean_gt']:.4f} | {a['center_error_median_gt']:.4f} | "
        f"{a['center_error_max_gt']:.4f} |",
        f"| centre error (% of spread radius) | {a['center_error_mean_pct_radius']:.3f} | | "
        f"{a['center_error_max_pct_radius']:.3f} |",
        f"| centre error (% of spread diameter) | {a['center_error_mean_pct_diameter']:.3f} | | "
        f"{a['center_error_max_pct_diameter']:.3f} |",
        f"| rotation error (degrees) | {a['rotation_error_mean_deg']:.4f} | {a['rotation_error_median_deg']:.4f} | "
        f"{a['rotation_error_max_deg']:.4f} |", "",
        "Rotation error in each camera's own frame (rotation vector about camera x right, y down, z forward, "
        "degrees): mean over cameras ({}); spread of the cameras about that common tilt: mean {:.4f}, max {:.4f} "
        "(small-angle difference of rotation vectors). A common tilt is what a principal point offset causes: "
        "the offset below predicts ({}) (COLMAP keeps the principal point at the image centre: pycolmap's "
        "ba_refine_principal_point is False by default).".format(
            ", ".join(f"{x:+.3f}" for x in a["rotation_error_common_tilt_deg"]),
            a["rotation_error_about_common_tilt_mean_deg"], a["rotation_error_about_common_tilt_max_deg"],
            "; ".join(", ".join(f"{x:+.3f}" for x in e["tilt_predicted_by_principal_point_deg"])
                      for e in r["intrinsics"]["estimated"])), "",
        "## Intrinsics (pixels of the input images)", "",
        f"GT K scaled by {k['gt_scale']:g} ({k['gt_scale_source']}): fx {k['gt_fx']:.2f}, fy {k['gt_fy']:.2f}, "
        f"cx {k['gt_cx']:.2f}, cy {k['gt_cy']:.2f} (the same K for every GT camera within "
        f"{k['gt_k_max_spread_px']:.3g} px; GT distortion max |k| = {k['gt_distortion_max_abs']:g}). COLMAP's "
        "undistortion keeps the focal length and the pixel pitch and only crops the image and scales the "
        "principal point with the size, so the estimated f compares directly with the scaled GT fx, fy; the "
        "estimated principal point is mapped back by input size / undistorted size. (Halving GT cx, cy assumes "
        "pixel-corner coordinates; with pixel-centre ones they would be 0.25 px lower.)", "",
        "| camera | model (undistorted size) | fx | fy | fx vs GT fx | fy vs GT fy | f vs GT mean(fx, fy) | "
        "principal point | offset from GT |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | --- |",
    ]
    for e in k["estimated"]:
        lines.append(
            f"| {e['camera_id']} | {e['model']} ({e['undistorted_size'][0]}x{e['undistorted_size'][1]}) | "
            f"{e['fx']:.2f} | {e['fy']:.2f} | {e['fx_rel_error_pct']:+.3f}% | {e['fy_rel_error_pct']:+.3f}% | "
            f"{e['f_rel_error_vs_gt_mean_pct']:+.3f}% | ({e['cx_input_px']:.2f}, {e['cy_input_px']:.2f}) | "
            f"({e['principal_point_offset_px'][0]:+.2f}, {e['principal_point_offset_px'][1]:+.2f}) px |")
    lines += ["", "## SfM time", ""]
    if r["sfm_seconds"]:
        lines += ["Per step, from sfm_report.json (wall seconds):", "",
                  "| " + " | ".join(r["sfm_seconds"]) + " |", "|" + " ---: |" * len(r["sfm_seconds"]),
                  "| " + " | ".join(f"{v:.1f}" for v in r["sfm_seconds"].values()) + " |", ""]
    if r["sfm_time_log"]:
        t = r["sfm_time_log"]
        lines += [f"Whole run (`/usr/bin/time -v`): `{t['command']}`: {t['wall_s']:.1f} s wall, {t['cpu_s']:.1f} s "
                  f"CPU (user {t['user_s']:.1f} + system {t['system_s']:.1f}), peak memory "
                  f"{t['max_rss_mb']:.0f} MB, exit status {t['exit_status']}.", ""]
    lines += ["## Per camera", "", "| image | centre error (GT units) | rotation error (deg) |",
              "| --- | ---: | ---: |"]
    lines += [f"| {c['name']} | {c['center_error_gt']:.4f} | {c['rotation_error_deg']:.4f} |" for c in r["per_camera"]]
    return "\n".join(lines) + "\n"


def write_atomic(path: str, text: str) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene_dir", help="a `ctgs sfm` output folder (sparse/0, sfm_report.json)")
    ap.add_argument("gt_dir", help="folder of NAME.camera ground-truth files (Strecha format)")
    ap.add_argument("--gt-scale", type=float, help="input pixels per GT pixel (default: input image size / GT size)")
    ap.add_argument("--sfm-command", default="", help="how SCENE_DIR was made, recorded verbatim")
    ap.add_argument("--time-log", help="`/usr/bin/time -v` output of the `ctgs sfm` run, recorded")
    ap.add_argument("--note", action="append", default=[], help="a line recorded in the results (repeatable)")
    ap.add_argument("--out", help="output prefix (default benchmarks/results/sfm_accuracy/<scene>_<commit>)")
    args = ap.parse_args()
    try:
        result = evaluate(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scene_name = os.path.basename(os.path.abspath(args.scene_dir))
    prefix = args.out or record.stem("sfm_accuracy", scene_name)
    os.makedirs(os.path.dirname(os.path.abspath(prefix)), exist_ok=True)
    write_atomic(prefix + ".json", json.dumps(result, indent=1) + "\n")
    md = markdown(result)
    write_atomic(prefix + ".md", md)
    print(md)
    print(f"wrote {prefix}.json and {prefix}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
