"""Training speed side by side: two commits, same scene, seed and config, run at the same time.

Usage:
  .venv/bin/python benchmarks/bench_train_speed.py --scene DIR [--images images_8] [--tag NAME]
      [--base e363f40] [--head HEAD] [--iterations 3000] [--seeds 0 1] [--work /tmp/ctgs_speed]
      [--set KEY=VALUE ...] [--serial]

For each commit it makes a detached git worktree (git worktree add --detach) under --work, builds that
worktree's CPU extension into the worktree's own build/ folder, and trains through the command line
(`python -m ctgs train SCENE -o RUN --config CFG --iterations N --set threads=1 --set seed=S -q`, with
the worktree first on PYTHONPATH and OMP_NUM_THREADS=1), so nothing here depends on internal APIs. The
two sides of one (scene, seed) pair run at the same time, one process each (two cores), so load from
other jobs on a shared machine hits both alike; --serial alternates them instead (base, head, base, ...).

Config, default: configs/demo.toml of the BASE commit (its `base` chain resolved), written to one flat
file with only the keys both commits' TrainConfig know, plus --set overrides. With --iterations below
the config's, schedule_scale is multiplied by iterations / config iterations, so every routine (texture
start, full routines, late downscales, reallocation) keeps its place in the run.

Config with --preset NAME (commits that have configs/NAME.toml and scene-relative rules, ctgs/train/
rules.py, e.g. `fast`): the HEAD side trains with the preset (plus --set), its iteration counts at the
schedule of the preset's full run (schedule_scale = preset iterations / 30000) unless --set
schedule_scale=... says otherwise, so --iterations N trains the first N iterations of that run. The BASE
side, which predates presets and rules, gets the same settings resolved by the HEAD's code for the
scene's image size (rules.resolve: lambda_texture, max_texture_res, max_primitives; init_point_cap ->
max_init_points; texture_reg_pixels = 0 since lambda_texture is already resolved), restricted to the keys
the base knows, with the same schedule_scale. A base that has the preset and the rules itself (e.g. main
after presets) trains with the same config file as the head.

Measured per side: it/s = iterations / train_seconds (train_summary.json: the training loop including
routines, excluding evaluation and checkpoints), final test PSNR, peak RSS of the training process
(os.wait4), and the share of routines in train_seconds estimated from log.jsonl (the step records'
cumulative seconds around each routine, minus the typical plain-iteration time). Results:
benchmarks/results/bench_train_speed/train_speed_<tag>.{json,md} with the machine, the load average and the command.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import time
import tomllib
from datetime import datetime, timezone

import tomli_w

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def git(*args: str, cwd: str = REPO) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


def worktree(commit: str, path: str) -> str:
    """A detached worktree of `commit` at `path` (reused if it is already there at that commit)."""
    sha = git("rev-parse", commit)
    if os.path.isdir(path):
        try:
            if git("rev-parse", "HEAD", cwd=path) == sha:
                return sha
        except subprocess.CalledProcessError:
            pass
        subprocess.run(["git", "worktree", "remove", "--force", path], cwd=REPO, check=False)
        shutil.rmtree(path, ignore_errors=True)
    subprocess.run(["git", "worktree", "add", "--detach", path, sha], cwd=REPO, check=True, capture_output=True)
    return sha


def side_env(tree: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = tree + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["OMP_NUM_THREADS"] = "1"
    env.pop("TORCH_EXTENSIONS_DIR", None)  # each worktree builds into its own build/ folder
    return env


def build(tree: str) -> None:
    code = ("from ctgs.ops.ext import load_cpu; import ctgs, sys; m = load_cpu(); "
            "assert ctgs.__file__.startswith(sys.argv[1]), ctgs.__file__; print(m.__file__)")
    r = subprocess.run([sys.executable, "-c", code, tree], cwd=tree, env=side_env(tree), capture_output=True,
                       text=True)
    if r.returncode != 0:
        raise SystemExit(f"building the extension in {tree} failed:\n{r.stderr[-3000:]}")
    print(f"built {r.stdout.strip()}", flush=True)


def config_keys(tree: str) -> set[str]:
    text = open(os.path.join(tree, "ctgs", "train", "config.py")).read()
    return set(re.findall(r"^    (\w+): [\w\[\], |]+ = _f\(", text, flags=re.M))


def resolved_toml(path: str) -> dict:
    chain = []
    while path:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
        chain.append(data)
        base = data.pop("base", None)
        path = os.path.join(os.path.dirname(path), base) if base else None
    out: dict = {}
    for data in reversed(chain):
        out.update(data)
    return out


def apply_sets(cfg: dict, sets: list[str]) -> None:
    """`key=value` items into cfg: TOML literals, else the text as a string."""
    for item in sets:
        k, v = item.split("=", 1)
        try:
            cfg[k] = tomllib.loads(f"x = {v}")["x"]
        except tomllib.TOMLDecodeError:
            cfg[k] = v


def write_config(base_tree: str, head_tree: str, iterations: int, sets: list[str], path: str) -> dict:
    cfg = resolved_toml(os.path.join(base_tree, "configs", "demo.toml"))
    keys = config_keys(base_tree) & config_keys(head_tree)
    cfg = {k: v for k, v in cfg.items() if k in keys}
    apply_sets(cfg, sets)
    full = int(cfg["iterations"])
    if iterations != full:
        cfg["schedule_scale"] = float(cfg["schedule_scale"]) * iterations / full
        cfg["iterations"] = iterations
    cfg["threads"] = 1
    with open(path, "wb") as fh:
        tomli_w.dump(cfg, fh)
    return cfg


def image_pixels(scene: str, images: str | None) -> float:
    """H*W of the scene's first training image (the scenes here hold one image size)."""
    import cv2

    folder = os.path.join(scene, images or "images")
    name = sorted(f for f in os.listdir(folder) if not f.startswith("."))[0]
    img = cv2.imread(os.path.join(folder, name), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"cannot read {os.path.join(folder, name)}")
    return float(img.shape[0] * img.shape[1])


