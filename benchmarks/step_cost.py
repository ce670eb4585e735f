"""What textures cost a CPU training step, and what a full routine costs in steps: side by side in one process.

Usage:
  .venv/bin/python benchmarks/step_cost.py SCENE --tag bonsai200_fast --images images_4 [--preset fast]
      [--state-at 1500] [--reps 30] [--threads 1] [--work /tmp/ctgs_prof]

The model is trained to --state-at once per tag (the snapshot of benchmarks/profile_train.py, shared with it), then,
in a fresh process and on that very model, three things are timed in process CPU seconds (one thread: robust to other
jobs on a shared machine), interleaved so that a change of the machine's speed reaches all of them alike:
  textured    a training step as the loop takes it (render, loss with its regularisers, backward, Adam, NaN guard)
  untextured  the same step with the textures switched off (the model's texture mode "none": the render reads no
              texel, the loss has no texel term, Adam has no texel gradient): the same primitives and pixels
  routine     one full routine (E rendered over the preset's error views, or with error_from_steps summed by the
              textured steps before it; splits, texel rescaling, prune, reallocation) on a copy of the model and
              optimiser
Each step uses the next training view of a fixed list, the same list for both kinds. Reported: the medians, the
ratio textured / untextured (goal: at most 1.25) and routine / textured step (goal: at most 10), and the renderer's own
phase counters (binning, forward and backward raster, reductions) for both kinds of step.
Records: benchmarks/results/step_cost/<tag>_<commit>.{json,md}.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402
from profile_train import machine  # noqa: E402


def measure(args) -> dict:
    import shutil

    import torch

    from ctgs.runs import training_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.config import schedule
    from ctgs.train.loop.trainer import Trainer
    from ctgs.train.step.adam import ALL_PARAMS
    from ctgs.train.step.loss import training_loss

    snap = os.path.join(args.work, f"snap_{args.tag}")
    run = os.path.join(args.work, f"cost_{args.tag}")
    shutil.rmtree(run, ignore_errors=True)
    shutil.copytree(snap, run)
    cfg = resolve_config(args.scene, run, args.config, None, [f"threads={args.threads}", *args.set], args.images,
                         True, "cpu", args.seed, preset=args.preset)
    tr = Trainer(cfg, training_scene(cfg), run, resume=True)
    it = tr.it
    model, opt = tr.model, tr.opt
    lrs = schedule.learning_rates(tr.cfg, it, tr.extent, model.sh.shape[1], tr.device)
    views = tr.train_views[: max(args.reps, 1)]
    mode = model.texture_mode

    from ctgs.ops.ext import load_cpu

    # The kernel's own counters (wall seconds per phase; one thread, so the raster loops' time), per step kind.
    counters = load_cpu().profile_counters
    phases = {True: {}, False: {}}

    def step(view, textured: bool) -> float:
        model.texture_mode = mode if textured else "none"
        counters(True)
        t0 = time.process_time()
        for name in ALL_PARAMS:
            getattr(model, name).grad = None
        inputs = model.render_inputs()
        # error_from_steps: the textured step sums E in its backward, as the loop's steps do
        stats = tr.strategy.step_stats(tr.state) if textured else None
        rgb, rasterized = tr.training_render(inputs, view, None, stats)
        terms = training_loss(rgb, view.image_t, model, view.camera, tr.cfg, rasterized=rasterized,
                              textures=inputs.textures, want_error=stats is not None)
        if stats is not None:
            stats.error_image = terms.error_image
        terms.total.backward()
        if textured:
            tr.strategy.post_backward(tr.state, it, view)
        opt.step(model, lrs)
        tr._check_finite(None)
        seconds = time.process_time() - t0
        for name, value in counters(True).items():
            phases[textured].setdefault(name, []).append(value)
        model.texture_mode = mode
        return seconds

    def routine() -> float:
        """One full routine on a copy of the model and optimiser (with E from the steps so far, if the run sums it)."""
        tr.state.model, tr.state.opt = copy.deepcopy(model), copy.deepcopy(opt)
        errors = copy.deepcopy(getattr(tr.strategy, "errors", None))
        try:
            t0 = time.process_time()
            stats = tr.strategy.full_routine(tr.state, it)
            return time.process_time() - t0, stats.get("E_steps", 0)
        finally:
            tr.state.model, tr.state.opt = model, opt
            if errors is not None:
                tr.strategy.errors = errors

    n0, t0_texels = model.num_primitives, model.num_texels
    for v in views[:2]:  # warm-up: first touches of the buffers
        step(v, True)
        step(v, False)
    phases[True].clear()
    phases[False].clear()
    textured, untextured, routines = [], [], []
    for k, v in enumerate(views):
        textured.append(step(v, True))
        untextured.append(step(v, False))
        if (k + 1) % max(1, len(views) // args.routines) == 0 and len(routines) < args.routines:
            routines.append(routine())
    e_steps = [e for _, e in routines]
    routines = [r for r, _ in routines]
    tex, plain, rout = (statistics.median(x) for x in (textured, untextured, routines))
    return {"tag": args.tag, "scene": os.path.abspath(args.scene), "images": args.images, "preset": args.preset,
            "sets": args.set, "threads": args.threads, "state_at": it, "primitives": n0, "texels": t0_texels,
            "pixels": tr.pixels, "error_views": tr.cfg.error_views, "reps": len(views),
            "textured_s": tex, "untextured_s": plain, "routine_s": rout, "textured_over_untextured": tex / plain,
            "routine_over_textured_step": rout / tex, "textured_all": textured, "untextured_all": untextured,
            "routine_all": routines, "routine_E_steps": e_steps, "error_from_steps": tr.cfg.error_from_steps,
            "kernel_phases_ms": {kind: {k: 1e3 * statistics.median(v) for k, v in sorted(phases[flag].items())}
                                 for kind, flag in (("textured", True), ("untextured", False))},
            "commit": record.commit(), "machine": machine(), "torch": torch.__version__,
            "loadavg": os.getloadavg(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": " ".join([os.path.relpath(sys.executable, record.ROOT)] + sys.argv)}


def markdown(r: dict) -> str:
    return "\n".join([
        f"# Step cost: {r['tag']} (commit {r['commit']})", "",
        f"Written by benchmarks/step_cost.py on {r['date']}. Command: `{r['command']}`", "",
        f"Machine: {r['machine']['cpu']}, {r['machine']['cores']} cores; torch {r['torch']}; {r['threads']} thread(s); "
        f"process CPU seconds (robust to other jobs); load average at the end {r['loadavg'][0]:.2f}.", "",
        f"Scene {r['scene']} ({r['images']}, {r['pixels'] / 1e3:.1f}k pixels per view), preset {r['preset']}, sets "
        f"{r['sets']}: the model at iteration {r['state_at']}, {r['primitives']} primitives, {r['texels']} texels; "
        f"{r['reps']} steps of each kind interleaved, {len(r['routine_all'])} routines ("
        + (f"E from the steps before each: {r['routine_E_steps']}" if r.get("error_from_steps")
           else f"E rendered over {r['error_views']} views") + ").", "",
        "| what | median CPU s | ratio | goal |", "| --- | ---: | ---: | --- |",
        f"| untextured step (same primitives, pixels) | {r['untextured_s']:.4f} | 1 | |",
        f"| textured step | {r['textured_s']:.4f} | {r['textured_over_untextured']:.2f}x untextured | <= 1.25x |",
        f"| full routine | {r['routine_s']:.3f} | {r['routine_over_textured_step']:.1f} textured steps | <= 10 |",
        "", *phase_table(r.get("kernel_phases_ms", {}))])


def phase_table(phases: dict) -> list[str]:
    """The kernel counters' medians, textured against untextured: where a textured step's extra time goes."""
    tex, plain = phases.get("textured", {}), phases.get("untextured", {})
    names = [k for k in tex if tex[k] > 0.05 or plain.get(k, 0) > 0.05]
    if not names:
        return []
    return ["Inside the renderer (its counters, median wall ms per step, one thread):", "",
            "| phase | textured | untextured | ratio |", "| --- | ---: | ---: | ---: |",
            *[f"| {k} | {tex[k]:.1f} | {plain.get(k, 0):.1f} | "
              f"{tex[k] / plain[k] if plain.get(k) else float('nan'):.2f}x |" for k in names], ""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--tag", required=True, help="names the snapshot (shared with profile_train.py) and the record")
    ap.add_argument("--images", default="images")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--state-at", type=int, default=1500)
    ap.add_argument("--reps", type=int, default=30, help="steps of each kind")
    ap.add_argument("--routines", type=int, default=3, help="full routines timed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--work", default="/tmp/ctgs_prof")
    ap.add_argument("--name", default=None, help="record name (default: the tag)")
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    if not os.path.exists(os.path.join(args.work, f"snap_{args.tag}", "snapshot.json")):
        here = os.path.dirname(os.path.abspath(__file__))
        cmd = [sys.executable, os.path.join(here, "profile_train.py"), args.scene, "--tag", args.tag, "--images",
               args.images, "--preset", args.preset, "--state-at", str(args.state_at), "--threads", str(args.threads),
               "--seed", str(args.seed), "--work", args.work, "--make-snapshot",
               *([] if args.config is None else ["--config", args.config]), *[x for s in args.set for x in ("--set", s)]]
        subprocess.run(cmd, check=True)
    result = measure(args)
    record.write_record(record.stem("step_cost", args.name or args.tag), result, markdown)


if __name__ == "__main__":
    main()
