"""Per-phase timing of training runs from their log.jsonl (trains nothing).

Phases of the paper's schedule (at 30k iterations: texture start 500, tau_tr settles at 7000, last full
routine 25000, then the tail; for the 2dgs/3dgs baselines: before densification (500), densification (until
15000), the tail), read from each run's config.toml: for each phase the iterations the log
covers, training seconds per 1000 iterations (the trainer's own `seconds`: steps and routines, without
test evaluations and checkpoints), primitives and texels at the end of what was covered, peak CUDA memory
(`cuda_peak_mb`), and every test-view PSNR/SSIM the run logged. A run stopped early (the device's time
ran out) is extrapolated to its planned iterations at the rate of the last 1000 iterations it ran, and the
table labels that figure as an extrapolation.

    python benchmarks/gpu_train_phases.py RUN_DIR [RUN_DIR ...] --machine machine.json -o OUT (.md, .json)
"""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path


def phases(cfg: dict) -> list[tuple[str, int, int]]:
    n = int(cfg.get("iterations", 30000))
    scale = n / 30000.0 if not cfg.get("schedule_scale") else float(cfg["schedule_scale"])
    if cfg.get("method", "content_aware") != "content_aware":  # the baselines' schedule: 3DGS/2DGS densification
        d0 = round(cfg.get("densify_from", 500) * scale)
        d1 = min(round(cfg.get("densify_until", 15000) * scale), n)
        return [("before densification", 0, d0), ("densification", d0, d1), ("tail", d1, n)]
    ts = round(cfg.get("texture_start", 500) * scale)
    tau = round(cfg.get("tau_tr_iters", 7000) * scale)
    last = min(round(cfg.get("routine_until", 25000) * scale), n - round(cfg.get("routine_margin", 3000) * scale))
    return [("before texture start", 0, ts), ("until tau_tr settles", ts, tau), ("until the last routine", tau, last),
            ("tail", last, n)]


def summarise(run: Path) -> dict:
    cfg = tomllib.loads((run / "config.toml").read_text())
    recs = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    steps = [r for r in recs if r["type"] == "step"]
    tests = [{"it": r["it"], "psnr": r["psnr"], "ssim": r["ssim"]} for r in recs if r["type"] == "test"]
    start = next((r for r in recs if r["type"] == "start"), {})
    last_it = steps[-1]["it"] if steps else 0
    planned = int(cfg.get("iterations", 30000))
    rows = []
    for name, a, b in phases(cfg):
        inside = [s for s in steps if a < s["it"] <= b]
        before = [s for s in steps if s["it"] <= a]
        if not inside:
            rows.append({"phase": name, "from": a, "to": b, "covered": 0})
            continue
        s0 = before[-1] if before else {"it": 0, "seconds": 0.0}
        s1 = inside[-1]
        rows.append({"phase": name, "from": a, "to": b, "covered": s1["it"] - s0["it"],
                     "s_per_1000": 1000 * (s1["seconds"] - s0["seconds"]) / max(1, s1["it"] - s0["it"]),
                     "primitives": s1["n"], "texels": s1["texels"], "cuda_peak_mb": s1.get("cuda_peak_mb")})
    tail = [s for s in steps if s["it"] > last_it - 1000]
    rate = (1000 * (tail[-1]["seconds"] - tail[0]["seconds"]) / max(1, tail[-1]["it"] - tail[0]["it"])
            if len(tail) > 1 else None)
    extrap = None
    if steps and last_it < planned and rate:
        extrap = steps[-1]["seconds"] + (planned - last_it) * rate / 1000
    return {"run": run.name, "method": cfg.get("method", start.get("method")), "device": start.get("device"),
            "planned_iterations": planned, "iterations_run": last_it,
            "train_seconds": steps[-1]["seconds"] if steps else 0.0, "wall_seconds": steps[-1]["wall"] if steps else 0.0,
            "phases": rows, "tests": tests, "last_rate_s_per_1000": rate,
            "extrapolated_train_seconds": extrap, "pixels": start.get("pixels")}


def to_markdown(runs: list[dict], machine: dict, note: str = "") -> str:
    lines = ["# Paper-scale training on a GPU: per-phase timing", ""]
    if note:
        lines += [note, ""]
    if machine:
        lines += [f"Machine: {machine.get('gpu')} (driver {machine.get('driver')}), torch {machine.get('torch')}, "
                  f"CUDA {machine.get('cuda')}, Python {machine.get('python')}; command: "
                  f"`{machine.get('command', '?')}`.", ""]
    for r in runs:
        lines += [f"## {r['run']} ({r['method']}, {r['device']}, {r['pixels']:.0f} px per image)", "",
                  f"Ran {r['iterations_run']:,} of {r['planned_iterations']:,} iterations in {r['train_seconds']:.1f} s "
                  f"of training ({r['wall_seconds']:.1f} s wall, evaluations and checkpoints included).", "",
                  "| phase | iterations | covered | s / 1000 it. | primitives | texels | peak CUDA MB |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for p in r["phases"]:
            if not p["covered"]:
                lines.append(f"| {p['phase']} | {p['from']:,}-{p['to']:,} | not reached | - | - | - | - |")
                continue
            mb = f"{p['cuda_peak_mb']:,.0f}" if p.get("cuda_peak_mb") is not None else "-"
            lines.append(f"| {p['phase']} | {p['from']:,}-{p['to']:,} | {p['covered']:,} | {p['s_per_1000']:.1f} | "
                         f"{p['primitives']:,} | {p['texels']:,} | {mb} |")
        if r["extrapolated_train_seconds"]:
            lines += ["", f"**Extrapolation, not a measurement**: {r['planned_iterations']:,} iterations at the rate of "
                          f"the last 1000 run ({r['last_rate_s_per_1000']:.1f} s / 1000) would take "
                          f"{r['extrapolated_train_seconds'] / 60:.1f} min of training; the phases not reached "
                          "change the primitive and texel counts, so the true figure differs."]
        if r["tests"]:
            lines += ["", "Test views (every 8th photo) during the run: " +
                      ", ".join(f"it {t['it']}: {t['psnr']:.2f} dB / SSIM {t['ssim']:.3f}" for t in r["tests"])]
        lines.append("")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--machine", type=Path)
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--note", default="", help="a paragraph under the title (where the runs come from, what differs)")
    args = ap.parse_args()
    machine = json.loads(args.machine.read_text()) if args.machine and args.machine.is_file() else {}
    runs = [summarise(r) for r in args.runs]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix(".json").write_text(json.dumps({"machine": machine, "runs": runs, "note": args.note},
                                                           indent=1) + "\n")
    md = to_markdown(runs, machine, args.note)
    args.output.with_suffix(".md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
