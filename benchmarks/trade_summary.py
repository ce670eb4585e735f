"""The speed/accuracy trade from every recorded run: each preset and the 2dgs baseline, over seeds where there are some.

Nothing is trained here. The script reads the JSON records other benchmarks wrote (trade.py, paired.py,
equal_time.py; the registry below names each file and which runs of it make a point), and writes for each scene
a table (mean, standard deviation and count over seeds; the commit of every source) and a plot: test PSNR against
wall-clock minutes and against parameters, content-aware in red and 2dgs in blue, one panel column per image
size, error bars one standard deviation over seeds where a point has several.

The records come from different commits (the trainer changed between them; each file names its commit), and
single runs on herzjesu25 move by up to 1 dB with the seed: read the seeded points first.

Usage: .venv/bin/python benchmarks/trade_summary.py  (writes benchmarks/results/trade_summary/<scene>.{md,png})
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")

# One point: (method, label, [(file, selector), ...]). A selector picks runs of a file:
#   ("trade", scale, row name)      rows of a trade.py record
#   ("paired", run label)           runs of a paired.py record
#   ("equal_time", method)          the test-split run of an equal_time.py record (ca | 2dgs)
#   ("scene_trade", variant)        the rows (seeds) of a scene_trade.py record for one variant
HERZ_EQUAL_TIME_192 = ["equal_time/herzjesu25_192_d64bc36.json", "equal_time/herzjesu25_192_seed1_d64bc36.json", "equal_time/herzjesu25_192_seed2_1c1d1a1.json",
                       "equal_time/herzjesu25_192_seed3_1c1d1a1.json"] + [
    f"equal_time/herzjesu25_192_seed{s}_edb494c.json" for s in range(4, 8)]
HERZ_EQUAL_TIME_384 = ["equal_time/herzjesu25_384_seed0_5de4149.json", "equal_time/herzjesu25_384_seed1_4865d28.json",
                       "equal_time/herzjesu25_384_seed2_4865d28.json"]


def size_budget_points(record: str, scale: str) -> list:
    """The size-budget trade pairs of a trade.py record: `fast` and `preview` with their size budget, and 2DGS given
    each one's wall time."""
    points = []
    for method, prefix, suffix in (("content-aware", "ca", ""), ("2dgs", "2dgs", "'s time")):
        for preset in ("fast", "preview"):
            points.append((method, f"{preset} + size budget{suffix}",
                           [(record, ("trade", scale, f"{prefix}_{preset}"))]))
    return points


