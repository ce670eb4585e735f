"""Thread scaling of CPU training (issue: CPU speed): 1 vs 2+ threads, libgomp's spin-wait (active) vs passive.

Runs benchmarks/profile_train.py (same snapshot, same window) once per (scene, OMP_WAIT_POLICY, threads, repeat),
one after the other, and writes the table benchmarks/results/<out>/thread_scaling.md with the it/s ratio per
policy and the per-phase speedup of the first pair, so what does not scale is visible. Measure on an otherwise
idle machine (the load average at each start is in the table): on a loaded machine a thread parked behind
another job makes every parallel region wait. Before each pair a control measures what the machine gives two
threads at that moment: a compute-bound float32 matmul (384 x 384, L2-resident, torch's own OpenMP pool) at
1 and at 2 threads; its ratio is the ceiling no training step can beat there (shared vCPUs, SMT siblings).

Usage: .venv/bin/python benchmarks/thread_scaling.py --scene demo=/path/to/demo:images
           --scene herzjesu25=/work/data/herzjesu25:images_8 --config CONFIG.toml [--threads 1 2]
           [--policies active passive] [--repeats a b] [--state-at 150] [--window 100]
           [--work /tmp/ctgs_threads] [--out threads_idle] [--table-only]
CONFIG: a training config whose snapshot/window are representative, e.g. configs/fast.toml with
iterations = 300, schedule_scale = 0.1, routine_margin = 0 (the 3000-iteration schedule, a full routine at 200).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", action="append", required=True, help="NAME=DIR:IMAGES")
    ap.add_argument("--config", required=True)
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--policies", nargs="+", default=["active", "passive"])
    ap.add_argument("--repeats", nargs="+", default=["a", "b"])
    ap.add_argument("--state-at", type=int, default=150)
    ap.add_argument("--window", type=int, default=100)
    ap.add_argument("--work", default="/tmp/ctgs_threads")
    ap.add_argument("--out", default="threads_idle")
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args()
    out = os.path.join(ROOT, "benchmarks", "results", args.out)
    os.makedirs(out, exist_ok=True)
    scenes = []
    for spec in args.scene:
        name, rest = spec.split("=", 1)
        path, images = rest.rsplit(":", 1)
        scenes.append((name, path, images))
    if not args.table_only:
        for name, path, images in scenes:
            for rep in args.repeats:
                for pol in args.policies:
                    for t in args.threads:
                        env = dict(os.environ, OMP_NUM_THREADS=str(t), OMP_WAIT_POLICY=pol)
                        cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "profile_train.py"), path,
                               "--tag", name, "--label", f"threads{t}_{pol}_{rep}", "--images", images,
                               "--config", args.config, "--state-at", str(args.state_at), "--window",
                               str(args.window), "--threads", str(t), "--work", args.work, "--out", out]
                        if t == args.threads[0]:
                            control(out, f"{name}_{pol}_{rep}", args.threads, env)
                        subprocess.run(cmd, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    write_table(out, [s[0] for s in scenes], args)


CONTROL = """
import json, sys, time, torch
a, b = torch.randn(384, 384), torch.randn(384, 384)
def rate(nt, secs=1.0):
    torch.set_num_threads(nt)
    for _ in range(20):
        a @ b
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < secs:
        for _ in range(20):
            a @ b
        n += 20
    return n / (time.perf_counter() - t0)
