"""Where a training run's GPU memory and time go: per-iteration peak memory, what is alive at the peak, and a
profile of the textured steps (the open question of the 14.8 GB peak of `paper` on herzjesu25).

Drives the trainer the way `ctgs train` does (same config resolution, same loop: Trainer.run's events) and,
on a CUDA device:
- per iteration, the peak of torch's allocator since the previous iteration (torch.cuda.max_memory_allocated,
  reset each time) and the memory held after it, tagged with the routines that ran in it;
- from --history-after on, torch's allocator history (torch.cuda.memory._record_memory_history, Python
  frames); each time an iteration sets a new peak (5% above the last, at most --snapshots times) the history
  is replayed (peak_live_set) to name the allocation sites alive at that peak, grouped by the innermost ctgs
  frame, with bytes;
- torch.profiler over --profile-steps iterations from --profile-at: the ops and kernels by CUDA time.
On the CPU it runs the same loop without the memory figures (a dry run of the script itself).

    python benchmarks/gpu_train_probe.py SCENE --out DIR [--label NAME] [--preset paper] [--iterations N]
        [--seconds S] [--history-after IT] [--profile-at IT] [--set key=value ...]

Writes DIR/probe_NAME.json and DIR/probe_NAME.md. Nothing of the run is kept (its folder is temporary).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections import defaultdict

MB = 2**20


def _site(frames: list[dict]) -> str:
    """The innermost frame in ctgs or benchmarks code (file:line function), else the innermost frame."""
    for f in frames or []:
        name = f.get("filename", "")
        if "/ctgs/" in name or "/benchmarks/" in name:
            short = name[name.rfind("/ctgs/") + 1:] if "/ctgs/" in name else name[name.rfind("/benchmarks/") + 1:]
            return f"{short}:{f.get('line')} {f.get('name')}"
    if frames:
        f = frames[0]
        return f"{f.get('filename')}:{f.get('line')} {f.get('name')}"
    return "(no frames)"


def peak_live_set(trace: list[dict], top: int = 15) -> dict:
    """Replay one device's allocator trace (torch.cuda.memory._snapshot()["device_traces"][i]): the point where
    the bytes allocated *within the trace* peak, and what was alive there, grouped by allocation site.

    Allocations made before the trace began are not in it (their frees are ignored), so `peak_bytes` is the
    rise above the memory held when the trace started, and `held_before_mb` is not known from here.
    Returns {"peak_rise_mb", "peak_index", "events", "sites": [{"site", "mb", "count"}]}.
    """
    live: dict[int, tuple[int, str]] = {}
    cur = best = 0
    best_i = -1
    best_live: dict[int, tuple[int, str]] = {}
    for i, ev in enumerate(trace):
        action, addr, size = ev.get("action"), ev.get("addr"), int(ev.get("size", 0))
        if action == "alloc":
            live[addr] = (size, _site(ev.get("frames", [])))
            cur += size
            if cur > best:
                best, best_i = cur, i
                best_live = dict(live)
        elif action == "free_completed" and addr in live:
            cur -= live.pop(addr)[0]
    sites: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for size, site in best_live.values():
        sites[site][0] += size
        sites[site][1] += 1
    ranked = sorted(sites.items(), key=lambda kv: -kv[1][0])[:top]
    return {"peak_rise_mb": round(best / MB, 1), "peak_index": best_i, "events": len(trace),
            "sites": [{"site": s, "mb": round(b / MB, 1), "count": c} for s, (b, c) in ranked]}


def _profile_table(prof, rows: int = 30) -> str:
    try:
        return prof.key_averages().table(sort_by="cuda_time_total", row_limit=rows, max_name_column_width=60)
    except Exception as e:  # noqa: BLE001 - a profiler table is a report, never a reason to fail the probe
        return f"(profile table failed: {e})"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--out", required=True)
    ap.add_argument("--label", default="run")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--config", default=None)
    ap.add_argument("--iterations", type=int, default=None, help="the run's planned length (schedules follow it)")
    ap.add_argument("--stop-at", type=int, default=None, help="stop after this iteration (default: the end)")
    ap.add_argument("--seconds", type=float, default=None, help="stop after this much wall time")
    ap.add_argument("--images", default=None)
    ap.add_argument("--backend", default=None)
    ap.add_argument("--history-after", type=int, default=None,
                    help="record the allocator history from this iteration (default: the texture start - 1)")
    ap.add_argument("--history-entries", type=int, default=400000)
    ap.add_argument("--snapshots", type=int, default=4)
    ap.add_argument("--profile-at", type=int, default=None)
    ap.add_argument("--profile-steps", type=int, default=20)
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--ab", action="append", default=[], metavar="KEY=VALUE",
                    help="side by side in one run: from the texture start + 100 on, blocks of --ab-block iterations "
                         "rotate between the plain run and each of these environment settings (read by the CUDA "
                         "backend at every launch), and the phase table "
                         "splits the textured steps, and those with a routine, by variant (routines alternate between two "
                         "variants when their spacing / --ab-block is odd: 250 / 50 at the paper's scale)")
    ap.add_argument("--ab-block", type=int, default=50)
    ap.add_argument("--no-history", action="store_true", help="no allocator history (timing runs)")
    args = ap.parse_args(argv)

    import torch

    from ctgs.runs import training_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.config import schedule
    from ctgs.train.events import Eval, Step
    from ctgs.train.loop.trainer import Trainer

    os.makedirs(args.out, exist_ok=True)
    env_at_start = {k: v for k, v in os.environ.items()  # (--ab changes it later)
                    if k.startswith("CTGS_CUDA")}
    run_dir = tempfile.mkdtemp(prefix="ctgs_probe_")
    cfg = resolve_config(args.scene, run_dir, args.config, args.iterations, args.sets, args.images, False,
                         args.backend, None, args.preset)
    scene = training_scene(cfg)
    trainer = Trainer(cfg, scene, run_dir)
    dev = trainer.device
    cuda = dev.type == "cuda"
    ts = schedule.texture_start(cfg) if cfg.method == "content_aware" else None
    hist_after = args.history_after if args.history_after is not None else max(1, (ts or 1) - 1)
    if args.no_history:
        hist_after = 1 << 62
    variants = [("plain", None)] + [(kv, kv.split("=", 1)) for kv in args.ab]
    ab_from = (ts or 0) + 100

    def set_variant(it: int) -> str:
        if len(variants) == 1 or it < ab_from:
            return "plain"
        name, kv = variants[((it - ab_from) // args.ab_block) % len(variants)]
        for _, other in variants[1:]:
            os.environ.pop(other[0], None)
        if kv is not None:
            os.environ[kv[0]] = kv[1]
        return name
    variant = set_variant(1)
    rows: list[dict] = []
    routines: dict[int, list[str]] = defaultdict(list)
    evals: list[dict] = []
    snapshots: list[dict] = []
    recording = False
    prof = None
    prof_window = None
    best = 0.0
    t_start = last = time.perf_counter()
    if cuda:
        torch.cuda.reset_peak_memory_stats(dev)
    for ev in trainer.run():
        if isinstance(ev, Step):
            now = time.perf_counter()
            row = {"it": ev.it, "wall_s": round(now - last, 5), "n": ev.num_primitives, "texels": ev.num_texels,
                   "variant": variant}
            variant = set_variant(ev.it + 1)  # for the next iteration (its launches happen before its Step)
            last = now
            if cuda:
                peak = torch.cuda.max_memory_allocated(dev) / MB
                row.update(peak_mb=round(peak, 1), held_mb=round(torch.cuda.memory_allocated(dev) / MB, 1))
                torch.cuda.reset_peak_memory_stats(dev)
                if recording and peak > 1.05 * best and len(snapshots) < args.snapshots:
                    snap = torch.cuda.memory._snapshot()
                    traces = snap.get("device_traces") or [[]]
                    idx = dev.index if dev.index is not None else torch.cuda.current_device()
                    summary = peak_live_set(traces[idx] if idx < len(traces) else traces[0])
                    summary.update(it=ev.it, peak_mb=round(peak, 1), held_after_mb=row["held_mb"])
                    snapshots.append(summary)
                    # Start afresh so that the next replay sees the next peak's own allocations.
                    torch.cuda.memory._record_memory_history(enabled=None)
                    torch.cuda.memory._record_memory_history(max_entries=args.history_entries, stacks="python")
                best = max(best, peak)
                if not recording and ev.it >= hist_after:
                    torch.cuda.memory._record_memory_history(max_entries=args.history_entries, stacks="python")
                    recording = True
            rows.append(row)
            if args.profile_at is not None and ev.it == args.profile_at - 1 and prof is None:
                acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
                prof = torch.profiler.profile(activities=acts)
                prof.__enter__()
                prof_window = [ev.it + 1, None]
            elif prof is not None and prof_window[1] is None and ev.it >= prof_window[0] + args.profile_steps - 1:
                prof.__exit__(None, None, None)
                prof_window[1] = ev.it
            if (args.stop_at and ev.it >= args.stop_at) or (args.seconds and now - t_start >= args.seconds):
                break
        elif isinstance(ev, Eval):
            evals.append({"it": ev.it, "psnr": ev.test_psnr, "ssim": ev.test_ssim})
        elif hasattr(ev, "kind"):
            routines[ev.it].append(ev.kind)
    if prof is not None and prof_window[1] is None:
        prof.__exit__(None, None, None)
        prof_window[1] = rows[-1]["it"] if rows else None
    if recording:
        torch.cuda.memory._record_memory_history(enabled=None)
    for r in rows:
        r["routines"] = routines.get(r["it"], [])

    def phase_stats(sel):
        sel = list(sel)
        if not sel:
            return None
        ms = sorted(r["wall_s"] for r in sel)[len(sel) // 2]
        out = {"iterations": len(sel), "ms_per_it_median": round(1000 * ms, 2)}
        if cuda:
            out["peak_mb_max"] = max(r["peak_mb"] for r in sel)
            out["peak_mb_median"] = sorted(r["peak_mb"] for r in sel)[len(sel) // 2]
            out["held_mb_max"] = max(r["held_mb"] for r in sel)
        return out

    before = [r for r in rows if ts is None or r["it"] < ts]
    after = [r for r in rows if ts is not None and r["it"] > ts]
    plain = [r for r in after if not r["routines"]]
    with_routine = [r for r in after if r["routines"]]
    by_variant = {name: phase_stats([r for r in plain if r["variant"] == name and r["it"] >= ab_from])
                  for name, _ in variants} \
        if len(variants) > 1 else {}
    routine_by_variant = {name: phase_stats([r for r in with_routine if r["variant"] == name and r["it"] >= ab_from])
                          for name, _ in variants} if len(variants) > 1 else {}
    result = {
        "label": args.label, "device": str(dev), "gpu": torch.cuda.get_device_name(dev) if cuda else None,
        "torch": torch.__version__, "preset": args.preset, "method": cfg.method, "iterations_planned": cfg.iterations,
        "iterations_run": rows[-1]["it"] if rows else 0, "texture_start": ts, "image_pixels": trainer.pixels,
        "env": env_at_start, "ab_variants": [name for name, _ in variants],
        "final": {"n": rows[-1]["n"], "texels": rows[-1]["texels"]} if rows else {},
        "phases": {"before_texture_start": phase_stats(before), "textured_steps": phase_stats(plain),
                   "textured_with_routine": phase_stats(with_routine),
                   **{f"textured_steps [{k}]": v for k, v in by_variant.items()},
                   **{f"textured_with_routine [{k}]": v for k, v in routine_by_variant.items()}},
        "peak_iterations": sorted(rows, key=lambda r: -r.get("peak_mb", 0))[:8] if cuda else [],
        "snapshots": snapshots, "evals": evals, "profile_window": prof_window,
        "wall_s": round(time.perf_counter() - t_start, 1), "rows": rows,
    }
    base = os.path.join(args.out, f"probe_{args.label}")
    with open(base + ".json", "w") as f:
        json.dump(result, f, indent=1)
    lines = [f"# Training probe `{args.label}`: {result['gpu'] or result['device']}, preset {args.preset}", "",
             f"{result['iterations_run']} of {cfg.iterations} planned iterations, {trainer.pixels} pixels per image, "
             f"texture start {ts}; final {result['final']}; env {result['env']}", "",
             "| phase | iterations | ms / it (median) | peak MB (max) | peak MB (median) | held MB (max) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, st in result["phases"].items():
        if st:
            lines.append(f"| {name} | {st['iterations']} | {st['ms_per_it_median']} | {st.get('peak_mb_max', '-')} | "
                         f"{st.get('peak_mb_median', '-')} | {st.get('held_mb_max', '-')} |")
    if cuda:
        lines += ["", "Iterations with the highest peaks: " + ", ".join(
            f"{r['it']} ({r['peak_mb']:.0f} MB{', ' + '+'.join(r['routines']) if r['routines'] else ''})"
            for r in result["peak_iterations"])]
    for s in snapshots:
        lines += ["", f"## Alive at the peak of iteration {s['it']} ({s['peak_mb']:.0f} MB; {s['peak_rise_mb']:.0f} MB "
                  f"allocated within the recorded history, {s['events']} events)", "", "| MB | count | site |",
                  "| --- | --- | --- |"]
        lines += [f"| {x['mb']:.1f} | {x['count']} | `{x['site']}` |" for x in s["sites"]]
    if prof is not None:
        lines += ["", f"## Profile of iterations {prof_window[0]}-{prof_window[1]}", "", "```", _profile_table(prof),
                  "```"]
    with open(base + ".md", "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines[:12 + 2 * len(snapshots)]))
    return result


if __name__ == "__main__":
    main()