MIN_PSNR_SPAN = 2.0  # dB: the least PSNR range a panel shows (the seed spread of one herzjesu25 run is ~1 dB)
BONSAI_15 = "scene_trade/bonsai252_images_4_15min_fast_2dgs_3seeds_531a0a8.json"
BONSAI_60 = "scene_trade/bonsai252_images_4_60min_balanced_1seed_531a0a8.json"
BONSAI_10 = "scene_trade/bonsai252_images_4_10min_fast_2dgs_1seed_db41397.json"
BONSAI_15P = "scene_trade/bonsai252_images_4_15min_preview_1seed_531a0a8.json"
BONSAI_15P12 = "scene_trade/bonsai252_images_4_15min_preview_seeds1-2_d42cfeb.json"
BONSAI_60S1 = "scene_trade/bonsai252_images_4_60min_balanced_seed1_d42cfeb.json"
BONSAI2_60 = "scene_trade/bonsai252_images_2_60min_fast_2dgs_1seed_d42cfeb.json"
BONSAI2_60B = "scene_trade/bonsai252_images_2_60min_balanced_1seed_d42cfeb.json"
BONSAI2_60E = "scene_trade/bonsai252_images_2_60min_fast_2dgs_1seed_16f95c3.json"
BONSAI2_60E1 = "scene_trade/bonsai252_images_2_60min_fast_2dgs_seed1_d4cb9cb.json"
BONSAI2_60E2 = "scene_trade/bonsai252_images_2_60min_fast_2dgs_seed2_86bc3e1.json"
BONSAI2_60EB = "scene_trade/bonsai252_images_2_60min_balanced_seed0_d4cb9cb.json"
BONSAI2_60EB1 = "scene_trade/bonsai252_images_2_60min_balanced_seed1_f579504.json"
BONSAI2_60EB2 = "scene_trade/bonsai252_images_2_60min_balanced_seed2_a216826.json"
BONSAI2_60P = "scene_trade/bonsai252_images_2_60min_preview_seed0_f579504.json"
BONSAI2_60P1 = "scene_trade/bonsai252_images_2_60min_preview_seed1_a216826.json"
BONSAI2_60P2 = "scene_trade/bonsai252_images_2_60min_preview_seed2_a216826.json"
BONSAI_60S2 = "scene_trade/bonsai252_images_4_60min_balanced_seed2_d4cb9cb.json"
REGISTRY = {
    "bonsai252": {
        "200x133": [
            ("content-aware", "preview, --time-budget 15",
             [(BONSAI_15P, ("scene_trade", "preview")), (BONSAI_15P12, ("scene_trade", "preview"))]),
            ("content-aware", "fast, --time-budget 15", [(BONSAI_15, ("scene_trade", "fast"))]),
            ("content-aware", "balanced, --time-budget 60",
             [(BONSAI_60, ("scene_trade", "balanced")), (BONSAI_60S1, ("scene_trade", "balanced")),
              (BONSAI_60S2, ("scene_trade", "balanced"))]),
            ("content-aware", "fast at 0.4 primitives per pixel, --time-budget 10", [(BONSAI_10, ("scene_trade", "fast"))]),
            ("2dgs", "the same 15 min", [(BONSAI_15, ("scene_trade", "2dgs"))]),
            ("2dgs", "the same 10 min", [(BONSAI_10, ("scene_trade", "2dgs"))]),
        ],
        "399x266": [
            ("content-aware", "fast, --time-budget 60 (E from 16 views, as shipped)",
             [(BONSAI2_60E, ("scene_trade", "fast")), (BONSAI2_60E1, ("scene_trade", "fast")),
              (BONSAI2_60E2, ("scene_trade", "fast"))]),
            ("content-aware", "balanced, --time-budget 60 (E from 16 views, as shipped)",
             [(BONSAI2_60EB, ("scene_trade", "balanced")), (BONSAI2_60EB1, ("scene_trade", "balanced")),
              (BONSAI2_60EB2, ("scene_trade", "balanced"))]),
            ("content-aware", "preview, --time-budget 60", [(BONSAI2_60P, ("scene_trade", "preview")),
                                                        (BONSAI2_60P1, ("scene_trade", "preview")),
                                                        (BONSAI2_60P2, ("scene_trade", "preview"))]),
            ("content-aware", "fast, --time-budget 60, E from 64 views (before error_pixels)",
             [(BONSAI2_60, ("scene_trade", "fast"))]),
            ("content-aware", "balanced, --time-budget 60, E from 64 views (before error_pixels)",
             [(BONSAI2_60B, ("scene_trade", "balanced"))]),
            ("2dgs", "the same 60 min (seeds 0, 0, 1, 2)",
             [(BONSAI2_60, ("scene_trade", "2dgs")), (BONSAI2_60E, ("scene_trade", "2dgs")), (BONSAI2_60E1, ("scene_trade", "2dgs")),
              (BONSAI2_60E2, ("scene_trade", "2dgs"))]),
        ],
    },
    "herzjesu25": {
        "192x128": [
            ("content-aware", "preview (1000 it.)", [("trade/herzjesu25_preview_66660b4.json", ("trade", "images_8", "ca_preview"))]),
            ("content-aware", "fast (3000 it.)",
             [("paired/herzjesu25_balanced_fast_eca05b4.json", ("paired", "fast"))]),
            ("content-aware", "fast, length chosen on validation",
             [(f, ("equal_time", "ca")) for f in HERZ_EQUAL_TIME_192]),
            ("content-aware", "balanced (10k it.)",
             [("paired/herzjesu25_balanced_fast_eca05b4.json", ("paired", "balanced"))]),
            ("content-aware", "paper (30k it.)", [("trade/herzjesu25_paper_3d53175.json", ("trade", "images_8", "ca_paper"))]),
            *size_budget_points("trade/herzjesu25_3148d9f.json", "images_8"),
            ("content-aware", "fast + size budget, 3000 it.",
             [("paired/herzjesu25_192_balanced_budget_fast_4seeds_17aac07.json", ("paired", "fast"))]),
            ("content-aware", "balanced + size budget, 10k it.",
             [("paired/herzjesu25_192_balanced_budget_fast_4seeds_17aac07.json", ("paired", "balanced"))]),
            ("content-aware", "balanced, no size budget, 10k it.",
             [("paired/herzjesu25_192_balanced_nobudget_budget_4seeds_030852a.json",
               ("paired", "balanced_max_params_per_value0"))]),
            ("content-aware", "balanced + size budget, trade run",
             [("trade/herzjesu25_96fa9a6.json", ("trade", "images_8", "ca_balanced"))]),
            ("content-aware", "fast as it ships (+ exposure gains), 3000 it.",
             [("paired/herzjesu25_192_balanced_fast_exposure_both_4seeds_f91220f.json", ("paired", "fast"))]),
            ("content-aware", "balanced as it ships (+ opacity resets, exposure gains), 10k it.",
             [("paired/herzjesu25_192_balanced_fast_exposure_both_4seeds_f91220f.json", ("paired", "balanced"))]),
            ("2dgs", "preview's time", [("trade/herzjesu25_preview_66660b4.json", ("trade", "images_8", "2dgs_preview"))]),
            ("2dgs", "fast's time", [("trade/herzjesu25_fff5bb3.json", ("trade", "images_8", "2dgs_fast"))]),
            ("2dgs", "length chosen on validation", [(f, ("equal_time", "2dgs")) for f in HERZ_EQUAL_TIME_192]),
            ("2dgs", "balanced's time", [("trade/herzjesu25_balanced_37db8bd.json", ("trade", "images_8", "2dgs_balanced"))]),
            ("2dgs", "balanced + size budget's time", [("trade/herzjesu25_96fa9a6.json", ("trade", "images_8", "2dgs_balanced"))]),
            ("2dgs", "paper's time", [("trade/herzjesu25_paper_3d53175.json", ("trade", "images_8", "2dgs_paper"))]),
        ],
        "384x256": [
            ("content-aware", "fast (3000 it.)",
             [("paired/herzjesu25_384_balanced_fast_0f67e86.json", ("paired", "fast"))]),
            ("content-aware", "fast, length chosen on validation",
             [(f, ("equal_time", "ca")) for f in HERZ_EQUAL_TIME_384]),
            ("content-aware", "balanced (10k it.)",
             [("paired/herzjesu25_384_balanced_fast_0f67e86.json", ("paired", "balanced"))]),
            ("content-aware", "balanced, --time-budget 57",
             [("paired/herzjesu25_384_balanced_hour_fast_3seeds_b366019.json", ("paired", "balanced_time_budget57"))]),
            ("content-aware", "fast, --time-budget 10",
             [("paired/herzjesu25_384_fast_2dgs_budget10_calendar_3seeds_c1f0a0a.json", ("paired", "fast_time_budget10"))]),
            ("content-aware", "fast, --time-budget 20",
             [("paired/herzjesu25_384_fast_2dgs_budget20_3seeds_e80749d.json", ("paired", "fast_time_budget20"))]),
            ("content-aware", "fast + tau_ds 0.04, --time-budget 20",
             [("paired/herzjesu25_384_fast_tau04_2dgs_budget20_3seeds_7044685.json",
               ("paired", "fast_tau_ds0.04_time_budget20"))]),
            ("content-aware", "fast + size budget, --time-budget 10",
             [("paired/herzjesu25_384_fast_default_budget_2dgs_budget10_3seeds_bd1eb71.json",
               ("paired", "fast_time_budget10"))]),
            ("content-aware", "fast + size budget, --time-budget 20",
             [("paired/herzjesu25_384_fast_default_budget_2dgs_budget20_3seeds_08494ec.json",
               ("paired", "fast_time_budget20"))]),
            ("content-aware", "fast + size budget, 3000 it.",
             [("paired/herzjesu25_384_balanced_budget_fast_3seeds_dbca6cf.json", ("paired", "fast"))]),
            ("content-aware", "balanced + size budget, 10k it.",
             [("paired/herzjesu25_384_balanced_budget_fast_3seeds_dbca6cf.json", ("paired", "balanced"))]),
            ("content-aware", "fast --max-params 1.28M, --time-budget 20",
             [("paired/herzjesu25_384_fast_maxparams_2dgs_budget20_3seeds_6ef5119.json",
               ("paired", "fast_time_budget20_max_params1284162"))]),
            ("content-aware", "fast as it ships (+ exposure gains), --time-budget 10",
             [("paired/herzjesu25_384_fast_2dgs_budget10_3seeds_b4e3dc3.json", ("paired", "fast_time_budget10"))]),
            ("content-aware", "fast as it ships (+ exposure gains), --time-budget 20",
             [("paired/herzjesu25_384_fast_2dgs_budget20_3seeds_2717385.json", ("paired", "fast_time_budget20"))]),
            ("2dgs", "fast's time", [("trade/herzjesu25_fff5bb3.json", ("trade", "images_4", "2dgs_fast"))]),
            ("2dgs", "the same 10 min",
             [("paired/herzjesu25_384_fast_2dgs_budget10_calendar_3seeds_c1f0a0a.json",
               ("paired", "fast_2dgs_time_budget10"))]),
            ("2dgs", "the same 20 min",
             [("paired/herzjesu25_384_fast_2dgs_budget20_3seeds_e80749d.json", ("paired", "fast_2dgs_time_budget20"))]),
            ("2dgs", "the same 10 min (beside `fast` as it ships)",
             [("paired/herzjesu25_384_fast_2dgs_budget10_3seeds_b4e3dc3.json", ("paired", "fast_2dgs_time_budget10"))]),
            ("2dgs", "the same 20 min (beside `fast` as it ships)",
             [("paired/herzjesu25_384_fast_2dgs_budget20_3seeds_2717385.json", ("paired", "fast_2dgs_time_budget20"))]),
            ("2dgs", "length chosen on validation", [(f, ("equal_time", "2dgs")) for f in HERZ_EQUAL_TIME_384]),
            ("2dgs", "balanced's time",
             [("paired/herzjesu25_384_balanced_2dgs_time_3seeds_264fb57.json", ("paired", "balanced_2dgs_time_budget43.5"))]),
        ],
        "768x512": [
            ("content-aware", "fast, --time-budget 30",
             [("paired/herzjesu25_768_fast_2dgs_budget30_3seeds_be1f70a.json", ("paired", "fast_time_budget30"))]),
            ("2dgs", "the same 30 min",
             [("paired/herzjesu25_768_fast_2dgs_budget30_3seeds_be1f70a.json", ("paired", "fast_2dgs_time_budget30"))]),
        ],
    },
    "demo": {
        "192x144": [
            ("content-aware", "preview (1000 it.)", [("trade/demo_6d9c165.json", ("trade", "192x144", "ca_preview"))]),
            ("content-aware", "fast (3000 it.)", [("paired/demo192x144_balanced_fast_16b8d40.json", ("paired", "fast"))]),
            ("content-aware", "balanced (10k it.)",
             [("paired/demo192x144_balanced_fast_16b8d40.json", ("paired", "balanced"))]),
            ("content-aware", "paper (30k it.)", [("trade/demo_paper_638e279.json", ("trade", "192x144", "ca_paper"))]),
            *size_budget_points("trade/demo_3148d9f.json", "192x144"),
            ("content-aware", "balanced + size budget", [("trade/demo_030852a.json", ("trade", "192x144", "ca_balanced"))]),
            ("content-aware", "fast + size budget, 3000 it.",
             [("paired/demo192x144_balanced_budget_fast_4seeds_d3509df.json", ("paired", "fast"))]),
            ("content-aware", "balanced + size budget, 10k it.",
             [("paired/demo192x144_balanced_budget_fast_4seeds_d3509df.json", ("paired", "balanced"))]),
            ("content-aware", "fast as it ships (+ exposure gains), 3000 it.",
             [("paired/demo192x144_balanced_fast_exposure_4seeds_68389ac.json", ("paired", "fast"))]),
            ("content-aware", "balanced as it ships (+ opacity resets, exposure gains), 10k it.",
             [("paired/demo192x144_balanced_fast_exposure_4seeds_68389ac.json", ("paired", "balanced"))]),
            ("2dgs", "preview's time", [("trade/demo_6d9c165.json", ("trade", "192x144", "2dgs_preview"))]),
            ("2dgs", "fast's time", [("trade/demo_fff5bb3.json", ("trade", "192x144", "2dgs_fast"))]),
            ("2dgs", "balanced's time", [("trade/demo_6d9c165.json", ("trade", "192x144", "2dgs_balanced"))]),
            ("2dgs", "balanced + size budget's time", [("trade/demo_030852a.json", ("trade", "192x144", "2dgs_balanced"))]),
            ("2dgs", "paper's time", [("trade/demo_paper_638e279.json", ("trade", "192x144", "2dgs_paper"))]),
        ],
        "384x288": [
            ("content-aware", "fast (3000 it.)", [("trade/demo_fff5bb3.json", ("trade", "384x288", "ca_fast"))]),
            ("2dgs", "fast's time", [("trade/demo_fff5bb3.json", ("trade", "384x288", "2dgs_fast"))]),
        ],
    },
}
COLOURS = {"content-aware": "tab:red", "2dgs": "tab:blue"}


