"""Where `ctgs sfm`'s time goes, per step, for one or more variants run in turn on one capture.

    .venv/bin/python benchmarks/sfm_profile.py IMAGES_DIR --scene NAME --reference SPARSE_DIR \\
        --variant NAME=CHECKOUT[::SFM OPTIONS] [--variant ...] [--rounds 2] [--work DIR] [--keep] [--note TEXT ...]

A variant is a checkout of ctgs (this one, or a `git worktree` of an older commit) and the options given to its
`ctgs sfm`: `before=/tmp/ctgs_old` runs `python -m ctgs sfm IMAGES_DIR -o WORK/... --force --threads 2` from
/tmp/ctgs_old (so that checkout's code is imported), `fast=.::--quality fast` this checkout with `--quality fast`.
The variants run one at a time, in turn, for --rounds rounds, the order reversed every other round (A B, B A, ...),
so that old and new share the machine's load; the records give per-round ratios against the first variant.

While a command runs, its process tree (ctgs and its pycolmap worker) is sampled every 0.25 s from /proc: the
step it is in (the first of the work folder's steps without its `.done` marker), each thread's CPU time and the
tree's resident memory. Per step it records:
- wall and CPU seconds (the CPU seconds of the whole tree; a step's wall time on a busy machine is inflated by
  the load, its CPU seconds much less);
- threads: the threads that did at least 10% of the step's CPU time, and `parallel`, the step's CPU time over
  that of its busiest thread (2.0: the work is spread evenly over two threads, 1.0: one thread does it all);
  `held`, the step's CPU seconds over its wall seconds (cores it got: at most 2 here, less when others run);
- peak resident memory of the tree (MB).
When mapping starts, the COLMAP database is read (read-only): features per photo, pairs matched, pairs verified.
At the end the scene's cameras are compared with the reference model (sfm_modes.agreement: a similarity fit on
the centres, errors in % of the camera spread radius, the focal length's relative error), and per camera: the
median and 95th percentile of the centre errors, how many exceed 0.5%, the three worst by name, both with that fit
and with a robust one (measures.align) that leaves out the cameras a least-squares fit lets bend the rest.

Record: benchmarks/results/sfm_profile/<scene>_<W>x<H>_<variants>_<commit>.json and .md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import sqlite3
import statistics
import subprocess
import sys
import threading
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, "benchmarks"))
import record  # noqa: E402

from ctgs.io.images import image_info, list_images  # noqa: E402
from ctgs.scene.sfm import STEPS, read_report  # noqa: E402
from measures.align import align_cameras  # noqa: E402
from sfm_modes import _poses, agreement, machine, reference_cameras  # noqa: E402

SAMPLE_S = 0.25
TICK = os.sysconf("SC_CLK_TCK")
BUSY_THREAD_SHARE = 0.10  # a thread counts as used by a step when it did this share of the step's CPU time


def _children(pid: int) -> list[int]:
    out = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


def _tree(pid: int) -> list[int]:
    todo, seen = [pid], []
    while todo:
        p = todo.pop()
        seen.append(p)
        todo += _children(p)
    return seen


def _threads(pid: int) -> dict[tuple[int, int], tuple[str, int]]:
    """(pid, tid) -> (thread name, CPU ticks so far) for each thread of a process."""
    out = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                text = f.read()
        except OSError:
            continue
        name = text[text.index("(") + 1:text.rindex(")")]
        fields = text[text.rindex(")") + 2:].split()
        out[(pid, int(tid))] = (name, int(fields[11]) + int(fields[12]))  # utime + stime
    return out


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _step(work: str) -> str:
    if not os.path.isfile(os.path.join(work, "inputs.json")):
        return "checks"
    return next((s for s in STEPS if not os.path.isfile(os.path.join(work, f"{s}.done"))), "report")


def database_figures(db: str) -> dict:
    """Features per photo and pairs from a COLMAP database (read-only)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
    try:
        rows = [r[0] for r in con.execute("SELECT rows FROM keypoints")]
        matched = con.execute("SELECT COUNT(*) FROM matches").fetchone()[0]
        verified = con.execute("SELECT COUNT(*) FROM two_view_geometries WHERE rows >= 15").fetchone()[0]
        inliers = con.execute("SELECT AVG(rows) FROM two_view_geometries WHERE rows >= 15").fetchone()[0]
    finally:
        con.close()
    return {"features_mean": statistics.fmean(rows) if rows else 0, "features_min": min(rows, default=0),
            "features_max": max(rows, default=0), "pairs_matched": matched, "pairs_verified": verified,
            "inliers_per_verified_pair": float(inliers or 0)}


