"""What `texture_trim` takes out of finished runs, and what it costs (issue 10, item 5).

For each finished content-aware run: crop its textures to the texels that hold something (ctgs.train.texels.trim
at each --eps: every texel whose activated offset is below eps in all channels goes, symmetric crops only, and
textures with no such texel are dropped), write the trimmed model as a copy of the run, and evaluate both with
`ctgs eval` (same code, same machine, one after the other): test PSNR / SSIM / LPIPS, texels, params, params
per observed value (the run's training pixels x 3, from its train_summary.json), render FPS. Also checks the
bound the trim promises: on every test view, no rendered value (float, before clamping to [0, 1]) moves by eps
or more.

The runs were trained without the trim; `ctgs train` with texture_trim > 0 applies the same function after
its last iteration (before its final evaluation), so these rows are what such a run reports.

Usage: .venv/bin/python benchmarks/trim.py --out NAME [--eps 0.004 ...] LABEL=RUN_DIR [LABEL=RUN_DIR ...]
Writes benchmarks/results/trim_NAME.md and .json; trimmed copies go to --work (default /tmp/ctgs_trim).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

COPY = ("config.toml", "train_summary.json", "log.jsonl")


def evaluate(run: str, out: str) -> dict:
    subprocess.run([sys.executable, "-m", "ctgs", "eval", run, "-o", out], check=True, cwd=ROOT,
                   capture_output=True)
    with open(os.path.join(out, "metrics.json")) as fh:
        return json.load(fh)


def allocation(model, scene_dir: str) -> dict | None:
    """The demo scene's allocation ratios (ctgs.train.allocation; None for other scenes)."""
    if not os.path.exists(os.path.join(scene_dir, "demo_meta.json")):
        return None
    from ctgs.scene.demo import load_demo_meta
    from ctgs.train.allocation import allocation_measures

    return allocation_measures(model, load_demo_meta(scene_dir))["ratios"]