def runs_of(path: str, selector: tuple) -> tuple[list[dict], str]:
    """([{psnr, wall_min, params, iterations}], commit or date) of the runs `selector` picks in the record."""
    with open(path) as fh:
        rec = json.load(fh)
    kind = selector[0]
    if kind == "trade":
        _, scale, name = selector
        rows = [r for r in rec["rows"] if r["scale"] == scale and r["name"] == name]
        picked = [{"psnr": r["metrics"]["psnr"], "wall_min": r["command_wall_s"] / 60, "params": r["metrics"]["params"],
                   "iterations": r["summary"]["iterations"]} for r in rows]
        source = rec.get("commit") or rec["date"]
    elif kind == "paired":
        runs = [r for r in rec["runs"] if r["label"] == selector[1]]
        picked = [{"psnr": r["psnr"], "wall_min": r["wall_s"] / 60, "params": r["params"],
                   "iterations": r["iterations"]} for r in runs]
        # the commits the runs trained at where their records name them (paired.py names them)
        source = "/".join(sorted({r["commit"] for r in runs if r.get("commit")})) or rec["commit"]
    elif kind == "equal_time":
        picked = [{"psnr": r["psnr"], "wall_min": r["wall_s"] / 60, "params": r["params"],
                   "iterations": r["iterations"]} for r in rec["test"] if r["method"] == selector[1]]
        source = rec["commit"]
    elif kind == "scene_trade":
        picked = [{"psnr": r["psnr"], "wall_min": r["wall_seconds"] / 60, "params": r["params"],
                   "iterations": r["iterations"]} for r in rec["rows"] if r["variant"] == selector[1]]
        source = rec["commit"]
    else:
        raise ValueError(f"unknown selector {selector!r}")
    if not picked:
        raise SystemExit(f"{path}: no run matches {selector!r}")
    return picked, source


