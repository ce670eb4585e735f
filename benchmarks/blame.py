"""Which primitives cost a test view the most? Leave-one-out over the primitives that cover it.

A test mean over four views (herzjesu25) or three (the demo) can move by several dB because one view goes
wrong. benchmarks/per_view.py shows *which view*; this shows *which primitives*: for one test view it takes
the K primitives with the largest blending weight in that view (the renderer's per-primitive `contrib`,
in pixels) and re-renders the view with each of them alone removed (opacity 0). A primitive whose removal
raises PSNR is one the training views constrained badly. For each it reports what the training views saw
of it: how many training frusta hold its centre, its summed weight over all training views, the training
view where it weighs most, and how close it sits to a training camera (distance to the nearest training
camera centre / that camera's median SfM-point depth). It also says how much of the view no primitive covers
(accumulated opacity < 0.9: the black background shows there) and what share of the view's squared error
sits in those pixels: the other way a view far from the training cameras loses.

Read-only diagnosis of a finished run: nothing here feeds a setting (test views are for measuring).

Usage: .venv/bin/python benchmarks/blame.py RUN_DIR [--view NAME] [--candidates 40] [--top 8] --out NAME
(default view: the run's worst test view by PSNR). Writes benchmarks/results/blame_NAME.{md,json}.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from ctgs.metrics.report import OPEN_ALPHA  # noqa: E402  rendered alpha below it: the background shows


def _depth(cam, pts):
    return (pts @ cam.R.float().T + cam.t.float())[:, 2]


def _inside(cam, pts):
    pc = pts @ cam.R.float().T + cam.t.float()
    z = pc[:, 2]
    u = cam.fx * pc[:, 0] / z.clamp_min(1e-9) + cam.cx
    v = cam.fy * pc[:, 1] / z.clamp_min(1e-9) + cam.cy
    return (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)


def blame(run_dir: str, view: str | None, candidates: int) -> dict:
    import torch

    from ctgs.io.run_model import load_run
    from ctgs.metrics.psnr import psnr
    from ctgs.render.api import render
    from ctgs.scene import load_scene

    run = load_run(run_dir)
    model = run.model
    scene = load_scene(run.scene_dir, images=run.images, holdout=run.holdout)
    inp = model.render_inputs()
    inp = type(inp)(**{k: (v.detach() if torch.is_tensor(v) else v) for k, v in vars(inp).items()})
    deg = model.sh_degree

    def rgb(inputs, cam):
        return render(inputs, cam, sh_degree=deg).rgb.clamp(0, 1)

    def contrib(cam):
        return render(inp, cam, sh_degree=deg, error_image=torch.zeros(cam.height, cam.width)).stats.contrib.float()

    with torch.no_grad():
        scores = {v.name: psnr(rgb(inp, v.camera), torch.from_numpy(v.image)) for v in scene.test}
        name = view or min(scores, key=scores.get)
        if name not in scores:
            raise SystemExit(f"{run_dir}: no test view named {name} (test views: {', '.join(scores)})")
        tv = next(v for v in scene.test if v.name == name)
        gt = torch.from_numpy(tv.image)
        full = render(inp, tv.camera, sh_degree=deg)
        se = ((full.rgb.clamp(0, 1) - gt) ** 2).mean(-1)
        open_px = full.alpha < OPEN_ALPHA  # where the background shows: no primitive covers the pixel
        coverage = {"alpha_threshold": OPEN_ALPHA, "open_fraction": float(open_px.float().mean()),
                    "open_error_share": float(se[open_px].sum() / se.sum().clamp_min(1e-20)),
                    "psnr_covered_only": float(-10 * torch.log10(se[~open_px].mean())) if bool((~open_px).any()) else None}
        c_test = contrib(tv.camera)
        c_train = torch.stack([contrib(v.camera) for v in scene.train])  # [V, N]
        mu = model.means.detach().float()
        seen = torch.stack([_inside(v.camera, mu) for v in scene.train]).sum(0)
        pts = torch.from_numpy(scene.points).float()
        med = torch.stack([(lambda z: z[z > 0].median())(_depth(v.camera, pts)) for v in scene.train])
        centres = torch.stack([v.camera.center.float() for v in scene.train])
        rel = torch.stack([(centres[j] - mu).norm(dim=1) / med[j] for j in range(len(centres))]).min(0).values
        order = torch.argsort(c_test, descending=True)[:candidates]
        rows = []
        for i in order.tolist():
            op = inp.opacities.clone()
            op[i] = 0.0
            gain = psnr(rgb(dataclasses.replace(inp, opacities=op), tv.camera), gt) - scores[name]
            rows.append({
                "primitive": i, "gain_db": gain, "contrib_px": float(c_test[i]),
                "opacity": float(inp.opacities[i]), "max_scale": float(model.scales[i].max()),
                "tex_res": [int(x) for x in model.tex_res[i]],
                "dist_to_test_camera": float((tv.camera.center.float() - mu[i]).norm()),
                "train_frusta_holding_centre": int(seen[i]), "train_contrib_px": float(c_train[:, i].sum()),
                "train_view_most": scene.train[int(c_train[:, i].argmax())].name,
                "train_contrib_px_there": float(c_train[:, i].max()),
                "near_train_camera_rel": float(rel[i]),
            })
        rows.sort(key=lambda r: -r["gain_db"])
        all_removed = torch.zeros_like(inp.opacities, dtype=torch.bool)
        for r in rows:
            if r["gain_db"] > 0.05:
                all_removed[r["primitive"]] = True
        op = torch.where(all_removed, torch.zeros_like(inp.opacities), inp.opacities)
        together = psnr(rgb(dataclasses.replace(inp, opacities=op), tv.camera), gt) - scores[name]
    qs = torch.tensor([0.001, 0.01, 0.05, 0.5])
    return {"run": os.path.abspath(run_dir), "view": name, "view_psnr": scores[name], "test_psnr": scores,
            "coverage": coverage,
            "primitives": model.num_primitives, "candidates": candidates, "rows": rows,
            "removed_together": {"count": int(all_removed.sum()), "gain_db": together},
            "near_train_camera_rel_quantiles": dict(zip(["0.1%", "1%", "5%", "50%"], rel.quantile(qs).tolist()))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--view", default=None, help="test view name (default: the worst by PSNR)")
    ap.add_argument("--candidates", type=int, default=40, help="primitives tried: the largest weights in the view")
    ap.add_argument("--top", type=int, default=8, help="rows in the table")
    ap.add_argument("--out", required=True)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    t0 = time.time()
    res = blame(args.run, args.view, args.candidates)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    res.update({"command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit,
                "machine": f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)",
                "seconds": time.time() - t0})
    out = os.path.join(ROOT, "benchmarks", "results", f"blame_{args.out}")
    with open(out + ".json", "w") as fh:
        json.dump(res, fh, indent=1)
    views = " / ".join(f"{k} {v:.2f}" for k, v in res["test_psnr"].items())
    q = res["near_train_camera_rel_quantiles"]
    lines = [f"# Which primitives cost test view {res['view']} the most ({res['machine']})", "",
             f"Command: `benchmarks/blame.py {' '.join(sys.argv[1:])}` on {res['date']}, commit {commit}. "
             f"Run: `{res['run']}` ({res['primitives']} primitives). Test PSNR per view: {views} dB. "
             f"Each row: the view re-rendered with that primitive alone removed (opacity 0), among the "
             f"{res['candidates']} with the largest weight in the view. A diagnosis of a finished run (no setting "
             "is chosen from it).", "",
             "| primitive | PSNR gain if removed | weight in this view (px) | opacity | max scale | texels | "
             "distance to this camera | training frusta holding its centre | weight over all training views (px) | "
             "training view it weighs most in (px) | distance to nearest training camera / its median SfM depth |",
             "| ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | --- | ---: |"]
    for r in res["rows"][:args.top]:
        lines.append(f"| {r['primitive']} | {r['gain_db']:+.2f} dB | {r['contrib_px']:.0f} | {r['opacity']:.2f} | "
                     f"{r['max_scale']:.3f} | {r['tex_res'][0]}x{r['tex_res'][1]} | {r['dist_to_test_camera']:.2f} | "
                     f"{r['train_frusta_holding_centre']} | {r['train_contrib_px']:.0f} | {r['train_view_most']} "
                     f"({r['train_contrib_px_there']:.0f}) | {r['near_train_camera_rel']:.3f} |")
    cv = res["coverage"]
    pc = cv["psnr_covered_only"]
    lines += ["", f"Pixels where the background shows (accumulated opacity < {cv['alpha_threshold']}): "
              f"{100 * cv['open_fraction']:.1f}% of the view, {100 * cv['open_error_share']:.0f}% of its squared error; "
              f"PSNR over the other pixels {'-' if pc is None else f'{pc:.2f}'} dB (whole view {res['view_psnr']:.2f})."]
    rt = res["removed_together"]
    lines += ["", f"Removing every primitive with a gain above 0.05 dB together ({rt['count']}): "
              f"{rt['gain_db']:+.2f} dB on {res['view']}. Distance to the nearest training camera / its median "
              f"SfM depth over all primitives: 0.1% {q['0.1%']:.3f}, 1% {q['1%']:.3f}, 5% {q['5%']:.3f}, "
              f"median {q['50%']:.3f}.", ""]
    with open(out + ".md", "w") as fh:
        fh.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
