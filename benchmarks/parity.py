"""The content-aware method against a 2DGS baseline at equal iterations: curves and the paper's relative figures.

Usage:
  .venv/bin/python benchmarks/parity.py --method RUN_A --baseline RUN_B --name bonsai252_images_4_paper_2dgs_seed0
      [--baseline-label "2DGS* (--max-params 11M)"] [--note TEXT]

Both runs are `ctgs train` folders trained with `--set test_lpips=true` (every periodic test evaluation then scores
PSNR, SSIM and LPIPS); finished or still running (the record covers the iterations both have reached, and says so).
The record (benchmarks/results/parity/NAME_<commit>.{md,json,png}) holds, at every common evaluation: test PSNR, SSIM,
LPIPS, primitives, texels, texels per primitive and parameters of both runs, their differences, and the paper's
relative figures beside the last common one, for --dataset mipnerf360 (the default; method - 2DGS* = -0.18 dB PSNR,
-0.019 LPIPS, 0.10x the primitives, 1.27x the parameters; bonsai: 30.8 texels per primitive) or deepblending (+0.51 dB,
-0.021, 0.15x, 0.93x; playroom: 147.7 texels per primitive). The method's parameters beside the paper's count the
texels as the authors' save crops them (texels_active), as the paper's do.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402

# The paper's trade against 2DGS* in its own pipeline, by dataset (method - 2DGS*; ratios method / 2DGS*), and the texels
# per primitive of one of the dataset's scenes (its per-scene table).
PAPERS = {
    "mipnerf360": {"dataset": "Mip-NeRF 360", "d_psnr": -0.18, "d_lpips": -0.019, "prim_ratio": 0.10,
                   "params_ratio": 1.27, "texels_per_prim": 30.8, "scene": "bonsai"},
    "deepblending": {"dataset": "Deep Blending", "d_psnr": 0.51, "d_lpips": -0.021, "prim_ratio": 0.15,
                     "params_ratio": 0.93, "texels_per_prim": 147.7, "scene": "playroom"},
}
PARAMS_PER_PRIM = {0: 14, 1: 23, 2: 38, 3: 59}  # 3 + 2 + 4 + 1 + 3 (SH coefficients) + texel exponent, by SH degree


def read_run(run: str) -> dict:
    """{"evals": {it: test record}, "steps": {it: step record}, "summary": dict | None, "config": dict}."""
    evals, steps = {}, {}
    with open(os.path.join(run, "log.jsonl")) as fh:
        for line in fh:
            d = json.loads(line)
            if d.get("type") == "test":
                evals[int(d["it"])] = d
            elif d.get("type") == "step":
                steps[int(d["it"])] = d
    summary = None
    if os.path.exists(os.path.join(run, "train_summary.json")):
        with open(os.path.join(run, "train_summary.json")) as fh:
            summary = json.load(fh)
    return {"evals": evals, "steps": steps, "summary": summary, "run": os.path.abspath(run)}


def size_at(run: dict, it: int) -> dict:
    """Primitives, texels and parameters at the step record nearest to `it` (at or before it)."""
    its = [k for k in run["steps"] if k <= it + 1]
    s = run["steps"][max(its)] if its else {}
    n, t = int(s.get("n", 0)), int(s.get("texels", 0))
    sh = int(s.get("sh_degree", 3))
    return {"primitives": n, "texels": t, "params": n * PARAMS_PER_PRIM.get(sh, 59) + 3 * t}


def rows(a: dict, b: dict) -> list[dict]:
    out = []
    for it in sorted(set(a["evals"]) & set(b["evals"])):
        ea, eb = a["evals"][it], b["evals"][it]
        sa, sb = size_at(a, it), size_at(b, it)
        # texels_active: inside the active extents, the authors' saved-model measure (ctgs.model.extent.active_texels);
        # logged with each evaluation since it existed, absent (None) in older logs
        sa["texels_active"] = ea.get("texels_active")
        for run, size in ((a, sa), (b, sb)):  # the end's evaluation scores the model as saved (after a final prune)
            summ = run["summary"]
            if summ and it == summ["iterations"]:
                size.update(primitives=summ["num_primitives"], texels=summ["num_texels"], params=summ["num_params"])
                if summ.get("num_texels_active") is not None and size is sa:
                    sa["texels_active"] = summ["num_texels_active"]
        if sa["texels_active"] is not None:  # the parameters as the authors' saved model holds them
            sa["params_saved"] = sa["params"] - 3 * sa["texels"] + 3 * sa["texels_active"]
        out.append({"it": it,  # (the periodic evaluations are scored after this step, before each multiple)
                    "a": {"psnr": ea["psnr"], "ssim": ea["ssim"], "lpips": ea.get("lpips"), **sa},
                    "b": {"psnr": eb["psnr"], "ssim": eb["ssim"], "lpips": eb.get("lpips"), **sb}})
    return out


def final(run: dict) -> dict | None:
    s = run["summary"]
    if not s:
        return None
    return {"it": s["iterations"], "psnr": s["final_test_psnr"], "ssim": s["final_test_ssim"],
            "primitives": s["num_primitives"], "texels": s["num_texels"], "params": s["num_params"],
            "train_seconds": s["train_seconds"]}


def plot(res: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = res["rows"]
    its = [x["it"] for x in r]
    for x in r:
        for side in ("a", "b"):
            v = x[side]
            v["texels_per_primitive"] = (v.get("texels_active") or v["texels"]) / max(v["primitives"], 1)
    fig, axes = plt.subplots(2, 3, figsize=(15, 7))
    axes = axes.flatten()
    panels = (("psnr", "test PSNR (dB)"), ("ssim", "test SSIM"), ("lpips", "test LPIPS (VGG)"),
              ("primitives", "primitives"), ("texels", "texels (allocated; dashed: as saved)"),
              ("texels_per_primitive", "texels per primitive (as saved)"))
    for ax, (key, label) in zip(axes, panels):
        ax.plot(its, [x["a"][key] for x in r], "o-", color="tab:red", label=res["method_label"], ms=3)
        if key == "texels" and any(x["a"].get("texels_active") is not None for x in r):
            ax.plot(its, [x["a"].get("texels_active") for x in r], "o--", color="tab:red", ms=2)
        if key not in ("texels", "texels_per_primitive"):
            ax.plot(its, [x["b"][key] for x in r], "s-", color="tab:blue", label=res["baseline_label"], ms=3)
        if key == "texels_per_primitive":
            paper = res["paper"]
            ax.axhline(paper["texels_per_prim"], color="grey", ls=":", label=f"paper ({paper['scene']})")
            ax.legend(fontsize=8)
        ax.set_xlabel("iteration")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(res["title"], fontsize=10)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def markdown(res: dict) -> str:
    r = res["rows"]
    last = r[-1] if r else None
    lines = [f"# {res['title']}", "",
             f"Written by benchmarks/parity.py on {res['date']} (commit {res['commit']}, {res['machine']}). "
             f"Command: `{res['command']}`", "",
             f"Method run: `{res['method_run']}`; baseline run: `{res['baseline_run']}`. {res['note']}".strip(), "",
             f"Common test evaluations: {len(r)}, up to iteration {last['it'] if last else '-'} "
             f"(method run {'finished' if res['final_a'] else 'still running'} at {res['reached_a']}, baseline "
             f"{'finished' if res['final_b'] else 'still running'} at {res['reached_b']}).", "",
             "| iteration | PSNR A | PSNR B | A - B | SSIM A | SSIM B | LPIPS A | LPIPS B | A - B | primitives A | "
             "primitives B | ratio | texels A | texels / primitive A | params A | params B |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
             "| ---: |"]
    for x in r:
        a, b = x["a"], x["b"]
        la = "-" if a["lpips"] is None else f"{a['lpips']:.3f}"
        lb = "-" if b["lpips"] is None else f"{b['lpips']:.3f}"
        dl = "-" if a["lpips"] is None or b["lpips"] is None else f"{a['lpips'] - b['lpips']:+.3f}"
        lines.append(f"| {x['it']} | {a['psnr']:.2f} | {b['psnr']:.2f} | {a['psnr'] - b['psnr']:+.2f} | {a['ssim']:.3f} | "
                     f"{b['ssim']:.3f} | {la} | {lb} | {dl} | {a['primitives']} | {b['primitives']} | "
                     f"{a['primitives'] / max(b['primitives'], 1):.2f}x | {a['texels']} | "
                     f"{a['texels'] / max(a['primitives'], 1):.1f} | {a['params'] / 1e6:.2f}M | {b['params'] / 1e6:.2f}M |")
    if last:
        a, b = last["a"], last["b"]
        paper = res["paper"]
        dl = None if a["lpips"] is None or b["lpips"] is None else a["lpips"] - b["lpips"]
        lines += ["", f"Beside the paper at the last common evaluation (iteration {last['it']}):", "",
                  "| figure | here | paper |", "| --- | ---: | ---: |",
                  f"| PSNR, method - 2DGS* | {a['psnr'] - b['psnr']:+.2f} dB | {paper['d_psnr']:+.2f} dB ({paper['dataset']}, 30k) |",
                  f"| LPIPS, method - 2DGS* | {'-' if dl is None else f'{dl:+.3f}'} | {paper['d_lpips']:+.3f} |",
                  f"| primitives, method / 2DGS* | {a['primitives'] / max(b['primitives'], 1):.2f}x | "
                  f"{paper['prim_ratio']:.2f}x |",
                  "| parameters, method (texels as saved) / 2DGS* | "
                  + ("-" if a.get("params_saved") is None else f"{a['params_saved'] / max(b['params'], 1):.2f}x")
                  + f" | {paper['params_ratio']:.2f}x ({paper['dataset']}) |",
                  f"| texels per primitive (method), as allocated | {a['texels'] / max(a['primitives'], 1):.1f} | - |",
                  "| texels per primitive (method), inside the active extents (the authors' saved models) | "
                  + ("-" if a.get("texels_active") is None else f"{a['texels_active'] / max(a['primitives'], 1):.1f}")
                  + f" | {paper['texels_per_prim']} ({paper['scene']}) |"]
    lines += ["", "![curves](" + os.path.basename(res["png"]) + ")", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", required=True, help="the content-aware run folder")
    ap.add_argument("--baseline", required=True, help="the 2DGS run folder")
    ap.add_argument("--name", required=True, help="record name: scene, resolution, variant")
    ap.add_argument("--method-label", default="content-aware (paper)")
    ap.add_argument("--baseline-label", default="2DGS*")
    ap.add_argument("--note", default="")
    ap.add_argument("--dataset", choices=sorted(PAPERS), default="mipnerf360", help="the paper's trade to set beside")
    args = ap.parse_args()
    a, b = read_run(args.method), read_run(args.baseline)
    stem = record.stem("parity", args.name)
    res = {"title": f"Equal iterations: {args.method_label} against {args.baseline_label} ({args.name})",
           "method_label": args.method_label, "baseline_label": args.baseline_label, "note": args.note,
           "method_run": record.portable(a["run"]), "baseline_run": record.portable(b["run"]),
           "rows": rows(a, b), "final_a": final(a), "final_b": final(b),
           "reached_a": max(a["steps"], default=0), "reached_b": max(b["steps"], default=0),
           "paper": PAPERS[args.dataset],
           "commit": record.commit(), "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
           "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "command": " ".join([os.path.relpath(sys.executable, record.ROOT)] + sys.argv), "png": stem + ".png"}
    plot(res, res["png"])
    res["png"] = record.portable(res["png"])
    record.write_record(stem, res, markdown)


if __name__ == "__main__":
    main()
