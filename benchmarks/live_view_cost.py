"""What watching a training costs it: two identical trainings side by side (one thread each, same seed), one followed
by `ctgs view RUN_DIR` with its page open in headless Chromium (software GL: the CPU draws the page too), the other
not. The sides swap every round, so that a difference between the two cores or the two processes' start cancels out;
a control round (`--control`) runs both without a viewer to show the noise of the comparison itself.

Figures per training: train seconds (its steps and routines) and wall seconds (from its start to its model written,
evaluations and checkpoints included), both from train_summary.json; per round the viewer side's over the other's; the viewer's own CPU seconds (server and browser) and the
models the page drew. Results: benchmarks/results/live_view_cost/<scene>_<images>_<preset>_<iterations>it_<commit>.
{json,md}.

Usage: .venv/bin/python benchmarks/live_view_cost.py --scene /work/shared/data/bonsai252 --images images_4
       [--preset fast] [--iterations 600] [--rounds 2] [--control] [--work /tmp/ctgs_live_view_cost]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from datetime import datetime, timezone

import record
from headless import Browser
from viewer_page import ViewerPage

REPO = record.ROOT
POLL_S = 1.0


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": REPO}


def _train(args, run: str, log) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "ctgs", "train", args.scene, "-o", run, "--preset", args.preset, "--iterations",
           str(args.iterations), "--images", args.images, "--seed", "0", "-q", "--set", "threads=1"]
    return subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=log, stderr=subprocess.STDOUT)


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` so far (Linux /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Viewer:
    """`ctgs view RUN --port 0 --no-browser` and a headless Chromium page on it, as a user's open viewer."""

    def __init__(self, run: str, log):
        self.proc = subprocess.Popen([sys.executable, "-m", "ctgs", "view", run, "--port", "0", "--no-browser"],
                                     cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=log, text=True)
        line = self.proc.stdout.readline()
        m = re.search(r"at (http://127\.0\.0\.1:\d+/)", line)
        if not m:
            self.proc.kill()
            raise SystemExit(f"ctgs view did not start: {line!r}")
        self.url = m.group(1)
        self.browser = Browser()
        self.page = ViewerPage(self.browser, self.url)  # waits for the run's first checkpoint
        self.versions = 1

    def poll(self) -> None:
        self.versions = max(self.versions, int(self.browser.evaluate("window.viewer.modelVersion")))

    def close(self) -> dict:
        self.poll()
        cpu = {"server_cpu_s": _cpu_seconds(self.proc.pid), "browser_cpu_s": self.browser.cpu_seconds()}
        errors = self.browser.page_errors()
        self.browser.close()
        self.proc.terminate()
        self.proc.wait()
        return {**cpu, "models_drawn": self.versions, "page_errors": errors}  # (the version of the last one drawn)


def _summary(run: str, wall: float) -> dict:
    with open(os.path.join(run, "train_summary.json")) as f:
        s = json.load(f)
    return {"iterations": s["iterations"], "train_seconds": s["train_seconds"], "wall_seconds": s["wall_seconds"],
            "command_seconds": wall, "test_psnr": s["final_test_psnr"], "primitives": s["num_primitives"]}


def one_round(args, k: int, watched: str | None) -> dict:
    """Trainings a and b at once; `watched` ("a", "b" or None) is followed by a viewer."""
    runs = {side: os.path.join(args.work, f"round{k}_{side}") for side in "ab"}
    for run in runs.values():
        shutil.rmtree(run, ignore_errors=True)
    logs = {side: open(runs[side] + ".log", "w") for side in "ab"}
    t0 = time.monotonic()
    procs = {side: _train(args, runs[side], logs[side]) for side in "ab"}
    ends, viewer, seen = {}, None, {}
    try:
        if watched:
            while not os.path.exists(os.path.join(runs[watched], "config.toml")):
                time.sleep(0.2)
            viewer = Viewer(runs[watched], logs[watched])
        while len(ends) < 2:
            for side, p in procs.items():
                if side not in ends and p.poll() is not None:
                    ends[side] = time.monotonic() - t0
                    if p.returncode != 0:
                        raise SystemExit(f"training {runs[side]} failed ({p.returncode}); see {runs[side]}.log")
            if viewer is not None and watched not in ends:
                viewer.poll()
            time.sleep(POLL_S)
        if viewer is not None:
            seen = viewer.close()
            viewer = None
    finally:
        if viewer is not None:
            viewer.close()
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
        for f in logs.values():
            f.close()
    out = {"watched": watched, "loadavg_end": os.getloadavg(), **{s: _summary(runs[s], ends[s]) for s in "ab"}}
    if watched:
        other = "b" if watched == "a" else "a"
        out["viewer"] = seen
        # the most the viewer can have taken from the two trainings: its CPU over the machine's while the run went on
        out["viewer_share"] = (seen["server_cpu_s"] + seen["browser_cpu_s"]) / (ends[watched] * os.cpu_count())
        for key in ("train_seconds", "wall_seconds"):
            out[f"{key}_ratio"] = out[watched][key] / out[other][key]
    else:
        for key in ("train_seconds", "wall_seconds"):
            out[f"{key}_ratio"] = out["a"][key] / out["b"][key]
    return out


