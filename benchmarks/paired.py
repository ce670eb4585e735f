"""Two training configurations over several seeds, paired by seed: is A better than B, or was one pair lucky?

On herzjesu25 one pair of runs says little: the test mean is over four views, and the first (the trajectory's
first camera, an extrapolation) swings by 3-4 dB from run to run with what the model happens to put where no
training view looked (docs/studies.md, 'Why does a herzjesu25 test mean swing between runs?'). This trains
A and B at each seed on the protocol split (every 8th view is a test view; nothing is chosen from them here:
A and B are fixed before the runs), two trainings at a time in seed order (1 thread each; A and B of a seed
start together), then `ctgs export` + `ctgs eval` of the exported model, and reports per
seed and per view, with the paired difference A - B, its standard deviation, paired t, p and 95% interval.

Usage: .venv/bin/python benchmarks/paired.py --scene /work/data/herzjesu25 --images images_8 \\
         --a balanced --b fast --seeds 0 1 2 3 --work /work/runs/paired --tag NAME
       [--a-set KEY=VALUE ...] [--b-set KEY=VALUE ...] [--a-config 2dgs] [--b-config 2dgs]
Writes benchmarks/results/paired/NAME_<commit>.{md,json}. Finished runs in --work are reused (a killed benchmark resumes).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paired_stats import paired, sentence  # noqa: E402
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)
from trade import ctgs, git_commit  # noqa: E402


def label_args(preset: str, config: str | None, sets: list[str]) -> tuple[str, list[str]]:
    args = ["--preset", preset] + (["--config", config] if config else [])
    for kv in sets:
        if "=" not in kv:
            raise SystemExit(f"paired.py: write overrides as KEY=VALUE, got {kv!r}")
        args += ["--set", kv]
    label = "_".join([preset] + ([config] if config else []) + [kv.replace("=", "") for kv in sets])
    return label, args


def run_one(args, label: str, train_args: list[str], seed: int, lpips: bool) -> dict:
    run = os.path.join(args.work, f"{label}_s{seed}")
    rec_path = os.path.join(run, "paired_record.json")
    if os.path.exists(rec_path):
        with open(rec_path) as fh:
            rec = json.load(fh)
        # a run linked in under this label (e.g. an earlier run of the same configuration under an older name)
        return {**rec, "label": label, "trained_label": rec["label"], "reused": True}
    os.makedirs(args.work, exist_ok=True)
    log = run + ".log"
    resume = ["--resume"] if os.path.exists(os.path.join(run, "checkpoints", "last.pt")) else []
    cmd = ["train", args.scene, "-o", run, "--images", args.images, "-q", *train_args,
           "--set", f"threads={args.threads}", "--set", f"seed={seed}", *resume]
    commit = git_commit()  # the code the training runs, which a commit made while it trains does not change
    t0 = time.time()
    ctgs(*cmd, log=log)
    wall = time.time() - t0
    rec = finish(run, label, seed, commit, "-m ctgs " + " ".join(cmd), wall, lpips, log)
    with open(rec_path, "w") as fh:
        json.dump(rec, fh, indent=1)
    return rec


def finish(run: str, label: str, seed: int, commit: str, command: str, wall: float, lpips: bool, log: str,
           scene: str | None = None) -> dict:
    """`ctgs export` + `ctgs eval` of a trained run (on this machine, wherever it trained: `scene` is this machine's
    copy of its scene when the run trained elsewhere) and its record."""
    ctgs("export", run, "-o", os.path.join(run, "model"), log=log)
    ctgs("eval", run, "--model", os.path.join(run, "model"), "-o", os.path.join(run, "eval"),
         *([] if lpips else ["--no-lpips"]), *(["--scene", scene] if scene else []), log=log)
    with open(os.path.join(run, "train_summary.json")) as fh:
        s = json.load(fh)
    with open(os.path.join(run, "eval", "metrics.json")) as fh:
        m = json.load(fh)
    return {"label": label, "seed": seed, "run": run, "commit": commit, "command": command, "wall_s": wall,
           "iterations": s["iterations"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
           "per_view_psnr": {r["name"]: r["psnr"] for r in m["per_image"]},
           "per_view_open": {r["name"]: r.get("open") for r in m["per_image"]},  # rendered alpha < 0.9 (ctgs eval)
           "primitives": m["points"], "texels": m["texels"], "params": m["params"],
           "params_per_value": s.get("params_per_observed_value"), "mb": m["bytes_on_disk"] / 1e6, "fps": m["fps"]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", required=True)
    ap.add_argument("--images", default="images")
    ap.add_argument("--a", required=True, help="preset of A")
    ap.add_argument("--b", required=True, help="preset of B")
    ap.add_argument("--a-config", default=None)
    ap.add_argument("--b-config", default=None)
    ap.add_argument("--a-set", nargs="*", default=[])
    ap.add_argument("--b-set", nargs="*", default=[])
    ap.add_argument("--seeds", nargs="+", type=int, required=True)
    ap.add_argument("--work", required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--tag", required=True)
    ap.add_argument("--trained-on", default=None,
                    help="where the runs in --work were trained, when not here (e.g. runs imported from a GPU by "
                         "benchmarks/device/import_runs.py); replaces the record's 'CPU backend, N threads' sentence")
    args = ap.parse_args()
    commit = git_commit()  # at the start: the runs this invocation trains use this code
    from ctgs.metrics.vgg_weights import find_vgg16

    lpips = find_vgg16().state is not None  # said in the table when missing (`make lpips-weights`)
    la, aa = label_args(args.a, args.a_config, args.a_set)
    lb, ba = label_args(args.b, args.b_config, args.b_set)
    if la == lb:
        raise SystemExit("paired.py: A and B are the same configuration")
    jobs = [(la, aa, s) for s in args.seeds] + [(lb, ba, s) for s in args.seeds]
    jobs.sort(key=lambda j: (j[2], j[0] != la))  # A and B of a seed next to each other: they run together
    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        recs = list(pool.map(lambda j: run_one(args, j[0], j[1], j[2], lpips), jobs))
    by = {(r["label"], r["seed"]): r for r in recs}
    pairs = [(s, by[(la, s)], by[(lb, s)]) for s in args.seeds]
    # runs found finished in --work (an earlier invocation) and runs this one trained at another commit (one made
    # while it ran, or a resumed run) are named apart: the record says which code trained what
    reused = [r for r in recs if r.get("reused")]
    run_commits = sorted({r["commit"] for r in reused if r.get("commit")})
    other_commits = sorted({r["commit"] for r in recs if not r.get("reused") and r.get("commit")} - {commit})
    machine = f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)"
    stats = {k: paired([a[k] - b[k] for _, a, b in pairs]) for k in ("psnr", "ssim")}
    if all(a["lpips"] is not None and b["lpips"] is not None for _, a, b in pairs):
        stats["lpips"] = paired([a["lpips"] - b["lpips"] for _, a, b in pairs])
    views = sorted(pairs[0][1]["per_view_psnr"])
    per_view = {v: paired([a["per_view_psnr"][v] - b["per_view_psnr"][v] for _, a, b in pairs]) for v in views}
    with open(record.stem("paired", args.tag) + ".json", "w") as fh:
        fh.write(record.portable(json.dumps(
            {"command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit,
             "reused_run_commits": run_commits, "other_run_commits": other_commits,
             "reused_runs": [f"{r['label']}_s{r['seed']}" for r in reused],
             "machine": machine, "a": la, "b": lb, "runs": recs, "stats": stats, "per_view": per_view}, indent=1)))

    def mean(label: str, key: str) -> float:
        return statistics.mean(r[key] for r in recs if r["label"] == label)

    lp = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731
    lines = [f"# {la} (A) vs {lb} (B), paired by seed ({os.path.basename(os.path.normpath(args.scene))} {args.images})",
             "", f"Written by `benchmarks/paired.py {' '.join(sys.argv[1:])}` on {time.strftime('%Y-%m-%d %H:%M')}, "
             f"{machine}, commit {commit} at the start"
             + (f" ({len(reused)} finished run(s) reused from --work, trained at {', '.join(run_commits) or 'an unrecorded commit'})"
                if reused else "")
             + (f" (runs of this invocation trained at {', '.join(other_commits)}: commits made while it ran)"
                if other_commits else "")
             + (f". Trained on {args.trained_on}" if args.trained_on else
                f", CPU backend, {args.threads} thread per training, {args.parallel} trainings "
                "at a time in seed order (A and B of a seed start together)")
             + ". Test views: the protocol's every 8th; A and B were fixed before "
             "the runs, nothing was chosen from the test views. Metrics: `ctgs eval` of the exported model."
             + ("" if lpips else " LPIPS: not computed (no VGG weights; `make lpips-weights`)."), "",
             "| seed | run | iterations | wall min | test PSNR | SSIM | LPIPS | " + " | ".join(views) +
             " | primitives | params | params/value | MB |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | " + " | ".join("---:" for _ in views) + " | ---: | ---: | ---: | ---: |"]
    for s, a, b in pairs:
        for r in (a, b):
            ppv = r["params_per_value"]
            lines.append(f"| {s} | {r['label']} | {r['iterations']} | {r['wall_s'] / 60:.1f} | {r['psnr']:.2f} | "
                         f"{r['ssim']:.3f} | {lp(r['lpips'])} | " +
                         " | ".join(f"{r['per_view_psnr'][v]:.2f}" for v in views) +
                         f" | {r['primitives']} | {r['params']} | {'-' if ppv is None else f'{ppv:.2f}'} | {r['mb']:.2f} |")
    lines += ["", f"Means over {len(pairs)} seeds: {la} {mean(la, 'psnr'):.2f} dB / SSIM {mean(la, 'ssim'):.3f}, "
              f"{mean(la, 'primitives'):.0f} primitives, {mean(la, 'params') / 1e6:.2f}M params, {mean(la, 'wall_s') / 60:.1f} min; "
              f"{lb} {mean(lb, 'psnr'):.2f} dB / SSIM {mean(lb, 'ssim'):.3f}, {mean(lb, 'primitives'):.0f} primitives, "
              f"{mean(lb, 'params') / 1e6:.2f}M params, {mean(lb, 'wall_s') / 60:.1f} min.", "",
              "- " + sentence(f"PSNR {la} - {lb}", stats["psnr"]),
              f"- SSIM {la} - {lb}: mean {stats['ssim']['mean']:+.4f} (p = {stats['ssim']['p']:.3f})."]
    if "lpips" in stats:
        lines.append(f"- LPIPS {la} - {lb}: mean {stats['lpips']['mean']:+.4f} (p = {stats['lpips']['p']:.3f}; lower is better).")
    lines += ["", "Per test view (PSNR, paired by seed):", "", "| view | A - B mean | sd | p | 95% interval |",
              "| --- | ---: | ---: | ---: | --- |"]
    for v in views:
        st = per_view[v]
        lo, hi = st["ci95"]
        lines.append(f"| {v} | {st['mean']:+.2f} dB | {st['sd']:.2f} | {st['p']:.3f} | [{lo:+.2f}, {hi:+.2f}] |")
    out = record.stem("paired", args.tag) + ".md"
    with open(out, "w") as fh:
        fh.write(record.portable("\n".join(lines) + "\n"))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
