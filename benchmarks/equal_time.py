"""Content-aware vs 2dgs at equal wall time, each at the run length it does best with (chosen on validation views).

Why: `--time-budget` gives a run all the time it has, and on small real captures longer runs can score lower
on held-out views (both methods overfit 21 training images of 192x128). Matching 2dgs to the content-aware
run by `--time-budget` alone (benchmarks/trade.py) then compares a well-fitted run with an over-long one. Here
each method may pick its length, on validation views only, among lengths that fit the same time:

1. Validation (`--set validation_holdout=8`: the protocol's test views are left out; every 8th remaining view
   is evaluated): every length in --ca-iters and --2dgs-iters, two trainings side by side.
2. The time limit T = validation wall time of the content-aware run at the preset's own length (the largest
   of --ca-iters). Each method's choice = the best validation PSNR among its lengths whose validation wall
   time is <= T (same machine, same load pattern, same number of views per iteration).
3. Test (the protocol split, every 8th view): the two chosen lengths, trained side by side, then export +
   eval. The table states wall times so the reader can check the time match.

Usage: .venv/bin/python benchmarks/equal_time.py --scene /work/data/herzjesu25 --images images_8
       [--preset fast] [--ca-iters 1500 2000 3000] [--2dgs-iters 1000 1500 2000 3000] [--work DIR] [--tag vm]
       [--ca-set KEY=VALUE ...]   (overrides for the content-aware runs only)
Writes benchmarks/results/equal_time/<tag>_<commit>.{md,json}. Runs already done in --work are reused (so the 2dgs runs of an
earlier benchmark with the same scene, preset and seed can be copied in when only the content-aware side changes; the
content-aware folders carry the --ca-set overrides in their names).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)
from trade import ctgs, git_commit  # noqa: E402  (one logged `python -m ctgs` runner for the benchmarks)


def train(args, method: str, iters: int, split: str) -> dict:
    """One `ctgs train` (+ export + eval on the test split) in its own folder; reused when done."""
    # --ca-set goes into the content-aware folder names, so runs with other overrides are never reused for them.
    extra = "".join("_" + kv.replace("=", "") for kv in args.ca_set) if method == "ca" else ""
    run = os.path.join(args.work, f"{split}_{method}_{iters}{extra}")
    rec_path = os.path.join(run, "equal_time_record.json")
    if os.path.exists(rec_path):
        with open(rec_path) as fh:
            return json.load(fh)
    os.makedirs(args.work, exist_ok=True)
    cmd = ["train", args.scene, "-o", run, "--images", args.images, "-q", "--preset", args.preset,
           "--iterations", str(iters), "--set", f"threads={args.threads}", "--set", f"seed={args.seed}"]
    if method == "2dgs":
        cmd += ["--config", "2dgs"]
    else:
        for kv in args.ca_set:
            cmd += ["--set", kv]
    if split == "val":
        cmd += ["--set", "validation_holdout=8"]
    log = run + ".log"
    if os.path.exists(log):
        os.remove(log)
    t0 = time.time()
    ctgs(*cmd, log=log)
    wall = time.time() - t0
    with open(os.path.join(run, "train_summary.json")) as fh:
        s = json.load(fh)
    rec = {"method": method, "iterations": iters, "split": split, "command": "-m ctgs " + " ".join(cmd), "wall_s": wall,
           "psnr": s["final_test_psnr"], "ssim": s["final_test_ssim"], "primitives": s["num_primitives"],
           "texels": s["num_texels"], "params": s["num_params"],
           "params_per_value": s.get("params_per_observed_value")}
    if split == "test":
        ctgs("export", run, "-o", os.path.join(run, "model"), log=log)
        ctgs("eval", run, "--model", os.path.join(run, "model"), "-o", os.path.join(run, "eval"), log=log)
        with open(os.path.join(run, "eval", "metrics.json")) as fh:
            m = json.load(fh)
        rec.update({"psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"], "fps": m["fps"],
                    "mb": m["bytes_on_disk"] / 1e6,
                    "per_view_psnr": {r["name"]: r["psnr"] for r in m.get("per_image", [])},
                    "per_view_open": {r["name"]: r.get("open") for r in m.get("per_image", [])}})
    with open(rec_path, "w") as fh:
        json.dump(rec, fh, indent=1)
    return rec


def both(args, jobs: list[tuple[str, int, str]]) -> list[dict]:
    """Run the jobs two at a time (longest first, so pairs finish close together)."""
    jobs = sorted(jobs, key=lambda j: -j[1] * (2 if j[0] == "2dgs" else 1))
    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        return list(pool.map(lambda j: train(args, *j), jobs))


def choose(val: list[dict], method: str, limit_s: float) -> dict:
    fits = [r for r in val if r["method"] == method and r["wall_s"] <= limit_s]
    if not fits:  # nothing fits: the shortest length
        fits = [min((r for r in val if r["method"] == method), key=lambda r: r["wall_s"])]
    return max(fits, key=lambda r: r["psnr"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", required=True)
    ap.add_argument("--images", default="images_8")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--ca-iters", nargs="+", type=int, default=[1500, 2000, 3000])
    ap.add_argument("--2dgs-iters", dest="gs_iters", nargs="+", type=int, default=[1000, 1500, 2000, 3000])
    ap.add_argument("--work", default="/tmp/ctgs_equal_time")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tag", default="herzjesu25", help="names the record: scene, resolution, variant")
    ap.add_argument("--ca-set", nargs="*", default=[], help="KEY=VALUE overrides for the content-aware runs")
    args = ap.parse_args()
    args.commit = git_commit()  # at the start: the code the runs train with
    if any("=" not in kv for kv in args.ca_set):
        raise SystemExit(f"equal_time.py: write --ca-set overrides as KEY=VALUE, got {args.ca_set}")
    args.scene = os.path.abspath(args.scene)

    val = both(args, [("ca", n, "val") for n in args.ca_iters] + [("2dgs", n, "val") for n in args.gs_iters])
    ref = next(r for r in val if r["method"] == "ca" and r["iterations"] == max(args.ca_iters))
    limit = ref["wall_s"]
    pick_ca, pick_gs = choose(val, "ca", limit), choose(val, "2dgs", limit)
    test = both(args, [("ca", pick_ca["iterations"], "test"), ("2dgs", pick_gs["iterations"], "test")])
    write(args, val, test, limit)


def write(args, val: list[dict], test: list[dict], limit: float) -> None:
    out = record.stem("equal_time", args.tag)
    machine = f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"
    commit = args.commit  # taken when the runs started (finished runs in --work are reused as they are)
    with open(out + ".json", "w") as fh:
        json.dump({"command": "benchmarks/equal_time.py " + " ".join(sys.argv[1:]), "machine": machine,
                   "commit": commit, "date": time.strftime("%Y-%m-%d %H:%M"), "time_limit_s": limit,
                   "validation": val, "test": test}, fh, indent=1)
    name = {"ca": "content-aware", "2dgs": "2dgs"}
    lines = [f"# Content-aware vs 2dgs at equal wall time, lengths chosen on validation views "
             f"({os.path.basename(args.scene)} {args.images}, preset {args.preset}"
             f"{''.join(' --set ' + kv for kv in args.ca_set) + ' for content-aware' if args.ca_set else ''})", "",
             f"Written by `benchmarks/equal_time.py {' '.join(sys.argv[1:])}` on {time.strftime('%Y-%m-%d')}, "
             f"{machine}, commit {commit}, CPU backend, {args.threads} thread per training, {args.parallel} "
             "trainings side by side. Wall = the whole `ctgs train` command.", "",
             f"## 1. Validation (test views left out; every 8th remaining view evaluated)", "",
             f"Time limit = the content-aware run at the preset length: {limit / 60:.1f} min.", "",
             "| method | iterations | val PSNR | val SSIM | primitives | params | wall min | fits the limit |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(val, key=lambda r: (r["method"] != "ca", r["iterations"])):
        lines.append(f"| {name[r['method']]} | {r['iterations']} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                     f"{r['primitives']} | {r['params']} | {r['wall_s'] / 60:.1f} | "
                     f"{'yes' if r['wall_s'] <= limit else 'no'} |")
    lines += ["", "## 2. Test (protocol split), each method at its chosen length", "",
              "| method | iterations | test PSNR | SSIM | LPIPS | primitives | params | params/value | MB | FPS | wall min |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in test:
        lp = "-" if r.get("lpips") is None else f"{r['lpips']:.3f}"
        lines.append(f"| {name[r['method']]} | {r['iterations']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {lp} | "
                     f"{r['primitives']} | {r['params']} | {r['params_per_value']:.2f} | {r['mb']:.2f} | "
                     f"{r['fps']:.1f} | {r['wall_s'] / 60:.1f} |")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