def machine() -> dict:
    cpu = ""
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
    except OSError:
        pass
    return {"host": platform.node(), "cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version()}


def markdown(r: dict) -> str:
    m = r["machine"]
    lines = [f"# The cost of watching a training: `ctgs view RUN_DIR` open beside it ({r['name']})", "",
             f"Written by benchmarks/live_view_cost.py on {r['date']} at commit {r['commit']}. Command: "
             f"`{r['command']}`", "",
             f"Machine: {m['cpu']}, {m['cores']} cores ({m['host']}); load average {r['loadavg_start'][0]:.2f} at "
             f"start (a shared machine: the two trainings of a round see the same load). Two identical trainings "
             f"at once, one thread each: scene {r['scene']} ({r['images']}), preset {r['preset']}, "
             f"{r['iterations']} iterations, seed 0. The watched one is followed by `ctgs view RUN_DIR` with its "
             f"page open in headless Chromium (SwiftShader: the CPU draws the page, the worst case; "
             f"800x600 image area), polling every 2 s and drawing each checkpoint as it lands.", "",
             "| round | watched | train s (watched / other) | ratio | wall s (watched / other) | ratio | "
             "newest model drawn (its version) | viewer CPU s (server + browser) | viewer's share of the machine |",
             "| --- | --- | --- | ---: | --- | ---: | ---: | ---: | ---: |"]
    for k, rd in enumerate(r["rounds"], 1):
        w = rd["watched"]
        if w:
            o = "b" if w == "a" else "a"
            v = rd["viewer"]
            lines.append(f"| {k} | {w} | {rd[w]['train_seconds']:.1f} / {rd[o]['train_seconds']:.1f} | "
                         f"{rd['train_seconds_ratio']:.3f} | {rd[w]['wall_seconds']:.1f} / "
                         f"{rd[o]['wall_seconds']:.1f} | {rd['wall_seconds_ratio']:.3f} | {v['models_drawn']} | "
                         f"{v['server_cpu_s']:.1f} + {v['browser_cpu_s']:.1f} | {100 * rd['viewer_share']:.1f}% |")
        else:
            lines.append(f"| {k} | none (control: a / b) | {rd['a']['train_seconds']:.1f} / "
                         f"{rd['b']['train_seconds']:.1f} | {rd['train_seconds_ratio']:.3f} | "
                         f"{rd['a']['wall_seconds']:.1f} / {rd['b']['wall_seconds']:.1f} | "
                         f"{rd['wall_seconds_ratio']:.3f} | - | - | - |")
    lines += ["", f"Slowdown of the watched training, mean over the rounds with a viewer: train seconds "
              f"**{100 * (r['mean_train_ratio'] - 1):+.1f}%**, wall seconds **{100 * (r['mean_wall_ratio'] - 1):+.1f}%**"
              + (f"; the control rounds (no viewer on either side) differ by "
                 f"{', '.join(f'{100 * (x - 1):+.1f}%' for x in r['control_train_ratios'])} (train seconds)."
                 if r["control_train_ratios"] else "."),
              "", "The viewer's CPU (server and browser) is taken from both trainings alike, so the ratio of the two "
              "sides shows what it costs the watched run beyond the other; its share of the machine's CPU while the "
              f"run went on bounds what it takes from both: **{100 * r['mean_viewer_share']:.1f}%** (mean over the "
              "rounds; CPU seconds over wall seconds times cores). With a GPU the browser's drawing leaves the CPU.",
              ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--images", default="images")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--rounds", type=int, default=2, help="rounds with a viewer, its side swapped each round")
    ap.add_argument("--control", action="store_true", help="one more round with no viewer on either side")
    ap.add_argument("--work", default="/tmp/ctgs_live_view_cost")
    ap.add_argument("--name", default=None, help="record name (default: scene_images_preset_<N>it)")
    args = ap.parse_args()
    os.makedirs(args.work, exist_ok=True)
    start = os.getloadavg()
    plan = ["a" if k % 2 == 0 else "b" for k in range(args.rounds)] + ([None] if args.control else [])
    rounds = []
    for k, watched in enumerate(plan, 1):
        print(f"round {k}: {'viewer on ' + watched if watched else 'control, no viewer'}", flush=True)
        rounds.append(one_round(args, k, watched))
        print(json.dumps({key: v for key, v in rounds[-1].items() if key.endswith("ratio")}), flush=True)
    watched = [rd for rd in rounds if rd["watched"]]
    name = args.name or (f"{os.path.basename(os.path.normpath(args.scene))}_{args.images}_{args.preset}_"
                         f"{args.iterations}it")
    result = {"name": name, "scene": os.path.basename(os.path.normpath(args.scene)), "images": args.images,
              "preset": args.preset, "iterations": args.iterations, "rounds": rounds,
              "mean_train_ratio": sum(rd["train_seconds_ratio"] for rd in watched) / len(watched),
              "mean_wall_ratio": sum(rd["wall_seconds_ratio"] for rd in watched) / len(watched),
              "control_train_ratios": [rd["train_seconds_ratio"] for rd in rounds if not rd["watched"]],
              "mean_viewer_share": sum(rd["viewer_share"] for rd in watched) / len(watched),
              "commit": record.commit(), "machine": machine(), "loadavg_start": start,
              "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "command": " ".join([os.path.relpath(sys.executable, REPO)] + sys.argv)}
    record.write_record(record.stem("live_view_cost", name), result, markdown)


if __name__ == "__main__":
    main()
