"""The speed/accuracy trade (issue: presets and the time budget), measured on the demo scene and on real photos.

For every scene and image scale it trains, through the `ctgs` CLI:
  - each preset (preview, fast, balanced) at its own length, and the 2dgs baseline with `--time-budget` set
    to the wall time that preset took (the same wall-clock time);
  - the content-aware method and the 2dgs baseline with `--time-budget` at each of the given budgets;
then exports and evaluates each run (test views: PSNR / SSIM / LPIPS, FPS, bytes) and writes
results/trade_<tag>.json + .md and two plots (PSNR vs train time, PSNR vs params).

Usage (each run is skipped when already done; several invocations with disjoint --only may share --work):
    .venv/bin/python benchmarks/trade.py --work /work/runs/trade [--scenes demo herzjesu]
        [--herzjesu /work/data/herzjesu25] [--budgets 5 15 45] [--presets preview fast balanced]
        [--scales 192x144 images_8 ...] [--only SUBSTRING ...] [--table-only] [--threads 1]
        [--re-eval-missing-lpips]
The herzjesu scene must exist (`ctgs sfm ../shared/data/herzjesu25/images -o SCENE`). Test views follow the
protocol (every 8th); nothing here chooses a setting.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

# Two image scales per scene: (label, demo size | herzjesu image folder).
DEMO_SCALES = [("192x144", (192, 144)), ("384x288", (384, 288))]
HERZ_SCALES = [("images_8", "images_8"), ("images_4", "images_4")]
METRIC_KEYS = ("psnr", "ssim", "lpips", "points", "texels", "params", "fps", "bytes_on_disk", "resolution")


def git_commit() -> str:
    """The checkout's HEAD, short: take it when runs start (a commit made while they train is not their code)."""
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=ROOT).stdout.strip() or "unknown"


def ctgs(*args: str, log: str) -> None:
    cmd = [sys.executable, "-m", "ctgs", *args]
    with open(log, "a") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        r = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    if r.returncode != 0:
        raise RuntimeError(f"failed ({r.returncode}): {' '.join(cmd)}; see {log}")


def scenes(args) -> list[dict]:
    out = []
    if "demo" in args.scenes:
        from ctgs.scene.demo import make_demo_scene

        for label, (w, h) in DEMO_SCALES:
            if args.scales and label not in args.scales:
                continue
            d = make_demo_scene(os.path.join(args.work, f"demo_{label}"), num_views=24, width=w, height=h,
                                points=3000)
            out.append({"scene": "demo", "scale": label, "dir": d, "images": "images", "pixels": w * h})
    if "herzjesu" in args.scenes:
        for label, folder in HERZ_SCALES:
            if args.scales and label not in args.scales:
                continue
            from ctgs.io.images import image_info

            first = sorted(os.listdir(os.path.join(args.herzjesu, folder)))[0]
            info = image_info(os.path.join(args.herzjesu, folder, first))
            out.append({"scene": "herzjesu", "scale": label, "dir": args.herzjesu, "images": folder,
                        "pixels": info.width * info.height})
    return out


def run_one(s: dict, name: str, train_args: list[str], args) -> dict | None:
    run = os.path.join(args.work, "runs", f"{s['scene']}_{s['scale']}_{name}")
    rec_path = os.path.join(run, "trade_record.json")
    selected = not args.only or any(o in os.path.basename(run) for o in args.only)
    if os.path.exists(rec_path):
        rec = json.load(open(rec_path))
        if args.re_eval_missing_lpips and rec["metrics"]["lpips"] is None and selected and not args.table_only:
            # The run was evaluated without the LPIPS weights (`make lpips-weights`): evaluate it again, metrics only.
            log = run + ".log"
            ctgs("eval", run, "--model", os.path.join(run, "model"), "-o", os.path.join(run, "eval"), log=log)
            metrics = json.load(open(os.path.join(run, "eval", "metrics.json")))
            rec["metrics"] = {k: metrics[k] for k in METRIC_KEYS}
            rec["per_view_psnr"] = per_view(metrics)
            rec["re_evaluated"] = time.strftime("%Y-%m-%d %H:%M")
            with open(rec_path, "w") as fh:
                json.dump(rec, fh, indent=1)
        return rec
    if args.table_only or not selected:
        return None
    os.makedirs(os.path.dirname(run), exist_ok=True)
    log = run + ".log"
    resume = ["--resume"] if os.path.exists(os.path.join(run, "checkpoints", "last.pt")) else []
    t0 = time.time()
    ctgs("train", s["dir"], "-o", run, "--images", s["images"], "-q", "--set", f"threads={args.threads}",
         *train_args, *resume, log=log)
    wall = time.time() - t0
    ctgs("export", run, "-o", os.path.join(run, "model"), log=log)
    ctgs("eval", run, "--model", os.path.join(run, "model"), "-o", os.path.join(run, "eval"), log=log)
    summary = json.load(open(os.path.join(run, "train_summary.json")))
    metrics = json.load(open(os.path.join(run, "eval", "metrics.json")))
    rec = {"scene": s["scene"], "scale": s["scale"], "name": name, "run": run, "train_args": train_args,
           "command_wall_s": wall, "summary": summary,
           "metrics": {k: metrics[k] for k in METRIC_KEYS}, "per_view_psnr": per_view(metrics)}
    if s["scene"] == "demo":
        rec["allocation"] = allocation(run, s["dir"])
    with open(rec_path, "w") as fh:
        json.dump(rec, fh, indent=1)
    return rec


