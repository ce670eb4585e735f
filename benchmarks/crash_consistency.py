"""A training under random kill -9s, resumed after each, against an uninterrupted run of the same seed.

Usage:
  .venv/bin/python benchmarks/crash_consistency.py --work /tmp/ctgs_crash [--kills 20] [--iterations 600]
      [--views 12 --width 128 --height 96] [--seed 0] [--name NAME] [--no-record]

On a demo scene, one `ctgs train` runs to the end untouched (the reference). Another, with the same options, is
started, SIGKILLed at a random moment, and started again as the Makefile's train rule starts it (`--resume` when
ctgs.runs.checkpoint finds a readable checkpoint, a fresh start otherwise), --kills times; the last
start runs to the end. A kill lands anywhere: while Python and the extension load, before the first checkpoint,
inside a step, a checkpoint, a log line or the final writes. On a CPU a resume replays the steps since its checkpoint
exactly, so the two model.pt files must hold the same tensors, bit for bit, and the logs the same step records.
Record: benchmarks/results/crash_consistency/<name>_<commit>.{json,md}, the machine and the date inside.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402
from profile_train import machine  # noqa: E402

# what varies between two identical runs: wall and CPU times (and every key ending in _s)
TIMED = ("seconds", "wall")


def _ctgs(*args: str) -> list[str]:
    return [sys.executable, "-m", "ctgs", *args]


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1"}


def train_args(scene: str, run: str, opts: argparse.Namespace) -> list[str]:
    extra = ["--set", f"checkpoint_every={opts.checkpoint_every}"] if opts.checkpoint_every else []
    return ["train", scene, "-o", run, "--preset", "fast", "--iterations", str(opts.iterations), "--seed",
            str(opts.seed), "--backend", "cpu", "-q", "--set", "threads=1", *extra]


def resume_flag(run: str) -> list[str]:
    """What the Makefile's train rule asks before each start (`python -m ctgs.runs.checkpoint RUN`, here in-process)."""
    return ["--resume"] if checkpoint_iteration(run) is not None else []


def checkpoint_iteration(run: str) -> int | None:
    from ctgs.runs.checkpoint import readable_checkpoint

    found = readable_checkpoint(run)
    return None if found is None else found[1]


def _wait_for_a_step(run: str, proc: subprocess.Popen, after_it: int) -> None:
    """Until the run's log holds a step past iteration `after_it` (the start is training) or the process ends."""
    path = os.path.join(run, "log.jsonl")
    while proc.poll() is None:
        try:
            with open(path, encoding="utf-8") as fh:
                lines = fh.read().splitlines()
        except OSError:
            lines = []
        for line in reversed(lines):
            try:
                rec = json.loads(line)
            except ValueError:
                continue  # a line being written
            if rec.get("type") == "step":
                if rec.get("it", 0) > after_it:
                    return
                break
        time.sleep(0.02)


def killed_run(scene: str, run: str, opts: argparse.Namespace, rng: random.Random, start_s: float,
               step_s: float) -> dict:
    """Start, kill at a random moment, resume, --kills times, then to the end. A quarter of the kills land while a
    start loads (within the first half of the reference's start-up, start_s: a start-up's length varies with the
    machine's load), the others in its training: once the start has logged a step past its checkpoint, after up to
    twice the left training's share of the kills left (step_s a step), so they spread over the whole run rather than
    the first ones ending it, and none waits past a start-up that came quicker than the reference's."""
    kills = []
    starts = 0
    while not os.path.isfile(os.path.join(run, "model.pt")):
        flag = resume_flag(run)
        proc = subprocess.Popen(_ctgs(*train_args(scene, run, opts), *flag), stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True, env=_env())
        starts += 1
        if len(kills) < opts.kills:
            began = time.monotonic()
            resumed_at = checkpoint_iteration(run) or 0
            left = opts.iterations - resumed_at
            share = step_s * left / (opts.kills - len(kills) + 1)
            in_start = rng.random() < 0.25
            delay = rng.uniform(0.1, 0.5 * start_s) if in_start else rng.uniform(0.0, 2.0 * share)
            if not in_start:
                _wait_for_a_step(run, proc, resumed_at)
            try:
                proc.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGKILL)
            err = proc.communicate()[1]
            if proc.returncode == -signal.SIGKILL:
                kills.append({"after_s": round(time.monotonic() - began, 2), "resumed": bool(flag),
                              "checkpoint_it": checkpoint_iteration(run)})
                continue
        else:
            err = proc.communicate(timeout=opts.timeout)[1]
        if proc.returncode != 0:
            raise RuntimeError(f"start {starts} ({' '.join(flag) or 'fresh'}) ended {proc.returncode}: {err[-2000:]}")
    return {"kills": kills, "starts": starts}


def _steps(run: str) -> list[dict]:
    """The log's step, routine and test records without their times."""
    out = []
    with open(os.path.join(run, "log.jsonl"), encoding="utf-8") as fh:
        for line in fh:
            d = json.loads(line)
            if d.get("type") in ("step", "routine", "test"):
                out.append({k: v for k, v in d.items() if k not in TIMED and not k.endswith("_s")})
    return out