_RESOLVE = """
import json, sys
from dataclasses import asdict
from ctgs.train.config import TrainConfig
from ctgs.train.config import rules
d, pixels = json.loads(sys.argv[1]), float(sys.argv[2])
cfg = TrainConfig(**d)
out = asdict(rules.resolve(cfg, pixels))
out["max_init_points"] = rules.init_point_cap(cfg, pixels)
print(json.dumps(out))
"""


def write_preset_configs(base_tree: str, head_tree: str, preset: str, iterations: int, sets: list[str],
                         pixels: float, head_path: str, base_path: str) -> tuple[dict, dict]:
    """Head: configs/<preset>.toml of the head + sets; base: the same resolved by the head's rules."""
    cfg = resolved_toml(os.path.join(head_tree, "configs", f"{preset}.toml"))
    full = int(cfg.get("iterations", 30000))
    cfg["schedule_scale"] = full / 30000.0
    apply_sets(cfg, sets)
    cfg["iterations"] = iterations
    cfg["threads"] = 1
    r = subprocess.run([sys.executable, "-c", _RESOLVE, json.dumps(cfg), str(pixels)], cwd=head_tree,
                       env=side_env(head_tree), capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"resolving the preset in {head_tree} failed:\n{r.stderr[-3000:]}")
    resolved = json.loads(r.stdout)
    keys = config_keys(base_tree)
    # Not settings of the method: where the scene is and what runs it come from the command line.
    run_keys = {"scene_dir", "images", "backend", "device", "seed", "threads", "debug_nan_at"}
    if os.path.exists(os.path.join(base_tree, "configs", f"{preset}.toml")) and "scale_rules" in keys:
        base_cfg = {k: v for k, v in cfg.items() if k in keys}  # a base with presets and rules: the same file
    else:
        base_cfg = {k: v for k, v in resolved.items() if k in keys and k not in run_keys and v is not None}
        base_cfg["threads"] = 1
        if "texture_reg_pixels" in keys:
            base_cfg["texture_reg_pixels"] = 0.0
    for path, c in ((head_path, cfg), (base_path, base_cfg)):
        with open(path, "wb") as fh:
            tomli_w.dump(c, fh)
    # Settings of the head the base cannot take: the base runs its built-in behaviour there, so the two
    # sides may not do the same work (neutralise them with --set KEY=<the base's behaviour>).
    head_only = {k: v for k, v in resolved.items() if k not in keys and k not in run_keys and v is not None}
    return cfg, base_cfg, head_only