class Sampler(threading.Thread):
    def __init__(self, pid: int, work: str) -> None:
        super().__init__(daemon=True)
        self.pid, self.work = pid, work
        self.stop = threading.Event()
        self.last: dict[tuple[int, int], int] = {}
        self.steps: dict[str, dict] = {}
        self.database: dict = {}
        self.current = "checks"
        self.keep_database = ""  # a path: the database is copied there when mapping starts
        self.keep_logs = ""  # a folder: the work folder's logs are copied there as each step ends

    def run(self) -> None:
        while not self.stop.is_set():
            self.sample()
            self.stop.wait(SAMPLE_S)

    def sample(self) -> None:
        step = _step(self.work)
        order = ["checks", *STEPS, "report"]
        if self.steps and order.index(step) < order.index(self.current):
            step = "report"  # the work folder is gone: the scene is being installed
        if step != self.current and self.keep_logs:
            os.makedirs(self.keep_logs, exist_ok=True)
            for name in os.listdir(self.work) if os.path.isdir(self.work) else []:
                if name.endswith((".log", ".result.json")):
                    try:
                        shutil.copy(os.path.join(self.work, name), self.keep_logs)
                    except OSError:  # the work folder went away meanwhile
                        pass
        self.current = step
        pids = _tree(self.pid)
        now = time.perf_counter()
        s = self.steps.setdefault(step, {"start": now, "end": now, "threads": {}, "peak_rss_mb": 0.0})
        s["end"] = now
        s["peak_rss_mb"] = max(s["peak_rss_mb"], sum(_rss_mb(p) for p in pids))
        for p in pids:
            for key, (name, ticks) in _threads(p).items():
                delta = ticks - self.last.get(key, 0)
                self.last[key] = ticks
                if delta > 0:
                    t = s["threads"].setdefault(f"{key[0]}/{key[1]}", {"name": name, "ticks": 0})
                    t["ticks"] += delta
        if step == "mapping" and not self.database:
            db = os.path.join(self.work, "database.db")
            try:
                self.database = database_figures(db)
                if self.keep_database:
                    src = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
                    dst = sqlite3.connect(self.keep_database)
                    src.backup(dst)
                    src.close()
                    dst.close()
            except sqlite3.Error as exc:
                self.database = {"error": str(exc)}


def camera_errors(scene_dir: str, reference: dict, worst: int = 3) -> dict:
    """Each camera's centre error (% of the spread radius, the same similarity fit as sfm_modes.agreement): the
    median, the 95th percentile and the worst cameras by name; under "robust", the same with the fit left to the
    cameras that agree (measures.align: one far camera pulls a least-squares fit and so every other camera)."""
    # pycolmap and numpy: only once a scene was made
    import numpy as np
    import pycolmap

    rec = pycolmap.Reconstruction(os.path.join(scene_dir, "sparse", "0"))
    names = sorted(im.name for im in rec.images.values() if im.name in reference)
    est_c, est_r = _poses(rec, names)
    out = {}
    for robust in (False, True):
        fit = align_cameras(est_c, est_r, np.stack([reference[n][0] for n in names]),
                            np.stack([reference[n][1] for n in names]), robust=robust)
        ce = fit.center_errors / fit.spread_radius * 100
        order = np.argsort(-ce)[:worst]
        errors = {"center_error_median_pct": float(np.median(ce)),
                  "center_error_p95_pct": float(np.percentile(ce, 95)), "cameras_over_0_5_pct": int((ce > 0.5).sum()),
                  "worst": [[names[i], float(ce[i])] for i in order],
                  "left_out": [names[i] for i in np.flatnonzero(~fit.fitted)]}
        out.update({"robust": errors} if robust else errors)
    return out


