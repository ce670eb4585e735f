"""`ctgs export --bake-textures --bake-max-splats N`: what a splat budget costs, planned per surfel against uniform.

A baked export holds a splat per texel; viewers and formats have limits (.spz readers refuse more than 10M points,
browsers run out of memory well before a paper-scale model's 46.6M texels). With a budget, ctgs.io.bake.plan_levels
bakes each surfel's texels as they are, box-averaged over 2^l x 2^l blocks, or folded into one colour, choosing per
surfel by the detail each option drops (flat textures first). This measures, on a trained run's test views (our
CPU renderer drawing the baked model directly, black background):
- the full bake, and budgets at fractions of its splat count;
- at the same splat counts, the uniform alternative: every surfel one or two levels coarser (the budget is then set
  to the uniform bake's count, so both hold the same number of splats);
- the fold (one splat per surfel, what --format ply gives without --bake-textures).
PSNR against the test photos and against the exact (textured) model's renders. Nothing is tuned here: plan_levels has
no constant to set.

Usage: .venv/bin/python benchmarks/bake_budget.py RUN_DIR --tag NAME [--fractions 0.5 0.25 0.125]
(writes benchmarks/results/bake_budget_<tag>.{json,md})
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from ctgs.io.bake import FOLD, LATTICE_MAX_TEXEL, _latticeable, bake_texels, plan_levels  # noqa: E402
from ctgs.io.run_model import load_run  # noqa: E402
from ctgs.metrics.psnr import psnr  # noqa: E402
from ctgs.render import render  # noqa: E402
from ctgs.scene import load_scene  # noqa: E402
from record import write_record  # noqa: E402 (benchmarks/record.py)


def render_views(model, views) -> list[torch.Tensor]:
    inputs = model.render_inputs()
    with torch.no_grad():
        return [render(inputs, v.camera.to("cpu", inputs.means.dtype), backend="cpu",
                       sh_degree=model.sh_degree).rgb.clamp(0, 1).float() for v in views]


def scores(model, views, exact: list[torch.Tensor] | None) -> dict:
    images = render_views(model, views)
    gt = [psnr(im, torch.as_tensor(v.image, dtype=torch.float32)) for im, v in zip(images, views)]
    out = {"psnr": sum(gt) / len(gt), "per_view": gt}
    if exact is not None:
        vs = [psnr(im, ex) for im, ex in zip(images, exact)]
        out["psnr_vs_exact"] = sum(vs) / len(vs)
    return out, images


def uniform_levels(model, level: int) -> torch.Tensor:
    """Every surfel at `level` where it can be (its grid tiles into 2^level blocks, texels not too wide), else at the
    finest level it can be, else folded."""
    out = torch.full((model.num_primitives,), FOLD)
    for lv in range(level + 1):
        out = torch.where(_latticeable(model, LATTICE_MAX_TEXEL, lv), lv, out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--tag", required=True)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.5, 0.25, 0.125])
    ap.add_argument("--uniform", type=int, nargs="+", default=[1, 2], help="uniform levels to compare against")
    ap.add_argument("--views", choices=["test", "train"], default="test",
                    help="train: choose between plan_levels' options on these, never on the test views")
    ap.add_argument("--area", choices=["pixels", "world"], default="pixels", help="plan_levels' texel area")
    a = ap.parse_args()
    torch.set_num_threads(1)
    run = load_run(a.run_dir)
    model = run.model
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    views = scene.test if a.views == "test" else scene.train
    rows = []
    exact_scores, exact = scores(model, views, None)
    rows.append({"what": "exact textured model", "splats": model.num_primitives, **exact_scores})
    t = time.perf_counter()
    full = bake_texels(model)
    full_s = time.perf_counter() - t
    n_full = full.num_primitives
    rows.append({"what": "full bake", "splats": n_full, "seconds": full_s, **scores(full, views, exact)[0]})
    del full
    budgets = [("planned", f"budget {f:g} x the full bake", int(f * n_full)) for f in a.fractions]
    for level in a.uniform:
        t = time.perf_counter()
        uni = bake_texels(model, levels=uniform_levels(model, level))
        uni_s = time.perf_counter() - t
        rows.append({"what": f"uniform: every surfel {2 ** level}x{2 ** level} texel blocks", "splats": uni.num_primitives,
                     "seconds": uni_s, **scores(uni, views, exact)[0]})
        budgets.append(("planned", f"planned at the uniform {2 ** level}x{2 ** level} bake's count", uni.num_primitives))
        del uni
    for _, label, budget in budgets:
        t = time.perf_counter()
        plan = plan_levels(model, budget, area=a.area)
        baked = bake_texels(model, levels=plan["level"])
        sec = time.perf_counter() - t
        share = {str(int(lv)): int((plan["level"] == lv).sum()) for lv in plan["level"].unique()}
        rows.append({"what": label, "budget": budget, "splats": baked.num_primitives, "seconds": sec,
                     "surfels_per_level": share, **scores(baked, views, exact)[0]})
        del baked
    fold = bake_texels(model, lattice_max_texel=0.0)
    rows.append({"what": "fold (one splat per surfel)", "splats": fold.num_primitives, **scores(fold, views, exact)[0]})
    commit = subprocess.run(["git", "-C", os.path.dirname(HERE), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    result = {"command": "benchmarks/bake_budget.py " + " ".join(sys.argv[1:]), "commit": commit,
              "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
              "machine": f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)",
              "run_dir": os.path.abspath(a.run_dir), "surfels": model.num_primitives, "texels": model.num_texels,
              "views": a.views, "area": a.area, "test_views": [v.name for v in views], "resolution": [views[0].camera.width, views[0].camera.height],
              "rows": rows}
    write_record(f"bake_budget_{a.tag}", result, markdown)


def markdown(r: dict) -> str:
    lines = [f"# Baking textures to a splat budget: {os.path.basename(os.path.dirname(r['run_dir']))}/"
             f"{os.path.basename(r['run_dir'])}", "",
             f"Written by `{r['command']}` on {r['date']}, {r['machine']}, commit {r['commit']}. The run's model: "
             f"{r['surfels']} surfels, {r['texels']} texels; {len(r['test_views'])} {r.get('views', 'test')} views at "
             f"{r['resolution'][0]}x{r['resolution'][1]}, drawn by our CPU renderer from the baked model itself "
             "(no file format's quantisation), black background. PSNR vs photo: mean over the views; vs exact: "
             f"against the textured model's own renders. plan_levels' texel area: {r.get('area', 'world')}.", "",
             "| bake | splats | PSNR vs photo | PSNR vs exact | per view | surfels per level (-1 = folded) | s |",
             "| --- | ---: | ---: | ---: | --- | --- | ---: |"]
    for row in r["rows"]:
        vs = f"{row['psnr_vs_exact']:.2f}" if "psnr_vs_exact" in row else "-"
        per = " / ".join(f"{p:.2f}" for p in row["per_view"])
        lv = ", ".join(f"{k}: {v}" for k, v in sorted(row.get("surfels_per_level", {}).items(), key=lambda kv: int(kv[0])))
        sec = f"{row['seconds']:.1f}" if "seconds" in row else "-"
        lines.append(f"| {row['what']} | {row['splats']} | {row['psnr']:.2f} | {vs} | {per} | {lv or '-'} | {sec} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