def summarise(scene: str) -> list[dict]:
    points = []
    for size, entries in REGISTRY[scene].items():
        for number, (method, label, sources) in enumerate(entries, start=1):
            runs, origins = [], []
            for name, selector in sources:
                picked, source = runs_of(os.path.join(RESULTS, name), selector)
                runs += picked
                origins.append(f"{name} ({source})")
            stat = {}
            for key in ("psnr", "wall_min", "params"):
                values = [r[key] for r in runs]
                stat[key] = statistics.fmean(values)
                stat[key + "_sd"] = statistics.stdev(values) if len(values) > 1 else 0.0
            its = sorted({r["iterations"] for r in runs})
            points.append({"size": size, "number": number, "method": method, "label": label, "n": len(runs), **stat,
                           "iterations": its, "sources": origins})
    return points


def plot(scene: str, points: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    sizes = list(REGISTRY[scene])
    rows_of_key = max(len(REGISTRY[scene][size]) for size in sizes)
    key_h = 0.75 + 0.17 * rows_of_key  # inches: one line per point of the longest column
    fig, axes = plt.subplots(3, len(sizes), figsize=(6.5 * len(sizes), 9 + key_h), squeeze=False,
                             gridspec_kw={"height_ratios": [4.5, 4.5, key_h]})
    for col, size in enumerate(sizes):
        mine = [p for p in points if p["size"] == size]
        for row, (key, xlabel) in enumerate((("wall_min", "wall-clock minutes (2-core VM, log scale)"),
                                             ("params", "parameters (log scale)"))):
            ax = axes[row][col]
            for p in mine:
                c = COLOURS[p["method"]]
                x = p[key] / (1e6 if key == "params" else 1)
                ax.errorbar(x, p["psnr"], yerr=p["psnr_sd"] or None, fmt="o" if p["n"] > 1 else "s", color=c,
                            ms=7 if p["n"] > 1 else 5, capsize=3, mfc=c if p["n"] > 1 else "white")
                # the point's number: its line in the key below the panels and its row in the .md table
                ax.annotate(str(p["number"]), (x, p["psnr"]), textcoords="offset points", fontsize=8, color=c,
                            fontweight="bold", xytext=(5, 2) if p["method"] == "content-aware" else (5, -9))
            ax.set_xscale("log")
            xs = [p[key] / (1e6 if key == "params" else 1) for p in points if p["size"] == size]
            lo, hi = min(xs) / 1.4, max(xs) * 1.6  # room for the labels, also when every point has one x
            ax.set_xlim(lo, hi)
            ticks = [t for t in (0.3, 0.5, 1, 2, 3, 5, 10, 20, 30, 60) if lo <= t <= hi]
            ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_xlabel(xlabel.replace("parameters", "parameters, millions") if key == "params" else xlabel)
            ax.set_ylabel("test PSNR (dB)")
            ys = [(p["psnr"] - (p["psnr_sd"] or 0), p["psnr"] + (p["psnr_sd"] or 0)) for p in points if p["size"] == size]
            y_lo, y_hi = min(y for y, _ in ys), max(y for _, y in ys)
            if y_hi - y_lo < MIN_PSNR_SPAN:  # a panel of close points is not zoomed until 0.2 dB looks like 2 dB
                mid = (y_lo + y_hi) / 2
                ax.set_ylim(mid - MIN_PSNR_SPAN / 2 - 0.2, mid + MIN_PSNR_SPAN / 2 + 0.2)
            ax.set_title(f"{scene} {size}")
            ax.grid(alpha=0.3, which="both")
        key_ax = axes[2][col]
        key_ax.axis("off")
        for i, p in enumerate(mine):
            key_ax.text(0.0, 1.0 - i / max(rows_of_key, 1), f"{p['number']:>2}  {p['label']}"
                        + (f" (n={p['n']})" if p["n"] > 1 else ""), transform=key_ax.transAxes, fontsize=8,
                        color=COLOURS[p["method"]], va="top", family="monospace")
    handles = [plt.Line2D([], [], color=COLOURS["content-aware"], marker="o", ls="", label="content-aware (ours)"),
               plt.Line2D([], [], color=COLOURS["2dgs"], marker="o", ls="", label="2dgs"),
               plt.Line2D([], [], color="k", marker="o", ls="", label="mean over seeds, bar = 1 sd"),
               plt.Line2D([], [], color="k", marker="s", mfc="white", ls="", label="one run")]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=9)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)
    plt.close(fig)