def camera_table(runs: list[dict]) -> list[str]:
    """Markdown lines: each run's per-camera centre errors, with the least-squares fit over all cameras and (where
    measured) with the robust fit, which names the cameras it left out."""
    lines = ["", "## Camera centres against the reference, per camera (% of the spread radius)", "",
             "Fit: `all`, least squares over every camera (the table above); `robust`, refitted on the cameras within "
             "5x the median error or 0.5% of the spread, whichever is larger; every camera still measured.", "",
             "| run | fit | median | 95th percentile | cameras over 0.5% | worst | left out of the fit |",
             "|---|---|---:|---:|---:|---|---|"]
    for r in runs:
        a = r.get("agreement", {})
        for fit, e in (("all", a), ("robust", a.get("robust"))):
            if e and "worst" in e:
                worst = ", ".join(f"{n} {v:.2f}" for n, v in e["worst"])
                lines.append(f"| {r['variant']} r{r['round']} | {fit} | {e['center_error_median_pct']:.3f} | "
                             f"{e['center_error_p95_pct']:.3f} | {e['cameras_over_0_5_pct']} | {worst} | "
                             f"{', '.join(e.get('left_out', [])) if fit == 'robust' else ''} |")
    return lines


def summarise_steps(sampled: dict, report) -> dict:
    out = {}
    for step in ["checks", *STEPS, "report"]:
        s = sampled.get(step)
        wall = report.seconds.get(step) if report and step in report.seconds else (s["end"] - s["start"] if s else 0)
        cpu_sampled = sum(t["ticks"] for t in s["threads"].values()) / TICK if s else 0.0
        cpu = report.cpu_seconds.get(step, cpu_sampled) if report and report.cpu_seconds else cpu_sampled
        busiest = max((t["ticks"] for t in s["threads"].values()), default=0) / TICK if s else 0.0
        used = sorted(((t["ticks"] / TICK, t["name"]) for t in (s["threads"].values() if s else [])
                       if cpu_sampled and t["ticks"] / TICK >= BUSY_THREAD_SHARE * cpu_sampled), reverse=True)
        out[step] = {"wall_s": wall, "cpu_s": cpu, "cpu_sampled_s": cpu_sampled,
                     "threads_used": len(used), "thread_names": [n for _, n in used],
                     "parallel": cpu_sampled / busiest if busiest else 0.0,
                     "held": cpu / wall if wall else 0.0, "peak_rss_mb": s["peak_rss_mb"] if s else 0.0}
    return out


def run_one(args, name: str, checkout: str, options: list[str], round_: int, reference: dict, ref_focal: float) -> dict:
    out = os.path.join(args.work, f"{args.scene}_{name}_r{round_}")
    work = os.path.join(args.work, f".{os.path.basename(out)}.sfm-work")
    cmd = [sys.executable, "-m", "ctgs", "sfm", args.images_dir, "-o", out, "--force", "--threads",
           str(args.threads), *options]
    load_start, date = list(os.getloadavg()), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    start = time.perf_counter()
    with open(os.path.join(args.work, f"{os.path.basename(out)}.log"), "w") as log:
        proc = subprocess.Popen(cmd, cwd=checkout, stdout=log, stderr=subprocess.STDOUT)
        sampler = Sampler(proc.pid, work)
        if args.keep_database:
            sampler.keep_database = f"{out}.database.db"
        sampler.keep_logs = f"{out}.logs"
        sampler.start()
        proc.wait()
        sampler.stop.set()
        sampler.join()
    wall = time.perf_counter() - start
    rec = {"variant": name, "round": round_, "checkout": checkout, "commit": _checkout_commit(checkout),
           "command": shlex.join(cmd), "date_utc": date, "load_average_start": load_start,
           "load_average_end": list(os.getloadavg()), "wall_s": wall, "exit_code": proc.returncode,
           "database": sampler.database}
    report = read_report(out) if proc.returncode == 0 else None
    rec["steps"] = summarise_steps(sampler.steps, report)
    if report is not None:
        rec["report"] = vars(report)
        rec["agreement"] = {**agreement(out, reference, ref_focal), **camera_errors(out, reference)}
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)
    return rec


