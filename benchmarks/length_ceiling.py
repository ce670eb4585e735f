"""How far run length takes each recipe on validation views: the seed-mean validation curves of several recipes,
their final values and the peak of each curve (the best length chosen with hindsight, an optimistic bound).

    .venv/bin/python benchmarks/length_ceiling.py RUN [RUN ...] --name NAME --reference fast [--margin 1.0]
        [--status status.json] [--machine machine.json] [--cpu RECIPE=P0,P1,... --cpu-source FILE]

Each RUN is a training folder of a tuning-mode run (`--set validation_holdout=K`), named RECIPE_sSEED; its
log.jsonl's periodic evaluations are on validation views (the test views were left out of training). Runs that were
stopped before their last iteration count with the curve they logged, and the table says where they stopped.
Writes benchmarks/results/length_ceiling_NAME.md and .json (or under --out-dir): per recipe the final validation PSNR of each seed (for
finished runs), the seed-mean curve, and its peak against the reference recipe's final mean + margin. --cpu adds
the same recipe's final validation PSNR per seed trained elsewhere (another backend), for a cross-check of the means.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def read_run(run: str) -> dict:
    evals, planned, last_it = {}, None, 0
    with open(os.path.join(run, "log.jsonl")) as fh:
        for line in fh:
            d = json.loads(line)
            if d.get("type") == "test":
                evals[int(d["it"])] = (float(d["psnr"]), float(d["ssim"]))
            if d.get("type") == "step":
                last_it = max(last_it, int(d["it"]))
    cfg = os.path.join(run, "config.toml")
    if os.path.exists(cfg):
        m = re.search(r"^iterations\s*=\s*(\d+)", open(cfg).read(), re.M)
        planned = int(m.group(1)) if m else None
    summary = os.path.join(run, "train_summary.json")
    done = os.path.exists(summary)
    final, train_s = None, None
    if done:
        s = json.load(open(summary))
        final = (float(s["final_test_psnr"]), float(s["final_test_ssim"]))
        train_s = s.get("train_seconds")
    if not evals:
        raise SystemExit(f"length_ceiling.py: {run}/log.jsonl has no evaluations; train with --set test_every=N")
    last_it = max(last_it, max(evals))  # a thinned log keeps every evaluation but not every step
    return {"evals": evals, "planned": planned, "last_it": last_it, "done": done, "final": final, "train_s": train_s}


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--name", required=True)
    ap.add_argument("--reference", required=True, help="the recipe whose final mean the peaks are measured against")
    ap.add_argument("--margin", type=float, default=1.0)
    ap.add_argument("--status", help="run_many.py's status.json (states and wall seconds)")
    ap.add_argument("--machine", help="machine.json of the device call")
    ap.add_argument("--cpu", action="append", default=[], help="RECIPE=P0,P1,...: final PSNR per seed elsewhere")
    ap.add_argument("--cpu-source", default="", help="the record the --cpu values come from")
    ap.add_argument("--note", default="")
    ap.add_argument("--out-dir", default=os.path.join(ROOT, "benchmarks", "results"))
    args = ap.parse_args(argv)

    recipes: dict[str, dict[int, dict]] = {}
    for r in args.runs:
        m = re.fullmatch(r"(.+)_s(\d+)", os.path.basename(os.path.normpath(r)))
        if not m:
            raise SystemExit(f"length_ceiling.py: {r}: name the run folder RECIPE_sSEED")
        recipes.setdefault(m.group(1), {})[int(m.group(2))] = read_run(r)
    if args.reference not in recipes:
        raise SystemExit(f"length_ceiling.py: no runs of the reference recipe {args.reference!r}")
    status = json.load(open(args.status))["jobs"] if args.status else {}
    machine = json.load(open(args.machine)) if args.machine else {}

    ref = recipes[args.reference]
    ref_final = [ref[s]["final"][0] for s in sorted(ref) if ref[s]["done"]]
    if not ref_final:
        raise SystemExit(f"length_ceiling.py: no run of {args.reference!r} finished: it has no final value")
    ref_mean = statistics.fmean(ref_final)
    out = {"name": args.name, "reference": args.reference, "reference_final_mean": ref_mean, "margin": args.margin,
           "machine": machine, "recipes": {}}
    lines = [f"# How far run length takes each recipe on validation views: {args.name}", "",
             f"Command: `benchmarks/length_ceiling.py {' '.join(sys.argv[1:] if argv is None else argv)}`." + (f" Device: {machine.get('gpu')}, torch {machine.get('torch')}, "
                                                    f"CUDA {machine.get('cuda')}." if machine else ""),
             "Each run's periodic evaluations on its validation views (tuning mode: the test views were left out of "
             "training and are not used here). Peak = the highest seed-mean value along the curve, at the length "
             "chosen with hindsight on these views: an optimistic bound for 'some length of this recipe'.", ""]
    if args.note:
        lines += [args.note, ""]
    lines += ["## Runs", "", "| recipe | seed | iterations run / planned | state | wall s | final PSNR / SSIM | "
              "curve peak PSNR (at it) |", "| --- | ---: | ---: | --- | ---: | ---: | ---: |"]
    for name, runs in recipes.items():
        for s in sorted(runs):
            r = runs[s]
            st = status.get(f"{name}_s{s}", {})
            state = "finished" if r["done"] else "stopped"
            pk = max(r["evals"], key=lambda i: r["evals"][i][0])
            fin = f"{r['final'][0]:.2f} / {r['final'][1]:.3f}" if r["done"] else "-"
            wall = st.get("wall_s", f"{r['train_s']:.0f} (training)" if r["train_s"] is not None else "-")
            lines.append(f"| {name} | {s} | {r['last_it']} / {r['planned']} | {state} | {wall} | "
                         f"{fin} | {r['evals'][pk][0]:.2f} ({pk}) |")
    lines += ["", "## Seed-mean validation curves", "",
              "At the evaluations every run of the recipe reached (PSNR / SSIM, mean over its seeds).", ""]
    for name, runs in recipes.items():
        common = sorted(set.intersection(*[set(r["evals"]) for r in runs.values()]))
        mean = {i: (statistics.fmean(r["evals"][i][0] for r in runs.values()),
                    statistics.fmean(r["evals"][i][1] for r in runs.values())) for i in common}
        pk = max(mean, key=lambda i: mean[i][0])
        finals = [runs[s]["final"][0] for s in sorted(runs) if runs[s]["done"]]
        rec = {"seeds": sorted(runs), "finished": sum(r["done"] for r in runs.values()),
               "planned": sorted({r["planned"] for r in runs.values()}),
               "reached": min(r["last_it"] for r in runs.values()),
               "curve": {str(i): mean[i] for i in common}, "peak_it": pk, "peak_psnr": mean[pk][0],
               "final_mean": statistics.fmean(finals) if len(finals) == len(runs) else None,
               "peak_minus_reference_final": mean[pk][0] - ref_mean}
        out["recipes"][name] = rec
        lines += [f"### {name} ({len(runs)} seeds, {rec['finished']} finished; evaluated up to iteration "
                  f"{common[-1]} of {'/'.join(map(str, rec['planned']))})", "",
                  "| iteration | " + " | ".join(str(i) for i in common) + " |",
                  "| --- |" + " ---: |" * len(common),
                  "| PSNR | " + " | ".join(f"{mean[i][0]:.2f}" for i in common) + " |",
                  "| SSIM | " + " | ".join(f"{mean[i][1]:.3f}" for i in common) + " |", ""]
    lines += ["## Against the reference", "",
              f"`{args.reference}` final validation PSNR, mean of {len(ref_final)} seeds: **{ref_mean:.2f} dB**; the "
              f"goal's margin: +{args.margin:.1f} dB, so {ref_mean + args.margin:.2f} dB.", "",
              "| recipe | final mean | curve peak (iteration) | peak - reference final | reaches the margin |",
              "| --- | ---: | ---: | ---: | --- |"]
    for name, rec in out["recipes"].items():
        fm = f"{rec['final_mean']:.2f}" if rec["final_mean"] is not None else "- (stopped)"
        reach = "yes" if rec["peak_minus_reference_final"] >= args.margin else "no"
        if rec["reached"] < max(rec["planned"]):
            reach += f" (curve only to iteration {rec['reached']})"
        lines.append(f"| {name} | {fm} | {rec['peak_psnr']:.2f} ({rec['peak_it']}) | "
                     f"{rec['peak_minus_reference_final']:+.2f} | {reach} |")
    if args.cpu:
        lines += ["", "## Cross-check: the same recipes and seeds trained elsewhere", "",
                  f"Final validation PSNR per seed from {args.cpu_source or 'another record'}; the two trainings "
                  "diverge over a run, so only the means are comparable.", "",
                  "| recipe | here (per seed) | there (per seed) | mean here - there |", "| --- | --- | --- | ---: |"]
        out["cross_check"] = {}
        for item in args.cpu:
            name, vals = item.split("=", 1)
            there = [float(v) for v in vals.split(",")]
            runs = recipes.get(name, {})
            here = [runs[s]["final"][0] for s in sorted(runs) if runs[s]["done"]]
            if len(here) != len(runs) or not here:
                lines.append(f"| {name} | not all finished | {', '.join(f'{v:.2f}' for v in there)} | - |")
                continue
            d = statistics.fmean(here) - statistics.fmean(there)
            out["cross_check"][name] = {"here": here, "there": there, "difference": d}
            lines.append(f"| {name} | {', '.join(f'{v:.2f}' for v in here)} | "
                         f"{', '.join(f'{v:.2f}' for v in there)} | {d:+.2f} |")
    base = os.path.join(args.out_dir, f"length_ceiling_{args.name}")
    for ext, text in ((".md", "\n".join(lines) + "\n"), (".json", json.dumps(out, indent=1) + "\n")):
        with open(base + ext + ".tmp", "w") as fh:
            fh.write(text)
        os.replace(base + ext + ".tmp", base + ext)
    print(base + ".md")
    return base


if __name__ == "__main__":
    main()