def write(scene: str, points: list[dict]) -> None:
    base = os.path.join(RESULTS, "trade_summary", scene)
    try:
        commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    lines = [f"# The speed/accuracy trade on {scene}, from the recorded runs", "",
             f"Written by `benchmarks/trade_summary.py` on {time.strftime('%Y-%m-%d %H:%M')}, {platform.node()}, commit "
             f"{commit}, from the records below (nothing trained here; every run on the dev VM: 2 x86-64 cores, 24 GB, "
             "no GPU, one thread per training, two trainings side by side). Mean over the runs of a point, +- one "
             "standard deviation where there are several (seeds). Wall = the whole `ctgs train` command. The records "
             "come from different commits (named per source): the trainer changed between them; `fast` and `preview` "
             "points not marked 'size budget' predate those presets' default size budget of "
             "0.3 parameters per observed value. Plot: "
             f"`{scene}.png`.", ""]
    for size in REGISTRY[scene]:
        lines += [f"## {size}", "", "| # | method | point | runs | iterations | test PSNR | wall min | params | sources |",
                  "| ---: | --- | --- | ---: | --- | --- | --- | --- | --- |"]
        for p in (p for p in points if p["size"] == size):
            sd = lambda k, f: f"{f.format(p[k])}" + (f" +- {f.format(p[k + '_sd'])}" if p["n"] > 1 else "")  # noqa: E731
            its = "/".join(str(i) for i in p["iterations"])
            lines.append(f"| {p['number']} | {p['method']} | {p['label']} | {p['n']} | {its} | {sd('psnr', '{:.2f}')} | "
                         f"{sd('wall_min', '{:.1f}')} | {p['params'] / 1e6:.2f}M | {'; '.join(p['sources'])} |")
        lines.append("")
    tmp = base + ".md.tmp"
    with open(tmp, "w") as fh:
        fh.write("\n".join(lines))
    os.replace(tmp, base + ".md")
    plot(scene, points, base + ".png")


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=sorted(REGISTRY), action="append", help="only these scenes (default: all)")
    args = ap.parse_args()
    for scene in args.scene or REGISTRY:
        write(scene, summarise(scene))
        print(f"wrote benchmarks/results/trade_summary/{scene}.md and .png")


if __name__ == "__main__":
    main()