def trimmed_copy(run: str, dest: str, eps: float) -> tuple[dict, float, dict | None, dict | None]:
    """Write RUN's model trimmed at eps into dest (a run folder); returns (trim stats, max |render change|,
    allocation ratios before and after on the demo scene)."""
    import torch

    from ctgs.io import atomic
    from ctgs.io.run_model import MODEL_FILE, load_run
    from ctgs.render import render
    from ctgs.scene.loader import load_scene
    from ctgs.train import texels

    os.makedirs(dest, exist_ok=True)
    for name in COPY:
        if os.path.exists(os.path.join(run, name)):
            shutil.copy(os.path.join(run, name), dest)
    ckpt = torch.load(os.path.join(run, MODEL_FILE), map_location="cpu", weights_only=True)
    r = load_run(run)
    model = r.model
    scene = load_scene(r.scene_dir, images=r.images, holdout=r.holdout)
    with torch.no_grad():
        before = [render(model.render_inputs(), v.camera, backend="cpu", sh_degree=model.sh_degree) for v in scene.test]
    alloc_before = allocation(model, r.scene_dir)
    stats = texels.trim(model, None, eps)
    alloc_after = allocation(model, r.scene_dir)
    with torch.no_grad():
        after = [render(model.render_inputs(), v.camera, backend="cpu", sh_degree=model.sh_degree) for v in scene.test]
    change = max(float((a.rgb - b.rgb).abs().max()) for a, b in zip(after, before))
    ckpt["model"] = model.state_dict()
    atomic.torch_save(ckpt, os.path.join(dest, MODEL_FILE))
    return stats, change, alloc_before, alloc_after


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--eps", type=float, nargs="+", default=[0.004])
    ap.add_argument("--work", default="/tmp/ctgs_trim")
    ap.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rows = []
    for spec in args.runs:
        label, run = spec.rsplit("=", 1)
        with open(os.path.join(run, "train_summary.json")) as fh:
            summary = json.load(fh)
        values = summary["observed_values"]
        base = evaluate(run, os.path.join(args.work, label, "eval_untrimmed"))
        base_row = len(rows)
        rows.append({"label": label, "run": run, "eps": 0.0, "observed_values": values, "metrics": base,
                     "stats": None, "max_change": 0.0, "allocation": None})
        for eps in args.eps:
            dest = os.path.join(args.work, label, f"trim_{eps:g}")
            stats, change, alloc_before, alloc_after = trimmed_copy(run, dest, eps)
            if alloc_before is not None:
                rows[base_row]["allocation"] = alloc_before
            m = evaluate(dest, os.path.join(dest, "eval"))
            rows.append({"label": label, "run": run, "eps": eps, "observed_values": values, "metrics": m,
                         "stats": stats, "max_change": change, "allocation": alloc_after})
            print(label, eps, stats, f"max change {change:.5f}", f"PSNR {base['psnr']:.3f} -> {m['psnr']:.3f}",
                  flush=True)
    import torch

    cmd = "benchmarks/trim.py " + " ".join(sys.argv[1:])
    lines = [f"# Texture trim on finished runs ({args.out})", "",
             f"Written by `{cmd}` on {time.strftime('%Y-%m-%dT%H:%M:%S%z')}. Machine: {platform.node()} "
             f"({platform.machine()}, {os.cpu_count()} cpus), torch {torch.__version__}; load average "
             f"{load0:.2f} at start, {os.getloadavg()[0]:.2f} at the end (FPS: one eval after the other on a shared "
             "machine, compare loosely).", "",
             "eps 0 = the run as trained; each eps row is the same model with `texels.trim(model, eps)` applied "
             "(what `ctgs train --set texture_trim=eps` does after its last iteration). Metrics from `ctgs eval` "
             "(test views, CPU backend). max change = the largest |rendered value after - before| over every "
             "pixel and channel of the test views (the trim promises < eps).", "",
             "| run | eps | test PSNR | SSIM | LPIPS | primitives | textured | texels | params | params / value | "
             "MB | FPS | max change |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        m = r["metrics"]
        lp = "n/a" if m["lpips"] is None else f"{m['lpips']:.3f}"
        textured = m["points"] - r["stats"]["textures_dropped"] if r["stats"] else None
        lines.append(f"| {r['label']} | {r['eps']:g} | {m['psnr']:.2f} | {m['ssim']:.3f} | {lp} | {m['points']} | "
                     f"{'-' if textured is None else textured} | {m['texels']} | {m['params']} | "
                     f"{m['params'] / r['observed_values']:.2f} | {m['bytes_on_disk'] / 1e6:.2f} | {m['fps']:.1f} | "
                     f"{r['max_change']:.4f} |")
    alloc = [r for r in rows if r.get("allocation")]
    if alloc:
        lines += ["", "On the demo scene, the allocation ratios of ctgs.train.allocation (what `make bench-claims` "
                  "checks; median over primitives with a texture):", "",
                  "| run | eps | texel size flat : photo | params per area photo : flat | texels per area photo : flat |",
                  "| --- | ---: | ---: | ---: | ---: |"]
        for r in alloc:
            a = r["allocation"]
            lines.append(f"| {r['label']} | {r['eps']:g} | {a['texel_size_prim_flat_over_photo']:.2f} | "
                         f"{a['params_per_area_photo_over_flat']:.2f} | {a['texels_per_area_photo_over_flat']:.2f} |")
    lines += ["", "Runs: " + ", ".join(f"{r['label']} = `{r['run']}`" for r in rows if r["eps"] == 0.0), ""]
    out = os.path.join(ROOT, "benchmarks", "results", f"trim_{args.out}")
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines))
    with open(out + ".json", "w") as fh:
        json.dump({"command": cmd, "rows": [{k: v for k, v in r.items() if k != "metrics"} |
                                            {"metrics": {k: r["metrics"][k] for k in
                                                         ("psnr", "ssim", "lpips", "points", "texels", "params",
                                                          "bytes_on_disk", "fps")}} for r in rows]}, fh, indent=1)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