def _checkout_commit(checkout: str) -> str:
    out = subprocess.run(["git", "-C", checkout, "rev-parse", "--short=7", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", checkout, "status", "--porcelain", "ctgs/scene/sfm", "ctgs/stages/sfm.py",
                            "ctgs/io/images.py"], capture_output=True, text=True).stdout.strip()
    return (out.stdout.strip() or "unknown") + ("+" if dirty else "")


def _row(r: dict) -> str:
    steps = r["steps"]
    cells = [f"{steps[s]['wall_s']:.1f} / {steps[s]['cpu_s']:.1f}" for s in STEPS]
    return " | ".join(cells)


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [f"# ctgs sfm profile: {result['scene']} ({result['size']}), {', '.join(result['variants'])} "
             f"({result['date_utc'][:10]})", "",
             f"Machine: {m['cpu_model']}, {m['logical_cores']} logical cores ({m['hostname']}), python {m['python']}, "
             f"pycolmap {m['pycolmap']}. Shared with other work: the load average at each run's start and end is "
             "in the tables; wall seconds are inflated by it, CPU seconds much less.", "",
             f"Benchmark: `{result['benchmark_command']}`. Reference: {result['reference']}.", ""]
    for v, spec in result["variant_specs"].items():
        lines.append(f"- `{v}`: checkout {spec['checkout']} ({spec['commit']}), `ctgs sfm` options "
                     f"`{' '.join(spec['options']) or '(defaults)'}`")
    lines += [""] + [f"Note: {n}" for n in result["notes"]] + ([""] if result["notes"] else [])
    lines += ["## Runs (wall s / CPU s per step)", "",
              "| run | start (UTC) | load start / end | " + " | ".join(STEPS) + " | whole command s | registered "
              "| centres mean / max % | focal % |", "|---|---|---|" + "---:|" * (len(STEPS) + 4)]
    for r in result["runs"]:
        load = f"{r['load_average_start'][0]:.1f} / {r['load_average_end'][0]:.1f}"
        if r["exit_code"] != 0:
            lines.append(f"| {r['variant']} r{r['round']} | {r['date_utc'][11:19]} | {load} | failed (exit "
                         f"{r['exit_code']}) |" + " |" * (len(STEPS) + 3))
            continue
        a, rep = r["agreement"], r["report"]
        lines.append(f"| {r['variant']} r{r['round']} | {r['date_utc'][11:19]} | {load} | {_row(r)} | "
                     f"{r['wall_s']:.0f} | {rep['registered']}/{rep['given']} | {a['center_error_mean_pct']:.3f} / "
                     f"{a['center_error_max_pct']:.3f} | {a['focal_error_pct']:+.3f} |")
    lines += camera_table(result["runs"])
    lines += ["", "## Per step: threads, memory (each variant's first run)", "",
              "| variant | step | wall s | CPU s | threads used | parallel | cores held | peak RSS MB |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for v in result["variants"]:
        r = next((r for r in result["runs"] if r["variant"] == v and r["exit_code"] == 0), None)
        if r is None:
            continue
        for step, s in r["steps"].items():
            if not s["wall_s"]:
                continue
            lines.append(f"| {v} | {step} | {s['wall_s']:.1f} | {s['cpu_s']:.1f} | {s['threads_used']} | "
                         f"{s['parallel']:.2f} | {s['held']:.2f} | {s['peak_rss_mb']:.0f} |")
    lines += ["", "## What was matched and mapped (each variant's first run)", "",
              "| variant | features per photo mean (min-max) | pairs matched | pairs verified (15+ inliers) | inliers "
              "per verified pair | points | reprojection px | track length |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for v in result["variants"]:
        r = next((r for r in result["runs"] if r["variant"] == v and r["exit_code"] == 0), None)
        if r is None:
            continue
        d, rep = r["database"], r["report"]
        lines.append(f"| {v} | {d.get('features_mean', 0):.0f} ({d.get('features_min', 0)}-{d.get('features_max', 0)}) "
                     f"| {d.get('pairs_matched', 0)} | {d.get('pairs_verified', 0)} | "
                     f"{d.get('inliers_per_verified_pair', 0):.0f} | {rep['points']} | "
                     f"{rep['mean_reprojection_error_px']:.3f} | {rep['mean_track_length']:.2f} |")
    if len(result["variants"]) > 1:
        base = result["variants"][0]
        lines += ["", f"## Ratios to `{base}`, run by run (same round: the machine's load alike)", "",
                  "| variant | round | " + " | ".join(STEPS) + " | whole command |", "|---|---|" + "---:|" * (len(STEPS) + 1)]
        for r in result["runs"]:
            b = next((x for x in result["runs"] if x["variant"] == base and x["round"] == r["round"]), None)
            if r["variant"] == base or b is None or r["exit_code"] or b["exit_code"]:
                continue
            cells = []
            for s in STEPS:
                bw = b["steps"][s]["wall_s"]
                cells.append(f"{r['steps'][s]['wall_s'] / bw:.2f}" if bw else "-")
            lines.append(f"| {r['variant']} | {r['round']} | " + " | ".join(cells) + f" | {r['wall_s'] / b['wall_s']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("images_dir")
    ap.add_argument("--scene", required=True, help="the capture's name in the record's name")
    ap.add_argument("--reference", required=True, help="the COLMAP model (sparse/0) the cameras are compared with")
    ap.add_argument("--variant", action="append", required=True,
                    help="NAME=CHECKOUT[::SFM OPTIONS], e.g. before=/tmp/ctgs_old or fast=.::'--quality fast'")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default="/tmp/sfm_profile")
    ap.add_argument("--keep", action="store_true", help="keep the scenes made (WORK/<scene>_<variant>_r<round>)")
    ap.add_argument("--keep-database", action="store_true",
                    help="copy each run's COLMAP database (features and matches) to WORK/<scene>_<variant>_r<round>"
                         ".database.db when mapping starts")
    ap.add_argument("--name", default="", help="the record's variant part (default: the variants' names)")
    ap.add_argument("--note", action="append", default=[])
    args = ap.parse_args()
    args.images_dir = os.path.abspath(args.images_dir)
    args.work = os.path.abspath(args.work)
    os.makedirs(args.work, exist_ok=True)
    specs = {}
    for v in args.variant:
        name, _, rest = v.partition("=")
        checkout, _, options = rest.partition("::")
        checkout = os.path.abspath(checkout or ".")
        specs[name] = {"checkout": checkout, "options": shlex.split(options), "commit": _checkout_commit(checkout)}
    ref_args = argparse.Namespace(reference=args.reference, gt_cameras=None, images_dir=args.images_dir)
    reference, ref_focal, ref_source = reference_cameras(ref_args)
    first = os.path.join(args.images_dir, list_images(args.images_dir)[0])
    info = image_info(first)
    result = {"scene": args.scene, "size": f"{info.width}x{info.height}", "images": len(list_images(args.images_dir)),
              "machine": machine(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "benchmark_command": shlex.join([os.path.relpath(sys.executable, REPO), *sys.argv]),
              "reference": ref_source, "variants": list(specs), "variant_specs": specs, "notes": args.note, "runs": []}
    names = list(specs)
    path = record.stem("sfm_profile", f"{args.scene}_{result['size']}_{args.name or '_'.join(names)}")
    for round_ in range(1, args.rounds + 1):
        for name in (names if round_ % 2 else names[::-1]):
            spec = specs[name]
            print(f"round {round_}: {name} ...", flush=True)
            result["runs"].append(run_one(args, name, spec["checkout"], spec["options"], round_, reference, ref_focal))
            record.write_record(path, result, markdown)  # after every run: a stopped benchmark keeps what it measured
    return 0


if __name__ == "__main__":
    sys.exit(main())