def train_cmd(scene: str, run: str, cfg_path: str, iterations: int, seed: int, images: str | None) -> list[str]:
    cmd = [sys.executable, "-m", "ctgs", "train", scene, "-o", run, "--config", cfg_path, "--iterations",
           str(iterations), "--set", "threads=1", "--set", f"seed={seed}", "-q"]
    if images:
        cmd += ["--images", images]
    return cmd


def wait_rss(proc: subprocess.Popen) -> tuple[int, float, float]:
    """Wait for proc; (exit status, peak RSS in MiB, CPU seconds user + system) from the kernel's
    accounting of that process."""
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, ru.ru_maxrss / 1024.0, ru.ru_utime + ru.ru_stime


def routine_share(run: str) -> float | None:
    """Share of train_seconds spent in routines, from log.jsonl: the step records carry cumulative seconds
    every log_every iterations; an interval holding routines costs more than its plain neighbours."""
    path = os.path.join(run, "log.jsonl")
    steps, routine_its = [], set()
    with open(path) as fh:
        for line in fh:
            r = json.loads(line)
            if r.get("type") == "step":
                steps.append((r["it"], r["seconds"]))
            elif r.get("type") == "routine":
                routine_its.add(r["it"])
    if len(steps) < 3:
        return None
    # Reallocations log nothing: they happen every realloc_every; count them through the config.
    cfg = tomllib.load(open(os.path.join(run, "config.toml"), "rb"))
    every = max(1, int(round(cfg["realloc_every"] * cfg["schedule_scale"])))
    start = max(1, int(round(cfg["texture_start"] * cfg["schedule_scale"])))
    if cfg["method"] == "content_aware":
        routine_its |= {it for it in range(start + 1, cfg["iterations"] + 1) if it % every == 0}
    intervals = []  # (per-iteration seconds, holds a routine)
    for (i0, s0), (i1, s1) in zip(steps, steps[1:]):
        has = any(i0 < it <= i1 for it in routine_its)
        intervals.append(((s1 - s0) / (i1 - i0), has, i1 - i0, s1 - s0))
    total = steps[-1][1] - steps[0][1]
    extra = 0.0
    for k, (per, has, n, sec) in enumerate(intervals):
        if not has:
            continue
        # The plain cost of this interval: median of the nearest plain intervals on both sides.
        near = [p for p, h, _, _ in intervals[max(0, k - 3): k + 4] if not h]
        plain = statistics.median(near) if near else per
        extra += max(0.0, sec - plain * n)
    return extra / total if total > 0 else None


def run_pair(sides: dict, scene: str, images: str | None, cfg_paths: dict, iterations: int, seed: int,
             work: str, tag: str, serial: bool) -> dict:
    out = {}
    procs = {}
    order = list(sides) if seed % 2 == 0 else list(reversed(list(sides)))
    for name in order:
        tree = sides[name]
        run = os.path.join(work, "runs", f"{tag}_{name}_seed{seed}")
        shutil.rmtree(run, ignore_errors=True)
        cmd = train_cmd(scene, run, cfg_paths[name], iterations, seed, images)
        t0 = time.time()
        p = subprocess.Popen(cmd, cwd=tree, env=side_env(tree))
        procs[name] = (p, run, t0, cmd)
        if serial:
            out[name] = finish(procs.pop(name))
    for name, item in procs.items():
        out[name] = finish(item)
    return out


