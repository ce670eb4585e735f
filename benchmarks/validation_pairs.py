"""Validation PSNR of paired runs, each read from its own train_summary.json (the renderer it trained with).

For a change that is not a setting (two code versions, e.g. a worktree at the commit before and the checkout), so
benchmarks/validation_runs.py, which renders every run with this checkout's renderer, cannot compare them: each
run's final evaluation was made by its own code. Runs must be validation runs (`--set validation_holdout=K`: the test
views are left out entirely; `final_test_psnr` is then the validation views' mean PSNR).

Usage: .venv/bin/python benchmarks/validation_pairs.py --work DIR --a-prefix new --b-prefix old \\
         --presets fast balanced --seeds 0 1 2 3 --max-loss 0.10 --out NAME [--note TEXT]
Runs are DIR/{prefix}_{preset}_s{seed}; pairs missing either run are skipped (and listed). Writes
benchmarks/results/validation_pairs/NAME_<commit>.{md,json}: per preset and seed, A and B validation PSNR / SSIM, params, primitives,
train seconds, and the mean difference A - B against the registered --max-loss (A passes a preset if its mean is not
lower than B's by more than it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402
from record import write_record  # noqa: E402


def summary(run: str) -> dict | None:
    path = os.path.join(run, "train_summary.json")
    if not os.path.exists(path):
        return None
    with open(os.path.join(run, "config.toml"), "rb") as fh:
        cfg = tomllib.load(fh)
    if int(cfg.get("validation_holdout", 0)) <= 0:
        raise SystemExit(f"{run}: not a validation run (validation_holdout = 0); train with --set validation_holdout=8")
    with open(path) as fh:
        return json.load(fh)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True)
    ap.add_argument("--a-prefix", required=True)
    ap.add_argument("--b-prefix", required=True)
    ap.add_argument("--presets", nargs="+", required=True)
    ap.add_argument("--seeds", nargs="+", type=int, required=True)
    ap.add_argument("--max-loss", type=float, required=True, help="dB: A passes if mean(A - B) >= -max_loss")
    ap.add_argument("--out", required=True)
    ap.add_argument("--note", default="")
    args = ap.parse_args()

    result = {"command": "benchmarks/validation_pairs.py " + " ".join(sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M"),
              "machine": f"{platform.node() or 'machine'} ({platform.machine()}, {os.cpu_count()} cpus)",
              "a": args.a_prefix, "b": args.b_prefix, "max_loss": args.max_loss, "note": args.note,
              "presets": {}, "missing": []}
    for preset in args.presets:
        rows = []
        for seed in args.seeds:
            ra, rb = (os.path.join(args.work, f"{p}_{preset}_s{seed}") for p in (args.a_prefix, args.b_prefix))
            a, b = summary(ra), summary(rb)
            if a is None or b is None:
                result["missing"].append(f"{preset} s{seed}")
                continue
            rows.append({"seed": seed, "a_run": ra, "b_run": rb,
                         **{f"{k}_{x}": r[key] for k, r in (("a", a), ("b", b))
                            for x, key in (("psnr", "final_test_psnr"), ("ssim", "final_test_ssim"),
                                           ("params", "num_params"), ("prims", "num_primitives"),
                                           ("train_s", "train_seconds"))}})
        if not rows:
            continue
        diffs = [r["a_psnr"] - r["b_psnr"] for r in rows]
        mean = statistics.fmean(diffs)
        result["presets"][preset] = {"rows": rows, "mean_diff": mean, "ahead": sum(d > 0 for d in diffs),
                                     "sd": statistics.stdev(diffs) if len(diffs) > 1 else 0.0,
                                     "passes": mean >= -args.max_loss}
    write_record(record.stem("validation_pairs", args.out), result, markdown)


def markdown(r: dict) -> str:
    a, b = r["a"], r["b"]
    lines = [f"# Validation pairs {a} vs {b} ({r['machine']})", "",
             f"Command: `{r['command']}` on {r['date']}. Each run's validation views (every 8th training view from the"
             " 4th; the test views are left out of training and of this table), evaluated by the code it trained with"
             " (train_summary.json).", ""]
    if r["note"]:
        lines += [r["note"], ""]
    for preset, p in r["presets"].items():
        lines += [f"## `{preset}`", "",
                  f"| seed | {a} PSNR | {b} PSNR | difference | {a} SSIM | {b} SSIM | {a} params | {b} params | "
                  f"{a} prims | {b} prims | {a} train min | {b} train min |",
                  "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for x in p["rows"]:
            lines.append(f"| {x['seed']} | {x['a_psnr']:.2f} | {x['b_psnr']:.2f} | {x['a_psnr'] - x['b_psnr']:+.2f} | "
                         f"{x['a_ssim']:.4f} | {x['b_ssim']:.4f} | {x['a_params'] / 1e6:.3f}M | "
                         f"{x['b_params'] / 1e6:.3f}M | {x['a_prims']} | {x['b_prims']} | {x['a_train_s'] / 60:.1f} | "
                         f"{x['b_train_s'] / 60:.1f} |")
        lines += ["", f"Mean difference {a} - {b}: **{p['mean_diff']:+.2f} dB** over {len(p['rows'])} seeds (ahead on "
                      f"{p['ahead']}; sd {p['sd']:.2f}); registered limit -{r['max_loss']:.2f} dB: "
                      f"**{'passes' if p['passes'] else 'fails'}**.", ""]
    if r["missing"]:
        lines += [f"Pairs not finished (left out): {', '.join(r['missing'])}.", ""]
    verdicts = {k: v["passes"] for k, v in r["presets"].items()}
    ok = bool(verdicts) and all(verdicts.values())
    lines += [f"Verdict: {a} {'passes' if ok else 'does not pass'} (" +
              ", ".join(f"{k}: {'yes' if v else 'no'}" for k, v in verdicts.items()) + ").", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
