"""Where the time of one training iteration goes: a phase breakdown of a window of iterations.

Usage:
  .venv/bin/python benchmarks/profile_train.py SCENE --tag demo192 [--images images_8]
      [--preset fast] [--config 2dgs] [--set KEY=VALUE ...] [--state-at 1500] [--window 240] [--threads 1]
      [--work /tmp/ctgs_prof]

The model is first trained to iteration --state-at (once per tag; the snapshot is reused, so profiles
of different commits start from the very same model), then --window iterations are trained from it
with timers around every phase, in a fresh process. Phases are timed by wrapping the functions the
trainer calls (no trainer edits), so their names follow the code:

  render_inputs   the model's activations (exp, sigmoid of the texels, texel size)
  validate        render()'s input checks
  preprocess      world -> camera space and SH -> colour (PyTorch)
  forward_cpu     the compiled forward; split by the kernel's own counters into bin (setup, bounds,
                  depth sort, tile lists), raster (blending) and reduce (error statistics)
  loss            L1 + SSIM (ssim_map below it) + regularisers, forward
  backward        loss.backward(): backward_cpu (split into setup, raster, per-primitive reduction,
                  texel-gradient reduction) and the rest of autograd (SSIM, activations, preprocess)
  nan_guard       Trainer._check_finite
  adam            SurfelAdam.step
  routines        Trainer._adapt (full/late routines, reallocations; their renders are listed below them)

To profile another commit (e.g. the one before this work), copy this script into a worktree of it and run
it there with a config that commit understands; its kernels then show as one forward_cpu / backward_cpu.

--clock cpu times everything in process CPU seconds instead of wall seconds (with one thread, robust to
other jobs on a shared machine); the result files then end in _cpu.

Timings are inclusive; a phase's children are listed under it ("a/b"). Every figure is seconds per
iteration over the window (routines too: their total over the window / window). Results go to
benchmarks/results/profile_train/profile_<tag>_<label>.{json,md}; --label names the code state (e.g. before, after).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from collections import defaultdict
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class Timers:
    """Inclusive wall time per call path ("backward/backward_cpu"), summed over calls."""

    def __init__(self, clock=time.perf_counter):
        self.clock = clock
        self.stack: list[str] = []
        self.total: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def wrap(self, owner, attr: str, name: str, generator: bool = False) -> None:
        orig = getattr(owner, attr)
        timers = self

        def wrapped(*args, **kwargs):
            timers.stack.append(name)
            path = "/".join(timers.stack)
            t0 = timers.clock()
            try:
                out = orig(*args, **kwargs)
                if generator:
                    out = iter(list(out))
                return out
            finally:
                timers.total[path] += timers.clock() - t0
                timers.calls[path] += 1
                timers.stack.pop()

        setattr(owner, attr, wrapped)

    def add(self, name: str, seconds: float) -> None:
        path = "/".join(self.stack + [name])
        self.total[path] += seconds
        self.calls[path] += 1


def install(timers: Timers, ext) -> None:
    import torch

    from ctgs.model.surfels import SurfelModel
    import ctgs.render.api as api
    import ctgs.render.rasterize as rz
    import ctgs.train.loop.trainer as trainer
    import ctgs.train.routines.passes as routines
    import ctgs.train.routines.texels as texels
    from ctgs.train.step.adam import SurfelAdam
    import ctgs.train.step.loss as loss_mod

    timers.wrap(SurfelModel, "render_inputs", "render_inputs")
    timers.wrap(api, "validate_inputs", "validate")
    timers.wrap(rz, "to_camera_space", "preprocess")
    timers.wrap(trainer, "training_loss", "loss")
    if hasattr(loss_mod, "ssim_map"):  # commits before the fused photometric loss
        timers.wrap(loss_mod, "ssim_map", "ssim_map")
    else:  # L1 + SSIM and (when the render needs one) its gradient, one compiled pass
        timers.wrap(loss_mod, "photometric_loss", "photometric")
    timers.wrap(torch.Tensor, "backward", "backward")
    timers.wrap(trainer.Trainer, "_check_finite", "nan_guard")
    timers.wrap(SurfelAdam, "step", "adam")
    timers.wrap(trainer.Trainer, "_adapt", "routines", generator=True)
    try:  # the module the routines are called from (commits before the training strategies: the trainer)
        from ctgs.train.strategies import content_aware as routine_caller
    except ImportError:
        routine_caller = trainer
    timers.wrap(routine_caller, "full_routine", "full_routine")
    timers.wrap(routine_caller, "late_routine", "late_routine")
    timers.wrap(routines, "compute_E", "compute_E")
    timers.wrap(texels, "realloc", "realloc")

    # the rasterizer's two ops (commits before the op registry: the module's functions)
    fwd, bwd = ((ext.forward_cpu, ext.backward_cpu) if hasattr(ext, "forward_cpu")
                else (torch.ops.ctgs.rasterize_forward, torch.ops.ctgs.rasterize_backward))

    # Commits before this work (e363f40) have no kernel counters: their forward/backward stay whole.
    counters = getattr(ext, "profile_counters", lambda reset: {})

    def kernel_split(prefix: str, scale: float) -> None:
        # The kernel's counters are wall-clock; with the CPU clock they are scaled by the call's CPU / wall
        # time (one thread: the share of the call during which the process was not preempted).
        for k, v in counters(True).items():
            if k.startswith(prefix):
                timers.add(k, v * scale)

    def timed(fn, name: str, prefix: str):
        def call(*args):
            counters(True)
            timers.stack.append(name)
            w0, c0 = time.perf_counter(), timers.clock()
            try:
                return fn(*args)
            finally:
                wall, spent = time.perf_counter() - w0, timers.clock() - c0
                kernel_split(prefix, spent / wall if wall > 0 else 1.0)
                timers.stack.pop()
                timers.add(name, spent)
        return call

    forward_cpu = timed(fwd, "forward_cpu", "fwd_")
    backward_cpu = timed(bwd, "backward_cpu", "bwd_")
    rz._load = lambda device: (forward_cpu, backward_cpu)


def make_snapshot(args) -> None:
    """Train to --state-at and write the checkpoint (run in its own process)."""
    from ctgs.runs import training_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    run = os.path.join(args.work, f"snap_{args.tag}")
    shutil.rmtree(run, ignore_errors=True)
    cfg = resolve_config(args.scene, run, args.config, None, [f"threads={args.threads}", *args.set], args.images,
                         False, "cpu", args.seed, preset=args.preset)
    tr = Trainer(cfg, training_scene(cfg), run)
    for _ in tr.run():
        if tr.it >= args.state_at:
            break
    tr._save_checkpoint()
    with open(os.path.join(run, "snapshot.json"), "w") as fh:  # marks the snapshot complete
        json.dump({"iteration": tr.it, "primitives": tr.model.num_primitives, "texels": tr.model.num_texels}, fh)
    print(f"snapshot at iteration {tr.it}: {tr.model.num_primitives} primitives, {tr.model.num_texels} texels")


def profile(args) -> dict:
    import torch

    from ctgs.ops.ext import load_cpu
    from ctgs.runs import training_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    snap = os.path.join(args.work, f"snap_{args.tag}")
    run = os.path.join(args.work, f"prof_{args.tag}_{args.label}")
    shutil.rmtree(run, ignore_errors=True)
    shutil.copytree(snap, run)
    cfg = resolve_config(args.scene, run, args.config, None, [f"threads={args.threads}", *args.set], args.images,
                         True, "cpu", args.seed, preset=args.preset)
    ext = load_cpu()
    tr = Trainer(cfg, training_scene(cfg), run, resume=True)
    # --clock cpu: process CPU time (user + system), robust to other jobs on a shared machine with one
    # training thread; wall (default): what a user waits, the only clock that shows thread scaling.
    timers = Timers(time.process_time if args.clock == "cpu" else time.perf_counter)
    install(timers, ext)
    start_it, start_s, cpu0 = tr.it, tr.train_seconds, time.process_time()
    n0, t0_texels = tr.model.num_primitives, tr.model.num_texels
    load0 = os.getloadavg()
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    gen = tr.run()
    for _ in gen:
        if tr.it >= start_it + args.window:
            break
    seconds = tr.train_seconds - start_s if args.clock == "wall" else time.process_time() - cpu0
    iters = tr.it - start_it
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / iters
    per_it = {k: v / iters for k, v in sorted(timers.total.items())}
    routine = per_it.get("routines", 0.0)
    return {
        "tag": args.tag, "label": args.label, "scene": os.path.abspath(args.scene), "images": args.images,
        "preset": args.preset, "config": args.config, "sets": args.set, "threads": args.threads, "clock": args.clock,
        "seed": args.seed, "state_at": start_it,
        "window": iters, "primitives_start": n0, "primitives_end": tr.model.num_primitives,
        "texels_start": t0_texels, "texels_end": tr.model.num_texels,
        "train_seconds": seconds, "it_per_s": iters / seconds, "seconds_per_it": seconds / iters,
        "routine_share": routine / (seconds / iters), "per_iteration_s": per_it,
        "calls": dict(sorted(timers.calls.items())),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "page_faults_per_it": faults,
        "loadavg_start": load0, "loadavg_end": os.getloadavg(),
        "commit": git_commit(), "machine": machine(), "torch": torch.__version__,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([os.path.relpath(sys.executable, REPO)] + sys.argv),
    }


def git_commit() -> str:
    try:
        head = subprocess.run(["git", "-C", REPO, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", REPO, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return {"host": platform.node(), "cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version()}


def write(res: dict, out_dir: str) -> None:
    base = os.path.join(out_dir, f"profile_{res['tag']}_{res['label']}{'_cpu' if res.get('clock') == 'cpu' else ''}")
    os.makedirs(out_dir, exist_ok=True)  # a profile of minutes is not lost to a missing folder
    with open(base + ".json", "w") as fh:
        json.dump(res, fh, indent=2)
    per = res["per_iteration_s"]
    total = res["seconds_per_it"]
    lines = [f"# Training iteration profile: {res['tag']} ({res['label']}, commit {res['commit']})", "",
             f"Written by benchmarks/profile_train.py on {res['date']}. Command: `{res['command']}`", "",
             f"Machine: {res['machine']['cpu']}, {res['machine']['cores']} cores ({res['machine']['host']}); "
             f"torch {res['torch']}; {res['threads']} thread(s); load average at start "
             f"{res['loadavg_start'][0]:.2f}, at end {res['loadavg_end'][0]:.2f} (a shared machine: "
             f"absolute times are inflated by other jobs, ratios side by side are the stable figure).", "",
             f"Scene {res['scene']} ({res['images']}), preset {res.get('preset')}, config {res['config']}, sets "
             f"{res.get('sets', [])}, seed {res['seed']}: iterations "
             f"{res['state_at']}..{res['state_at'] + res['window']} from a snapshot, "
             f"{res['primitives_start']} -> {res['primitives_end']} primitives, {res['texels_start']} -> "
             f"{res['texels_end']} texels. Peak RSS {res['peak_rss_mib']:.0f} MiB; "
             f"{res['page_faults_per_it']:.0f} minor page faults per iteration.", "",
             f"Clock: {res.get('clock', 'wall')} ("
             f"{'process CPU seconds: iterations per CPU second' if res.get('clock') == 'cpu' else 'wall clock'}).", "",
             f"**{res['it_per_s']:.2f} it/s** ({1000 * total:.1f} ms per iteration, routines included); "
             f"routines' share {100 * res['routine_share']:.1f}%.", "",
             "| phase (inclusive; children indented) | ms / iteration | share | calls |",
             "| --- | ---: | ---: | ---: |"]
    for path, v in per.items():
        depth = path.count("/")
        name = ("&nbsp;&nbsp;" * 2 * depth) + path.split("/")[-1]
        lines.append(f"| {name} | {1000 * v:.2f} | {100 * v / total:.1f}% | {res['calls'].get(path, 0)} |")
    top = sum(v for k, v in per.items() if "/" not in k)
    lines.append(f"| (rest: schedule, view choice, logging, Python) | {1000 * (total - top):.2f} | "
                 f"{100 * (total - top) / total:.1f}% | |")
    with open(base + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--tag", required=True, help="names the snapshot and the result files")
    ap.add_argument("--label", default="current", help="names the code state in the result files")
    ap.add_argument("--images", default="images")
    ap.add_argument("--preset", default="fast", help="ctgs train --preset")
    ap.add_argument("--config", default=None, help="ctgs train --config (an overlay on the preset)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="ctgs train --set (repeatable)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--state-at", type=int, default=1500)
    ap.add_argument("--window", type=int, default=240)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="wall-clock time, or process CPU time (load-robust with one thread)")
    ap.add_argument("--work", default="/tmp/ctgs_prof")
    ap.add_argument("--out", default=os.path.join(REPO, "benchmarks", "results", "profile_train"))
    ap.add_argument("--make-snapshot", action="store_true", help="(internal) only write the snapshot")
    ap.add_argument("--new-snapshot", action="store_true", help="retrain the snapshot even if it exists")
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    if args.make_snapshot:
        make_snapshot(args)
        return
    if args.new_snapshot or not os.path.exists(os.path.join(args.work, f"snap_{args.tag}", "snapshot.json")):
        cmd = [sys.executable, os.path.abspath(__file__), *sys.argv[1:], "--make-snapshot"]
        subprocess.run(cmd, check=True)
    write(profile(args), args.out)


if __name__ == "__main__":
    main()