def finish(item) -> dict:
    p, run, t0, cmd = item
    code, rss, cpu = wait_rss(p)
    wall = time.time() - t0
    if code != 0:
        raise SystemExit(f"training failed ({code}): {' '.join(cmd)}")
    with open(os.path.join(run, "train_summary.json")) as fh:
        s = json.load(fh)
    return {"run": run, "iterations": s["iterations"], "train_seconds": s["train_seconds"],
            "it_per_s": s["iterations"] / s["train_seconds"], "test_psnr": s["final_test_psnr"],
            "test_ssim": s["final_test_ssim"], "primitives": s["num_primitives"], "texels": s["num_texels"],
            "peak_rss_mib": rss, "wall_seconds": wall, "cpu_seconds": cpu, "routine_share": routine_share(run),
            "loadavg_end": os.getloadavg()}


def machine() -> dict:
    cpu = ""
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
    except OSError:
        pass
    import torch

    return {"host": platform.node(), "cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "torch": torch.__version__}


def write(res: dict, path: str) -> None:
    with open(path + ".json", "w") as fh:
        json.dump(res, fh, indent=2)
    m = res["machine"]
    lines = [f"# Training speed side by side: {res['tag']}", "",
             f"Written by benchmarks/bench_train_speed.py on {res['date']}. Command: `{res['command']}`", "",
             f"Machine: {m['cpu']}, {m['cores']} cores ({m['host']}), torch {m['torch']}; load average "
             f"{res['loadavg_start'][0]:.2f} at start, {res['loadavg_end'][0]:.2f} at the end (a shared "
             f"machine: absolute it/s move with the load; the two sides ran "
             f"{'one after the other' if res['serial'] else 'at the same time, one core each'}).", "",
             f"Scene {res['scene']} ({res['images'] or 'images'}); config {res['config_source']}"
             f"{'' if 'preset' in res['config_source'] else ' resolved at the base commit, keys both commits know'}"
             f", {res['iterations']} iterations, schedule_scale "
             f"{res['config']['schedule_scale']:.4g}; 1 thread per training. base = {res['base']}, "
             f"head = {res['head']}.", "",
             *([f"Head settings the base does not know (it runs its built-in behaviour there; compare the "
                f"primitives and texels columns): {', '.join(f'{k}={v}' for k, v in res['head_only_settings'].items())}.",
                ""] if res.get("head_only_settings") else []),
             "| seed | side | it/s | train s | process CPU s | test PSNR | primitives | texels | peak RSS MiB | "
             "routines' share |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for seed, pair in res["pairs"].items():
        for side in ("base", "head"):
            r = pair[side]
            share = f"{100 * r['routine_share']:.1f}%" if r["routine_share"] is not None else "-"
            cpu = f"{r['cpu_seconds']:.0f}" if "cpu_seconds" in r else "-"
            lines.append(f"| {seed} | {side} | {r['it_per_s']:.3f} | {r['train_seconds']:.0f} | {cpu} | "
                         f"{r['test_psnr']:.2f} | "
                         f"{r['primitives']} | {r['texels']} | {r['peak_rss_mib']:.0f} | {share} |")
        cpu_r = f"base / head {pair['cpu_ratio']:.2f}x" if "cpu_ratio" in pair else ""
        lines.append(f"| {seed} | **head / base** | **{pair['ratio']:.2f}x** | | {cpu_r} | "
                     f"{pair['head']['test_psnr'] - pair['base']['test_psnr']:+.2f} dB | | | | |")
    lines += ["", f"Mean it/s ratio head / base: **{res['mean_ratio']:.2f}x**."]
    cpu_rs = [p["cpu_ratio"] for p in res["pairs"].values() if "cpu_ratio" in p]
    if cpu_rs:
        lines.append(f"Mean process CPU-seconds ratio base / head: {statistics.mean(cpu_rs):.2f}x (whole process: "
                     f"start-up and final evaluation included).")
    if len(res["pairs"]) > 1:
        for side in ("base", "head"):
            ps = [p[side]["test_psnr"] for p in res["pairs"].values()]
            lines.append(f"Test PSNR {side}: mean {statistics.mean(ps):.2f} dB, seeds spread "
                         f"{max(ps) - min(ps):.2f} dB.")
    with open(path + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--images", default=None)
    ap.add_argument("--tag", default=None)
    ap.add_argument("--base", default="e363f40")
    ap.add_argument("--head", default="HEAD")
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--preset", default=None, help="head trains with configs/PRESET.toml (see Config above)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--work", default="/tmp/ctgs_speed")
    ap.add_argument("--serial", action="store_true", help="alternate the sides instead of running them together")
    ap.add_argument("--out", default=os.path.join(REPO, "benchmarks", "results", "bench_train_speed"))
    args = ap.parse_args()
    tag = args.tag or os.path.basename(os.path.normpath(args.scene))
    os.makedirs(args.work, exist_ok=True)
    load0 = os.getloadavg()
    sides = {"base": os.path.join(args.work, "base"), "head": os.path.join(args.work, "head")}
    shas = {name: worktree(getattr(args, name), path) for name, path in sides.items()}
    for tree in sides.values():
        build(tree)
    scene = os.path.abspath(args.scene)
    if args.preset:
        cfg_paths = {name: os.path.join(args.work, f"config_{tag}_{name}.toml") for name in sides}
        cfg, base_cfg, head_only = write_preset_configs(sides["base"], sides["head"], args.preset, args.iterations, args.sets,
                                             image_pixels(scene, args.images), cfg_paths["head"],
                                             cfg_paths["base"])
    else:
        cfg_path = os.path.join(args.work, f"config_{tag}.toml")
        cfg = write_config(sides["base"], sides["head"], args.iterations, args.sets, cfg_path)
        base_cfg, head_only = cfg, {}
        cfg_paths = {name: cfg_path for name in sides}
    pairs = {}
    for seed in args.seeds:
        pair = run_pair(sides, scene, args.images, cfg_paths, args.iterations, seed, args.work, tag, args.serial)
        pair["ratio"] = pair["head"]["it_per_s"] / pair["base"]["it_per_s"]
        # Load-robust cross-check: CPU seconds of the whole process (start-up and final evaluation
        # included, so it understates the training loop's gain), base / head.
        pair["cpu_ratio"] = pair["base"]["cpu_seconds"] / pair["head"]["cpu_seconds"]
        pairs[str(seed)] = pair
        print(json.dumps({"seed": seed, "ratio": pair["ratio"],
                          **{k: pair[k]["it_per_s"] for k in ("base", "head")}}), flush=True)
    res = {"tag": tag, "scene": scene, "images": args.images, "iterations": args.iterations, "seeds": args.seeds,
           "base": f"{args.base} ({shas['base'][:10]})", "head": f"{args.head} ({shas['head'][:10]})",
           "config_source": (f"preset {args.preset} (head), resolved by the head's rules for the base"
                             if args.preset else "configs/demo.toml"),
           "config": cfg, "base_config": base_cfg, "head_only_settings": head_only, "serial": args.serial, "pairs": pairs,
           "mean_ratio": statistics.mean(p["ratio"] for p in pairs.values()), "machine": machine(),
           "loadavg_start": load0, "loadavg_end": os.getloadavg(),
           "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "command": " ".join([os.path.relpath(sys.executable, REPO)] + sys.argv)}
    os.makedirs(args.out, exist_ok=True)
    write(res, os.path.join(args.out, f"train_speed_{tag}"))


if __name__ == "__main__":
    main()
