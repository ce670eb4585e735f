"""The presets' trade on one real scene at equal wall-clock time: each variant trained with `--time-budget MINUTES`,
over several seeds, on the protocol's split; then exported, evaluated (PSNR / SSIM / LPIPS, FPS, bytes) and, for the
content-aware models, whether texel size follows the content.

    .venv/bin/python benchmarks/scene_trade.py ../shared/data/bonsai252 --scene bonsai252 --images images_4 \\
        --minutes 15 --variants fast 2dgs --seeds 0 1 2 --work /tmp/trade [--parallel 2] [--validation]

Variants: a preset name (preview, fast, balanced, paper) or `2dgs` (the baseline under --baseline-preset, default
fast). A variant may carry config overrides after `@`, comma-separated:
`fast@primitives_per_pixel=0.8,max_params_per_value=0.5` (a recipe study, on --validation views). With --parallel 2 two runs train at once, one thread each: every pair shares the machine alike, so their
times stay comparable (a run alone on 2 cores would not be). Runs already finished in --work are reused.
--validation trains on the training views less a validation split (validation_holdout 8) and scores on it: the
split for choices; the default scores the protocol's test views, for reporting only.

Texel size against content (content-aware models): for each test view, every primitive's texel size in pixels of
that view (texel world size / (depth / focal)) and the mean image-gradient energy (|grad|^2 of the photo's luminance,
Sobel) of the pixels it covers, weighted by its blending weight (the renderer's error statistics give both sums).
Reported: the weighted Spearman correlation over primitives, and the median texel size per gradient-energy quartile.
A negative correlation means detailed content gets smaller texels.

Writes benchmarks/results/scene_trade/<scene>_<images>_<minutes>min_<variants>_<seeds>_<commit>.{json,md} and a plot
(PSNR against train minutes and against parameters) beside them.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import re
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402
from trade import ctgs  # noqa: E402 (runs `python -m ctgs ...`, output appended to a log)

METRICS = ("psnr", "ssim", "lpips", "points", "texels", "params", "fps", "bytes_on_disk", "train_seconds")


def train_one(args, variant: str, seed: int, threads: int) -> str:
    tag = variant.replace("@", "_").replace(",", "_").replace("=", "")
    if len(tag) > 60:  # a long list of overrides: a file name holds at most 255 bytes
        tag = tag[:40] + "_" + hashlib.sha1(variant.encode()).hexdigest()[:10]
    run = os.path.join(args.work, f"{args.scene}_{args.images}_{args.minutes:g}min_{tag}_s{seed}")
    if os.path.isfile(os.path.join(run, "eval", "metrics.json")):
        return run
    name, _, overrides = variant.partition("@")
    preset = args.baseline_preset if name == "2dgs" else name
    train = ["train", args.scene_dir, "-o", run, "--images", args.images, "--preset", preset,
                    "--time-budget", f"{args.minutes:g}", "--seed", str(seed), "--set", f"threads={threads}", "-q"]
    if name == "2dgs":
        train += ["--config", "2dgs"]
    for kv in filter(None, overrides.split(",")):
        train += ["--set", kv]
    if args.validation:
        train += ["--set", "validation_holdout=8"]
    os.makedirs(args.work, exist_ok=True)
    log = run + ".log"
    if not os.path.isfile(os.path.join(run, "model.pt")):
        resume = ["--resume"] if os.path.isdir(os.path.join(run, "checkpoints")) else []
        ctgs(*train, *resume, log=log)
    ctgs("export", run, "-o", os.path.join(run, "model"), log=log)
    ctgs("eval", run, "--model", os.path.join(run, "model"), "-o", os.path.join(run, "eval"), "--scene-name", args.scene,
         log=log)
    return run


def texel_content(run: str, max_views: int) -> dict | None:
    """Weighted Spearman correlation between texel size (pixels) and gradient energy of the covered pixels."""
    import torch
    import torch.nn.functional as F

    from ctgs.render import render
    from ctgs.runs import load_run
    from ctgs.scene.loader import load_scene, validation_split
    from ctgs.train.routines.texels import texel_size

    r = load_run(run)
    m = r.model
    if m.texture_mode != "content_aware" or m.num_primitives == 0:
        return None
    scene = load_scene(r.scene_dir, images=r.images, holdout=r.holdout)
    views = scene.test
    if int(r.config.get("validation_holdout", 0)) > 0:
        _, views = validation_split(scene.train, int(r.config["validation_holdout"]))
    ts_world = texel_size(m).double()
    inputs = m.render_inputs()
    sobel = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8
    sizes, energies, weights = [], [], []
    for v in views[:max_views]:
        img = torch.from_numpy(np.ascontiguousarray(v.image)).float()
        lum = (img[..., :3] @ torch.tensor([0.299, 0.587, 0.114]))[None, None]
        lum = F.pad(lum, (1, 1, 1, 1), mode="replicate")
        gx, gy = F.conv2d(lum, sobel[None, None]), F.conv2d(lum, sobel.T[None, None])
        energy = (gx ** 2 + gy ** 2)[0, 0]
        with torch.no_grad():
            stats = render(inputs, v.camera, backend="cpu", sh_degree=m.sh_degree, error_image=energy).stats
        seen = stats.contrib > 1e-3
        vm = v.camera.viewmat.to(m.means.dtype)
        depth = (m.means.detach() @ vm[2, :3] + vm[2, 3]).double()
        px = ts_world / (depth.clamp_min(1e-9) / float(np.sqrt(v.camera.fx * v.camera.fy)))
        sizes.append(px[seen].numpy())
        energies.append((stats.err[seen] / stats.contrib[seen]).double().numpy())
        weights.append(stats.contrib[seen].double().numpy())
    s, e, w = (np.concatenate(x) for x in (sizes, energies, weights))
    if len(s) < 10:
        return None

    def ranks(x):
        return np.argsort(np.argsort(x)).astype(np.float64)

    rs, re_ = ranks(s), ranks(e)
    ms, me = np.average(rs, weights=w), np.average(re_, weights=w)
    cov = np.average((rs - ms) * (re_ - me), weights=w)
    rho = cov / np.sqrt(np.average((rs - ms) ** 2, weights=w) * np.average((re_ - me) ** 2, weights=w))
    q = np.quantile(e, [0.25, 0.5, 0.75])
    bins = np.digitize(e, q)
    return {"spearman_weighted": float(rho), "views": min(len(views), max_views), "pairs": int(len(s)),
            "median_texel_px_by_energy_quartile": [float(np.median(s[bins == b])) if np.any(bins == b) else None
                                                   for b in range(4)]}


def summarise(args, runs: dict) -> dict:
    rows = []
    for (variant, seed), run in sorted(runs.items()):
        m = json.load(open(os.path.join(run, "eval", "metrics.json")))
        s = json.load(open(os.path.join(run, "train_summary.json")))
        row = {"variant": variant, "seed": seed, **{k: m.get(k) for k in METRICS},
               "iterations": s.get("iterations"), "wall_seconds": s.get("wall_seconds"),
               "params_per_observed_value": m["params"] / s["observed_values"] if s.get("observed_values") else None,
               "open_pixels": m.get("open_pixels"), "resolution": m["resolution"],
               "texel_content": texel_content(run, args.content_views) if not args.no_content else None}
        rows.append(row)
    return {"scene": args.scene, "images": args.images, "minutes": args.minutes, "seeds": args.seeds,
            "variants": args.variants, "baseline_preset": args.baseline_preset, "parallel": args.parallel, "threads": args.threads,
            "split": "validation (validation_holdout 8)" if args.validation else
            ("test (the scene's test_views.txt)" if any(_test_list(r) for r in runs.values()) else "test (every 8th photo)"),
            "commit": args.commit_start, "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "processor": platform.processor()},
            "load_average_start": args.load_start, "load_average_end": os.getloadavg(), "rows": rows}


def _test_list(run: str) -> bool:
    with open(os.path.join(run, "eval", "metrics.json")) as fh:
        return bool(json.load(fh).get("test_list"))


def markdown(res: dict) -> str:
    out = [f"# {res['scene']} {res['images']}: {', '.join(res['variants'])} at {res['minutes']:g} minutes each",
           "", f"Split: {res['split']}. Commit {res['commit']}, {res['date_utc']}, {res['machine']['cpus']}-core "
           f"{res['machine']['processor'] or 'x86'} machine, {res['parallel']} run(s) at a time, "
           f"{res.get('threads', '?')} thread(s) each; load average "
           f"{res['load_average_start'][0]:.1f} at the start, {res['load_average_end'][0]:.1f} at the end.", "",
           "| variant | seed | PSNR | SSIM | LPIPS | wall min | its | primitives | texels | params | params/value | "
           "FPS | MB | open | texel~energy rho |", "|---|---:|" + "---:|" * 13]
    for r in res["rows"]:
        tc = r["texel_content"]
        lp = "n/a" if r["lpips"] is None else f"{r['lpips']:.3f}"
        out.append(f"| {r['variant']} | {r['seed']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {lp} | "
                   f"{(r['wall_seconds'] or 0) / 60:.1f} | {r['iterations']} | {r['points']} | {r['texels']} | "
                   f"{r['params']} | {r['params_per_observed_value'] or 0:.3f} | {r['fps']:.1f} | "
                   f"{r['bytes_on_disk'] / 1e6:.1f} | {100 * (r['open_pixels'] or 0):.1f}% | "
                   + (f"{tc['spearman_weighted']:.2f}" if tc else "-") + " |")
    out += ["", "Means over seeds:", "", "| variant | PSNR | SSIM | LPIPS | params | primitives |",
            "|---|---:|---:|---:|---:|---:|"]
    for v in res["variants"]:
        rs = [r for r in res["rows"] if r["variant"] == v]
        if not rs:
            continue
        lp = [r["lpips"] for r in rs if r["lpips"] is not None]
        out.append(f"| {v} | {np.mean([r['psnr'] for r in rs]):.2f} | {np.mean([r['ssim'] for r in rs]):.3f} | "
                   + (f"{np.mean(lp):.3f}" if len(lp) == len(rs) else "n/a")
                   + f" | {np.mean([r['params'] for r in rs]):.0f} | {np.mean([r['points'] for r in rs]):.0f} |")
    return "\n".join(out) + "\n"


def plot(res: dict, path: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib missing (pip install -e '.[bench]'): no plot")
        return
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for v in res["variants"]:
        rs = [r for r in res["rows"] if r["variant"] == v]
        ax[0].scatter([r["wall_seconds"] / 60 for r in rs], [r["psnr"] for r in rs], label=v)
        ax[1].scatter([r["params"] / 1e6 for r in rs], [r["psnr"] for r in rs], label=v)
    ax[0].set_xlabel("train wall minutes")
    ax[1].set_xlabel("parameters (M)")
    for a in ax:
        a.set_ylabel("PSNR (dB)")
        a.grid(alpha=0.3)
    ax[0].legend()
    fig.suptitle(f"{res['scene']} {res['images']}, {res['minutes']:g} min each ({res['split'].split(' ')[0]} views)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scene_dir")
    ap.add_argument("--scene", required=True, help="scene name in records (e.g. bonsai252)")
    ap.add_argument("--images", default="images_4")
    ap.add_argument("--minutes", type=float, required=True, help="--time-budget of every run")
    ap.add_argument("--variants", nargs="+", default=["fast", "2dgs"])
    ap.add_argument("--baseline-preset", default="fast", help="the preset the 2dgs baseline trains under")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--work", required=True, help="folder for the runs (reused when finished)")
    ap.add_argument("--parallel", type=int, default=1, help="runs at once (threads = cores / parallel each)")
    ap.add_argument("--threads", type=int, default=0,
                    help="threads per run (default cores / parallel; set it when another sweep shares the machine)")
    ap.add_argument("--validation", action="store_true", help="score a validation split of the training views")
    ap.add_argument("--content-views", type=int, default=8, help="views of the texel-size analysis")
    ap.add_argument("--no-content", action="store_true", help="skip the texel-size analysis")
    ap.add_argument("--name", default=None, help="record name (default from scene, images, minutes, variants)")
    args = ap.parse_args()
    args.scene_dir, args.work = os.path.abspath(args.scene_dir), os.path.abspath(args.work)  # the runs' cwd is the repo
    args.load_start = os.getloadavg()
    args.commit_start = record.commit()  # the code the runs train with (HEAD may move while they run)
    threads = args.threads or max(1, (os.cpu_count() or 2) // max(args.parallel, 1))
    args.threads = threads
    jobs = [(v, s) for s in args.seeds for v in args.variants]
    with ThreadPoolExecutor(max(args.parallel, 1)) as pool:
        runs = dict(zip(jobs, pool.map(lambda j: train_one(args, j[0], j[1], threads), jobs)))
    res = summarise(args, runs)
    name = args.name or (f"{args.scene}_{args.images}_{args.minutes:g}min_{'_'.join(v.partition('@')[0] for v in args.variants)}_"
                         f"{len(args.seeds)}seed{'s' if len(args.seeds) > 1 else ''}"
                         + ("_validation" if args.validation else ""))
    # named by the commit the runs trained at (a name that ends with a commit keeps it)
    path = record.stem("scene_trade", name if re.search(r"_[0-9a-f]{7}$", name) else f"{name}_{args.commit_start}")
    record.write_record(path, res, markdown)
    plot(res, path + ".png")


if __name__ == "__main__":
    main()