def compare(ref: str, run: str) -> dict:
    """How far `run`'s model.pt and log are from `ref`'s: tensors equal or their largest differences."""
    import torch

    a = torch.load(os.path.join(ref, "model.pt"), map_location="cpu", weights_only=True)["model"]
    b = torch.load(os.path.join(run, "model.pt"), map_location="cpu", weights_only=True)["model"]
    diffs = {}
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if not (isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor)):
            if x != y:
                diffs[key] = f"{x!r} vs {y!r}"
        elif x.shape != y.shape:
            diffs[key] = f"shape {list(x.shape)} vs {list(y.shape)}"
        elif not torch.equal(x, y):
            diffs[key] = float((x.double() - y.double()).abs().max())
    sa, sb = (json.load(open(os.path.join(r, "train_summary.json"))) for r in (ref, run))
    logs_equal = _steps(ref) == _steps(run)
    return {"identical": not diffs and logs_equal, "tensor_diffs": diffs, "logs_equal": logs_equal,
            **{k: [sa[k], sb[k]] for k in ("iterations", "final_test_psnr", "num_primitives", "num_texels")}}


def run_check(work: str, opts: argparse.Namespace) -> dict:
    """The whole check in `work` (made; its runs replaced): reference, killed run, comparison."""
    os.makedirs(work, exist_ok=True)
    scene = os.path.join(work, "scene")
    subprocess.run(_ctgs("demo-scene", scene, "--views", str(opts.views), "--width", str(opts.width), "--height",
                         str(opts.height), "--points", str(opts.points), "--supersample", "1"),
                   check=True, capture_output=True, env=_env())
    ref, run = os.path.join(work, "reference"), os.path.join(work, "killed")
    for folder in (ref, run):
        shutil.rmtree(folder, ignore_errors=True)
    from ctgs.ops.ext import load_cpu

    load_cpu()  # the extension built before anything is timed (a build would count as the reference's start-up)
    t0 = time.monotonic()
    subprocess.run(_ctgs(*train_args(scene, ref, opts)), check=True, capture_output=True, env=_env(),
                   timeout=opts.timeout)
    ref_s = time.monotonic() - t0
    # how long a start takes before its first step, and a step: from the reference's log (wall: seconds since the
    # command started)
    with open(os.path.join(ref, "log.jsonl"), encoding="utf-8") as fh:
        walls = [(d["it"], d["wall"]) for d in map(json.loads, fh) if d.get("type") == "step"]
    wall_s = json.load(open(os.path.join(ref, "train_summary.json")))["wall_seconds"]
    start_s = ref_s - wall_s + walls[0][1]
    step_s = (walls[-1][1] - walls[0][1]) / max(walls[-1][0] - walls[0][0], 1)
    t0 = time.monotonic()
    killed = killed_run(scene, run, opts, random.Random(opts.seed), start_s, step_s)
    return {"start_s": round(start_s, 1), "step_s": round(step_s, 3), "reference_wall_s": round(ref_s, 1),
            "killed_wall_s": round(time.monotonic() - t0, 1), **killed, **compare(ref, run)}


def markdown(res: dict) -> str:
    o = res["options"]
    lines = [f"# A training under {len(res['kills'])} random kill -9s against an uninterrupted run",
             "", f"Machine: {res['machine']['cpu']} ({res['machine']['cores']} cores), {res['date']}; commit "
             f"{res['commit']}.", "", f"Command: `{res['command']}`", "",
             f"Demo scene {o['views']} views at {o['width']}x{o['height']}, `fast` preset, {o['iterations']} "
             f"iterations, seed {o['seed']}, one thread, checkpoints as "
             + (f"checkpoint_every = {o['checkpoint_every']} places them." if o["checkpoint_every"] else
                "the preset places them."),
             "", "| | uninterrupted | killed and resumed |", "| --- | --- | --- |",
             f"| wall time | {res['reference_wall_s']} s | {res['killed_wall_s']} s over {res['starts']} starts |"]
    for key in ("iterations", "final_test_psnr", "num_primitives", "num_texels"):
        lines.append(f"| {key} | {res[key][0]} | {res[key][1]} |")
    verdict = ("identical: every tensor of model.pt bit for bit, and the log's step, routine and test records"
               if res["identical"] else f"different: {res['tensor_diffs'] or 'the logs differ'}")
    lines += ["", f"Result: {verdict}.", "", "| kill | after (s) | started with | checkpoint after the kill |",
              "| --- | --- | --- | --- |"]
    for i, k in enumerate(res["kills"], 1):
        ck = "none" if k["checkpoint_it"] is None else f"iteration {k['checkpoint_it']}"
        lines.append(f"| {i} | {k['after_s']} | {'--resume' if k['resumed'] else 'a fresh start'} | {ck} |")
    return "\n".join(lines) + "\n"


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", required=True, help="scratch folder (the scene and both runs)")
    p.add_argument("--kills", type=int, default=20)
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--checkpoint-every", type=int, default=0, help="the config key checkpoint_every (paper-scale "
                   "iterations: x iterations / 30000 of this run); 0: the preset's")
    p.add_argument("--views", type=int, default=12)
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--height", type=int, default=96)
    p.add_argument("--points", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds any one uninterrupted training may take")
    p.add_argument("--name", default=None, help="record name (default from the options)")
    p.add_argument("--no-record", action="store_true")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    opts = parse(argv)
    res = run_check(opts.work, opts)
    res.update({"options": {k: v for k, v in vars(opts).items() if k not in ("work", "name", "no_record")},
                "machine": machine(), "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                "commit": record.commit(), "command": " ".join(["benchmarks/crash_consistency.py", *sys.argv[1:]])})
    if opts.no_record:
        print(markdown(res))
    else:
        name = opts.name or f"demo{opts.width}_{opts.iterations}it_{len(res['kills'])}kills_seed{opts.seed}"
        record.write_record(record.stem("crash_consistency", name), res, markdown)
    return 0 if res["identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