print(json.dumps({str(t): rate(t) for t in map(int, sys.argv[1:])}))
"""


def control(out: str, key: str, threads: list[int], env: dict) -> None:
    """Matmuls per second at each thread count, right before a pair of training runs (CONTROL)."""
    res = subprocess.run([sys.executable, "-c", CONTROL, *map(str, threads)], check=True, env=env,
                         capture_output=True, text=True)
    with open(os.path.join(out, f"control_{key}.json"), "w") as fh:
        fh.write(res.stdout)


def write_table(out: str, names: list[str], args) -> None:
    rows = {}
    for f in glob.glob(os.path.join(out, "profile_*.json")):
        with open(f) as fh:
            d = json.load(fh)
        if d["tag"] in names:
            t, pol, rep = d["label"].split("_")
            rows[(d["tag"], pol, rep, int(t[len("threads"):]))] = d
    if not rows:
        return
    any_row = next(iter(rows.values()))
    m = any_row["machine"]
    machine = ", ".join(str(m[k]) for k in ("host", "cpu", "cores") if k in m) + " cores" if isinstance(m, dict) else m
    lines = ["# Thread scaling of CPU training", "",
             f"Written by `benchmarks/thread_scaling.py {' '.join(sys.argv[1:])}` on {any_row['date']} "
             f"({machine}, torch {any_row['torch']}, commit {any_row['commit']}). Each row: "
             f"benchmarks/profile_train.py, iterations {args.state_at}..{args.state_at + args.window} from one "
             "snapshot per scene (the command is in each JSON file), runs one after the other; wall-clock it/s "
             "including routines. Load average (1 min) at each start: the run before it counts in it.", "",
             "| scene | OMP_WAIT_POLICY | repeat | it/s 1 thread | it/s 2 threads | speedup | control (matmul) speedup "
             "| speedup / control | load at start (1 thr / 2 thr) |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    ts = sorted({k[3] for k in rows})
    lo, hi = ts[0], ts[-1]
    for (tag, pol, rep, t) in sorted(rows):
        if t != lo or (tag, pol, rep, hi) not in rows:
            continue
        a, b = rows[(tag, pol, rep, lo)], rows[(tag, pol, rep, hi)]
        speedup = b["it_per_s"] / a["it_per_s"]
        ctrl_path = os.path.join(out, f"control_{tag}_{pol}_{rep}.json")
        ctrl, ratio = "-", "-"
        if os.path.exists(ctrl_path):
            with open(ctrl_path) as fh:
                c = json.load(fh)
            if str(lo) in c and str(hi) in c:
                cs = c[str(hi)] / c[str(lo)]
                ctrl, ratio = f"{cs:.2f}x", f"{speedup / cs:.2f}"
        lines.append(f"| {tag} | {pol} | {rep} | {a['it_per_s']:.2f} | {b['it_per_s']:.2f} | "
                     f"{speedup:.2f}x | {ctrl} | {ratio} | {a['loadavg_start'][0]:.2f} / "
                     f"{b['loadavg_start'][0]:.2f} |")
    for tag in names:
        for pol in sorted({k[1] for k in rows if k[0] == tag}):
            sp = sorted(rows[(tag, pol, r, hi)]["it_per_s"] / rows[(tag, pol, r, lo)]["it_per_s"]
                        for (t2, p2, r, t) in rows if t2 == tag and p2 == pol and t == lo and (tag, pol, r, hi) in rows)
            if sp:
                lines.append(f"\nMedian speedup {tag}, {pol}: {statistics.median(sp):.2f}x over {len(sp)} repeats "
                             f"(range {sp[0]:.2f}-{sp[-1]:.2f}x).")
    for tag in names:
        keys = sorted(k for k in rows if k[0] == tag and k[1] == "active" and k[3] == lo)
        if not keys or (tag, "active", keys[-1][2], hi) not in rows:
            continue
        rep = keys[-1][2]
        pa, pb = rows[(tag, "active", rep, lo)]["per_iteration_s"], rows[(tag, "active", rep, hi)]["per_iteration_s"]
        lines += ["", f"Per phase, {tag}, active, repeat {rep} (ms per iteration; phases >= 1 ms):", "",
                  f"| phase | {lo} thread | {hi} threads | speedup |", "| --- | ---: | ---: | ---: |"]
        for k, v in pa.items():
            if v >= 1e-3 and pb.get(k):
                lines.append(f"| {k} | {v * 1e3:.1f} | {pb[k] * 1e3:.1f} | {v / pb[k]:.2f}x |")
    with open(os.path.join(out, "thread_scaling.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