def per_view(metrics: dict) -> dict:
    """{view name: test PSNR}: a mean over 3-4 views can be carried by one (benchmarks/per_view.py, blame.py)."""
    return {r["name"]: r["psnr"] for r in metrics.get("per_image", [])}


def allocation(run: str, scene_dir: str) -> dict:
    from ctgs.runs import load_run
    from measures.allocation import allocation_measures

    model = load_run(run).model
    meta = json.load(open(os.path.join(scene_dir, "demo_meta.json")))
    return allocation_measures(model, meta)["ratios"]


def preset_spec(spec: str) -> tuple[str, list[str], str]:
    """'fast:tau_ds=0.04,texture_trim=0' -> ('fast', ['--set', 'tau_ds=0.04', ...], 'fast_tau_ds0.04_texture_trim0')."""
    preset, _, rest = spec.partition(":")
    pairs = [kv for kv in rest.split(",") if kv]
    for kv in pairs:
        if "=" not in kv:
            raise SystemExit(f"trade.py: --presets {spec!r}: write overrides as PRESET:KEY=VALUE[,KEY=VALUE]")
    sets = [a for kv in pairs for a in ("--set", kv)]
    tag = "_".join([preset, *(kv.replace("=", "") for kv in pairs)])
    return preset, sets, tag


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default="/tmp/ctgs_trade")
    ap.add_argument("--scenes", nargs="*", default=["demo", "herzjesu"])
    ap.add_argument("--herzjesu", default=os.path.join(ROOT, "..", "data", "herzjesu25"))
    ap.add_argument("--presets", nargs="*", default=["preview", "fast", "balanced"])
    ap.add_argument("--budgets", nargs="*", type=float, default=[5.0, 15.0, 45.0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--scales", nargs="*", default=None, help="only these scales (192x144 384x288 images_8 images_4)")
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--re-eval-missing-lpips", action="store_true",
                    help="evaluate finished runs again whose records have no LPIPS (weights were missing)")
    ap.add_argument("--tag", default="herzjesu25_demo", help="names the record")
    args = ap.parse_args()
    try:
        import matplotlib  # noqa: F401  (the plots: checked before hours of training, not after them)
    except ImportError:
        raise SystemExit("trade.py: matplotlib is missing (it draws the plots): pip install -e '.[bench]'")
    from ctgs.metrics.vgg_weights import find_vgg16

    if find_vgg16().state is None and not args.table_only:  # LPIPS is a column: found out now, not after the runs
        raise SystemExit("trade.py: the LPIPS weights are missing: run `make lpips-weights` first")
    rows = []
    for s in scenes(args):  # already limited to --scales
        for spec in args.presets:
            p, sets, tag = preset_spec(spec)
            rec = run_one(s, f"ca_{tag}", ["--preset", p, *sets], args)
            if rec:
                rows.append(rec)
                # The 2dgs twin runs the bare preset (content-aware overrides do not apply to it); its name says
                # which run's wall time it was given when that run had overrides.
                twin = f"2dgs_{tag}" if not sets else f"2dgs_{p}_timed_as_ca_{tag}"
                rows_2 = run_one(s, twin, ["--preset", p, "--config", "2dgs", "--time-budget",
                                                  f"{rec['summary']['wall_seconds'] / 60:.3f}"], args)
                if rows_2:
                    rows.append(rows_2)
        for b in args.budgets:
            for method, extra in (("ca", []), ("2dgs", ["--config", "2dgs"])):
                rec = run_one(s, f"{method}_budget{b:g}", ["--preset", "fast", "--time-budget", f"{b:g}", *extra], args)
                if rec:
                    rows.append(rec)
    write(rows, args)


def write(rows: list[dict], args) -> None:
    out = record.stem("trade", args.tag)
    machine = {"host": platform.node(), "machine": platform.machine(), "cpus": os.cpu_count(),
               "python": platform.python_version(), "load_avg_end": os.getloadavg()}
    with open(out + ".json", "w") as fh:
        json.dump({"command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine,
                   "rows": rows}, fh, indent=1)
    lines = [f"# Speed/accuracy trade ({machine['host']}, {machine['machine']}, {machine['cpus']} cpus, "
             f"CPU backend, {args.threads} thread(s) per training)", "",
             f"Command: `{' '.join(sys.argv)}`. Test views: every 8th (protocol). Wall = the whole `ctgs train` "
             "command; budget runs state the budget asked for.", "",
             "| scene | scale | run | budget min | wall min | iterations | test PSNR | SSIM | LPIPS | points | texels | "
             "params | params/value | MB | FPS | texel size flat:photo | params/area photo:flat |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        s, m = r["summary"], r["metrics"]
        al = r.get("allocation", {})
        bud = s.get("time_budget_s")
        lp = "-" if m["lpips"] is None else f"{m['lpips']:.3f}"
        lines.append(
            f"| {r['scene']} | {r['scale']} | {r['name']} | {'-' if not bud else f'{bud / 60:.1f}'} | "
            f"{s['wall_seconds'] / 60:.1f} | {s['iterations']} | {m['psnr']:.2f} | {m['ssim']:.3f} | {lp} | "
            f"{m['points']} | {m['texels']} | {m['params']} | {s['params_per_observed_value']:.2f} | "
            f"{m['bytes_on_disk'] / 1e6:.2f} | {m['fps']:.1f} | "
            f"{al.get('texel_size_prim_flat_over_photo', float('nan')):.1f} | "
            f"{al.get('params_per_area_photo_over_flat', float('nan')):.1f} |")
    with_views = [r for r in rows if r.get("per_view_psnr")]
    if with_views:  # records written before per-view PSNR was kept have none
        lines += ["", "Test PSNR per view (the mean above is over these; the first view of a one-sided trajectory "
                  "is an extrapolation: docs/studies.md):", ""]
        for scene, scale in sorted({(r["scene"], r["scale"]) for r in with_views}):
            group = [r for r in with_views if (r["scene"], r["scale"]) == (scene, scale)]
            names = sorted({v for r in group for v in r["per_view_psnr"]})
            lines += [f"| {scene} {scale} | run | " + " | ".join(names) + " |",
                      "| --- | --- |" + " ---: |" * len(names)]
            for r in group:
                pv = r["per_view_psnr"]
                lines.append(f"| | {r['name']} | " + " | ".join(f"{pv[n]:.2f}" if n in pv else "-" for n in names) + " |")
            lines.append("")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    plot(rows, out)


def plot(rows: list[dict], out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({(r["scene"], r["scale"]) for r in rows})
    if not groups:
        return
    fig, axes = plt.subplots(2, len(groups), figsize=(4.2 * len(groups), 7), squeeze=False)
    for j, (scene, scale) in enumerate(groups):
        for method, color in (("ca", "tab:red"), ("2dgs", "tab:blue")):
            pts = [r for r in rows if r["scene"] == scene and r["scale"] == scale and r["name"].startswith(method + "_")]
            for r in pts:
                marker = "o" if "budget" in r["name"] else "s"
                x_t = r["summary"]["wall_seconds"] / 60
                axes[0][j].scatter(x_t, r["metrics"]["psnr"], c=color, marker=marker)
                axes[1][j].scatter(r["metrics"]["params"] / 1e6, r["metrics"]["psnr"], c=color, marker=marker)
                label = r["name"].split("_", 1)[1]
                axes[0][j].annotate(label, (x_t, r["metrics"]["psnr"]), fontsize=6)
        for ax in (axes[0][j], axes[1][j]):
            ax.ticklabel_format(useOffset=False)
            ax.set_xlim(left=0, right=ax.get_xlim()[1] * 1.15)  # from zero, and room for the labels
        axes[0][j].set_title(f"{scene} {scale}")
        axes[0][j].set_xlabel("wall time (min)")
        axes[1][j].set_xlabel("parameters (M)")
        axes[0][j].set_ylabel("test PSNR (dB)")
        axes[1][j].set_ylabel("test PSNR (dB)")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color="tab:red", marker="o", ls="", label="content-aware (ours)"),
               Line2D([], [], color="tab:blue", marker="o", ls="", label="2dgs"),
               Line2D([], [], color="k", marker="s", ls="", label="preset at its length"),
               Line2D([], [], color="k", marker="o", ls="", label="--time-budget")]
    wide = len(groups) > 1  # one column of panels is too narrow for the legend on one row
    fig.legend(handles=handles, loc="lower center", ncol=4 if wide else 2, fontsize=8)
    fig.tight_layout(rect=(0, 0.05 if wide else 0.09, 1, 1))
    fig.savefig(out + ".png", dpi=110)


if __name__ == "__main__":
    main()
