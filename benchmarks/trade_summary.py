"""The speed/accuracy trade from every recorded run: each preset and the 2dgs baseline, over seeds where there are some.

Nothing is trained here. The script reads the JSON records other benchmarks wrote (trade.py, paired.py,
equal_time.py, scene_trade.py; the registry beside it, trade_summary.toml, names each file and which runs of it
make a point), and writes for each scene a table (mean, standard deviation and count over seeds; the commit of every
source) and a plot: test PSNR against wall-clock minutes and against parameters, content-aware in red and 2dgs in
blue, one panel column per image size, error bars one standard deviation over seeds where a point has several.

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
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")

# The points of each scene and image size, in order: benchmarks/trade_summary.toml (its header says how a source
# picks the runs of a record). Loaded as {scene: {size: [(method, label, [(record, selector), ...]), ...]}}, a
# selector picking runs of a record:
#   ("trade", scale, row name)      rows of a trade.py record
#   ("paired", run label)           runs of a paired.py record
#   ("equal_time", method)          the test-split run of an equal_time.py record (ca | 2dgs)
#   ("scene_trade", variant)        the rows (seeds) of a scene_trade.py record for one variant
REGISTRY_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "trade_summary.toml")
MIN_PSNR_SPAN = 2.0  # dB: the least PSNR range a panel shows (the seed spread of one herzjesu25 run is ~1 dB)


def _selector(source: dict) -> tuple:
    """A source of the registry file -> its selector (the record's folder names its kind)."""
    kind = source["record"].split("/", 1)[0]
    if kind == "trade":
        return kind, source["scale"], source["run"]
    if kind in ("paired", "equal_time", "scene_trade"):
        return kind, source["run"]
    raise ValueError(f"{REGISTRY_FILE}: {source['record']}: no tool of that name writes the records read here")


def load_registry(path: str = REGISTRY_FILE) -> dict:
    with open(path, "rb") as fh:
        data = tomllib.load(fh)
    return {scene: {size: [(p["method"], p["label"], [(src["record"], _selector(src)) for src in p["sources"]])
                           for p in points]
                    for size, points in sizes.items()}
            for scene, sizes in data.items()}


REGISTRY = load_registry()
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


def plot(columns: list[tuple[str, str]], points: dict[str, list[dict]], path: str) -> None:
    """One panel column per (scene, image size) of `columns`, from each scene's summarised points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    rows_of_key = max(len(REGISTRY[scene][size]) for scene, size in columns)
    key_h = 0.75 + 0.17 * rows_of_key  # inches: one line per point of the longest column
    fig, axes = plt.subplots(3, len(columns), figsize=(6.5 * len(columns), 9 + key_h), squeeze=False,
                             gridspec_kw={"height_ratios": [4.5, 4.5, key_h]})
    for col, (scene, size) in enumerate(columns):
        mine = [p for p in points[scene] if p["size"] == size]
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
            xs = [p[key] / (1e6 if key == "params" else 1) for p in mine]
            lo, hi = min(xs) / 1.4, max(xs) * 1.6  # room for the labels, also when every point has one x
            ax.set_xlim(lo, hi)
            ticks = [t for t in (0.3, 0.5, 1, 2, 3, 5, 10, 20, 30, 60) if lo <= t <= hi]
            ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_xlabel(xlabel.replace("parameters", "parameters, millions") if key == "params" else xlabel)
            ax.set_ylabel("test PSNR (dB)")
            ys = [(p["psnr"] - (p["psnr_sd"] or 0), p["psnr"] + (p["psnr_sd"] or 0)) for p in mine]
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
    plot([(scene, size) for size in REGISTRY[scene]], {scene: points}, base + ".png")


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=sorted(REGISTRY), action="append", help="only these scenes (default: all)")
    ap.add_argument("--figure", metavar="NAME=SCENE:SIZE,SCENE:SIZE", action="append", default=[],
                    help="also one plot of these panel columns side by side, NAME.png (e.g. the README's: "
                         "datasets=bonsai252:200x133,playroom225:158x104)")
    args = ap.parse_args()
    summaries = {}
    for scene in args.scene or REGISTRY:
        summaries[scene] = summarise(scene)
        write(scene, summaries[scene])
        print(f"wrote benchmarks/results/trade_summary/{scene}.md and .png")
    for spec in args.figure:
        name, _, cols = spec.partition("=")
        columns = [tuple(c.split(":", 1)) for c in cols.split(",")]
        for scene, size in columns:
            if scene not in REGISTRY or size not in REGISTRY[scene]:
                raise SystemExit(f"--figure {spec}: {scene} {size} is not in {REGISTRY_FILE}")
            summaries.setdefault(scene, summarise(scene))
        plot(columns, summaries, os.path.join(RESULTS, "trade_summary", f"{name}.png"))
        print(f"wrote benchmarks/results/trade_summary/{name}.png")


if __name__ == "__main__":
    main()
