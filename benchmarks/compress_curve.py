"""The size-quality curve of `ctgs compress` on one trained run.

Usage:
  .venv/bin/python benchmarks/compress_curve.py RUN_DIR --name demo [--work DIR] [--only POINT ...]
      [--no-lpips] [--note TEXT]

Exports RUN_DIR (raw float32 model folder), then for every point below compresses it, evaluates the
result on the run's test views with `ctgs eval`'s code (PSNR, SSIM, LPIPS when the VGG weights are
present) and renders the training views for their PSNR/SSIM (the settings are chosen on those; test
views only report). Writes benchmarks/results/compress_curve/<name>_<commit>.{json,md,png}. Points already measured
with the same spec are reused from WORK/<name>/points/ (delete the folder, or pass --only, to redo).

Points: raw (the export); packed f32 (every value float32, only sorting + xz); texel modes (scalar
K=256/128/64/32/16, vector K=256/4096/65536, f16) with float32 attributes; each attribute option on top of the scalar
texels; the --target presets; the default with zlib / no coder / no sorting.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import sys
import time
from dataclasses import asdict, replace

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ctgs.io import atomic  # noqa: E402
from ctgs.formats.compress import DEFAULT_TARGET, TARGETS, Spec, compress_model  # noqa: E402
from ctgs.formats.model_format import read_model, write_model, write_packed_model  # noqa: E402
from ctgs.runs import load_run  # noqa: E402
from ctgs.evaluation.evaluate import EvalOptions, evaluate  # noqa: E402

RAW = Spec(texels="f32")  # every value float32: what sorting + xz alone gain
SCALAR = Spec(texels="scalar")  # the paper's texel codebook, attributes float32


def points() -> list[tuple[str, str, Spec | None]]:
    """(name, group, spec); spec None = the raw export."""
    out: list[tuple[str, str, Spec | None]] = [("raw", "raw", None), ("packed_f32", "coder", RAW)]
    out += [("texels_scalar_256", "texels", SCALAR), ("texels_f16", "texels", replace(RAW, texels="f16"))]
    out += [(f"texels_scalar_{k}", "texels", replace(SCALAR, codebook_size=k)) for k in (128, 64, 32, 16)]
    out += [(f"texels_vector_{k}", "texels", replace(RAW, texels="vector", codebook_size=k)) for k in (256, 4096, 65536)]
    for attr, codecs in (("means", ("f16", "q16")), ("scales", ("f16", "q16", "q8")), ("quats", ("f16", "q8")),
                         ("opacity", ("f16", "q8")), ("sh_dc", ("f16", "q8")),
                         ("sh_rest", ("f16", "q8", "kmeans:1024", "kmeans:4096")), ("k_min", ("f16",))):
        out += [(f"{attr}_{c.replace(':', '')}", "attributes", replace(SCALAR, **{attr: c})) for c in codecs]
    out += [(f"sh_degree_{d}", "attributes", replace(SCALAR, sh_degree=d)) for d in (2, 1, 0)]
    out += [(f"target_{t}", "targets", spec) for t, spec in TARGETS.items()]
    default = TARGETS[DEFAULT_TARGET]
    out += [("default_zlib", "coder", replace(default, coder="zlib")),
            ("default_no_coder", "coder", replace(default, coder="none")),
            ("default_unsorted", "coder", replace(default, sort=False))]
    return out


def train_view_metrics(model, scene, backend: str) -> dict:
    """Mean PSNR/SSIM over the training views (the views settings may be chosen on)."""
    from ctgs.metrics.psnr import psnr
    from ctgs.metrics.ssim import ssim
    from ctgs.render import render

    ps, ss = [], []
    with torch.no_grad():
        inputs = model.render_inputs()
        for view in scene.train:
            rgb = render(inputs, view.camera, backend=backend, sh_degree=model.sh_degree).rgb.clamp(0, 1)
            gt = torch.as_tensor(view.image, dtype=torch.float32)
            ps.append(psnr(rgb, gt))
            ss.append(float(ssim(rgb, gt)))
    return {"train_psnr": float(np.mean(ps)), "train_ssim": float(np.mean(ss)), "num_train_views": len(ps)}


def measure(run_dir: str, name: str, spec: Spec | None, work: str, scene, lpips: bool) -> dict:
    model_dir = os.path.join(work, "models", name)
    t0 = time.perf_counter()
    if spec is None:
        write_model(load_run(run_dir).model, model_dir, plain_ply=False)
        stats: dict = {}
    else:
        packed = compress_model(read_model(os.path.join(work, "models", "raw"))[0], spec)
        write_packed_model(packed, model_dir, extra={"compression": {"target": name, **packed.stats}})
        stats = packed.stats
    seconds = time.perf_counter() - t0
    model, files = read_model(model_dir)
    m = evaluate(run_dir, EvalOptions(out_dir=os.path.join(work, "evals", name), model_dir=model_dir,
                                      backend="cpu", device="cpu", lpips=lpips))
    row = {"point": name, "spec": None if spec is None else asdict(spec), "bytes": files.bytes_on_disk,
           "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"], "num_test_views": m["num_test_views"],
           "points": m["points"], "texels": m["texels"], "compress_seconds": seconds,
           "sections": {e["name"]: e["bytes"] for e in files.manifest.get("sections", [])},
           "texel_rmse": stats.get("texels", {}).get("rmse_activated"),
           "kmeans": {k: v for k, v in stats.items() if k in ("texels", "sh_rest_kmeans")}}
    row.update(train_view_metrics(model, scene, "cpu"))
    return row


def table(rows: list[dict], raw: dict) -> str:
    scalar = next((r for r in rows if r["point"] == "texels_scalar_256"), None)
    lines = ["| group | point | bytes | ratio | test PSNR | dPSNR | SSIM | LPIPS | train PSNR | dPSNR train "
             "| dPSNR train vs scalar |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lp = "n/a" if r["lpips"] is None else f"{r['lpips']:.4f}"
        own = f"{r['train_psnr'] - scalar['train_psnr']:+.3f}" if scalar and r["group"] == "attributes" else ""
        lines.append(f"| {r['group']} | {r['point']} | {r['bytes'] / 1e6:.3f} MB | {raw['bytes'] / r['bytes']:.1f}x "
                     f"| {r['psnr']:.3f} | {r['psnr'] - raw['psnr']:+.3f} | {r['ssim']:.4f} | {lp} "
                     f"| {r['train_psnr']:.3f} | {r['train_psnr'] - raw['train_psnr']:+.3f} | {own} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker below)

    metrics = [("psnr", "test PSNR (dB)"), ("ssim", "test SSIM"), ("lpips", "test LPIPS (lower is better)")]
    metrics = [m for m in metrics if all(r[m[0]] is not None for r in rows)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4.8))
    axes = np.atleast_1d(axes)
    colours = {"raw": "black", "coder": "tab:gray", "texels": "tab:blue", "attributes": "tab:orange",
               "targets": "tab:red"}
    for ax, (key, label) in zip(axes, metrics):
        for group, colour in colours.items():
            pts = [r for r in rows if r["group"] == group]
            if not pts:
                continue
            ax.scatter([r["bytes"] / 1e6 for r in pts], [r[key] for r in pts], c=colour, label=group,
                       s=60 if group == "targets" else 25, zorder=3)
            if group in ("texels", "targets", "raw"):
                for r in pts:
                    ax.annotate(r["point"].replace("texels_", "").replace("target_", ""), (r["bytes"] / 1e6, r[key]),
                                fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_xlabel("model size on disk (MB, log)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run_dir")
    ap.add_argument("--name", required=True, help="result files: benchmarks/results/compress_curve/<name>_<commit>.*")
    ap.add_argument("--work", default="/work/runs/compress/curve")
    ap.add_argument("--only", nargs="*", default=None, help="re-measure these points (others are reused)")
    ap.add_argument("--points", nargs="*", default=None, help="measure only these points (a partial curve)")
    ap.add_argument("--no-lpips", action="store_true")
    ap.add_argument("--note", default="", help="provenance of the run (config, commit) for the results")
    args = ap.parse_args()
    try:
        import matplotlib  # noqa: F401  (the plot: checked before the measurements, not after them)
    except ImportError:
        raise SystemExit("compress_curve.py: matplotlib is missing (it draws the plot): pip install -e '.[bench]'")
    from ctgs.scene import load_scene

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    work = os.path.join(args.work, args.name)
    os.makedirs(os.path.join(work, "points"), exist_ok=True)
    run = load_run(args.run_dir)
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    load_start = os.getloadavg()
    rows = []
    for name, group, spec in points():
        if args.points is not None and name not in args.points and name != "raw":
            continue
        cache = os.path.join(work, "points", name + ".json")
        cached = json.load(open(cache)) if os.path.isfile(cache) else None
        redo = args.only is not None and name in args.only
        if cached and not redo and cached["spec"] == (None if spec is None else asdict(spec)):
            rows.append({**cached, "group": group})
            continue
        if name != "raw" and not os.path.isdir(os.path.join(work, "models", "raw")):
            raise SystemExit("the raw point must be measured first (it is the first point)")
        print(f"[{time.strftime('%H:%M:%S')}] {args.name}: {name}", flush=True)
        row = measure(args.run_dir, name, spec, work, scene, not args.no_lpips)
        atomic.write_json(cache, row, indent=1)
        rows.append({**row, "group": group})
    raw = rows[0]
    default = next((r for r in rows if r["point"] == f"target_{DEFAULT_TARGET}"), rows[-1])
    summary = {"default_target": DEFAULT_TARGET, "raw_bytes": raw["bytes"], "default_bytes": default["bytes"],
               "size_ratio": raw["bytes"] / default["bytes"],
               "test_psnr_loss_db": raw["psnr"] - default["psnr"],
               "train_psnr_loss_db": raw["train_psnr"] - default["train_psnr"]}
    info = {"name": args.name, "run_dir": run.run_dir, "scene_dir": run.scene_dir, "images": run.images,
            "iterations": run.iteration, "config": run.config, "note": args.note,
            "command": "python " + shlex.join(sys.argv), "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "machine": {"node": platform.node(), "processor": platform.processor() or platform.machine(),
                        "cpu_count": os.cpu_count(), "torch": torch.__version__,
                        "load_average_start": load_start, "load_average_end": os.getloadavg()},
            "summary": summary, "rows": rows}
    out = os.path.relpath(record.stem("compress_curve", args.name))
    atomic.write_json(out + ".json", info, indent=1)
    md = [f"# Compression curve: {args.name}", "",
          f"Run `{run.run_dir}` ({run.images}, {run.iteration} iterations, {raw['points']} primitives, "
          f"{raw['texels']} texels). {args.note}".strip(), "",
          f"{info['date']}; {info['machine']['node']}, {info['machine']['cpu_count']} CPUs; CPU backend; "
          "points cached in WORK are reused, so the date is the table's, not each point's. Command:", "",
          "```", info["command"], "```", "",
          f"**Default (`--target {DEFAULT_TARGET}`): {default['bytes'] / 1e6:.3f} MB vs raw {raw['bytes'] / 1e6:.3f} MB "
          f"(x{summary['size_ratio']:.1f} smaller), test PSNR {default['psnr']:.3f} vs {raw['psnr']:.3f} dB "
          f"({-summary['test_psnr_loss_db']:+.3f} dB), train PSNR {-summary['train_psnr_loss_db']:+.3f} dB.**", "",
          "Test metrics over the run's test views (every 8th); train PSNR over the other views. "
          "dPSNR: difference to the raw export. Attribute rows change one attribute on top of "
          "`texels_scalar_256` (all other values float32).", "", table(rows, raw)]
    atomic.write_text(out + ".md", "\n".join(md))
    plot(rows, out + ".png", f"ctgs compress: {args.name} ({raw['points']} primitives, {raw['texels']} texels)")
    print("\n".join(md))


if __name__ == "__main__":
    main()
