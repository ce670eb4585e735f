"""Write results/rule_table/rules_<commit>.md: every scene-relative rule (ctgs/train/config/rules.py, ctgs/train/config/schedule.py) with
its value at the paper's scale and at 200 px wide images, for the paper's recipe and the fast preset.

Usage: .venv/bin/python benchmarks/rule_table.py [--scene NAME=SCENE_DIR[@IMAGES] ...]

With --scene, also what each preset bounds on those scenes (rules.for_scene, as `ctgs train` resolves it): for the
content-aware method and for 2dgs under each preset, the initial points kept of the SfM points, the primitive cap,
the size budget, the iterations, and the baselines' densifications (their spacing in steps and how many the run
makes). Written to results/rule_table/presets_<scenes>_<commit>.md. Caps, not counts: what a run ends with is in its
record.
"""

from __future__ import annotations

import os
import sys
from dataclasses import replace

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

from ctgs.train.config import TrainConfig, load_config, schedule  # noqa: E402
from ctgs.train.config.keys import PRESETS, config_path  # noqa: E402
from ctgs.train.config.rules import ITERATION_KEYS, MIN_TEXTURE_CAP, for_scene, resolve, with_size_budget  # noqa: E402

SIZES = {"paper scale (1000x1000)": (1000, 1000), "200x150": (200, 150)}


def rule_table(cfg: TrainConfig, sizes: dict[str, tuple[int, int]], iterations: dict[str, int]) -> list[dict]:
    """Rows (setting, rule, value per named image size / run length) of the record (and of the presets' tests).

    sizes: {"label": (width, height)}; iterations: {"label": iterations}.
    """
    rows = []
    for key, rule in (("tau_tr_start", "x (HW / 1e6) ** tau_tr_pixel_exponent (0: none, texels are >= 2 px already)"),
                      ("tau_tr_end", "x (HW / 1e6) ** tau_tr_pixel_exponent (0: none, texels are >= 2 px already)"),
                      ("max_texture_res", f"x sqrt(HW / 1e6), next power of two, >= {MIN_TEXTURE_CAP}"),
                      ("lambda_texture", "x 1e6 / HW"),
                      ("max_primitives", "min(max_primitives, primitives_per_pixel x HW x coverage, max_params / "
                                         "(params per primitive + 3 x smallest texture)); 0 = no cap"),
                      ("error_views", "min(error_views, error_pixels / HW), at least 1, when error_pixels > 0; "
                                      "0 = every view")):
        vals = {label: getattr(resolve(cfg, w * h), key) for label, (w, h) in sizes.items()}
        unit = {"lambda_texture": "per texel", "max_primitives": "primitives", "error_views": "views"}.get(key, "texels")
        rows.append({"setting": key, "unit": unit,
                     "rule": rule, "paper": getattr(cfg, key), "values": vals})
    # the relative size budget: per training view (the budget is this times the number of training views)
    vals = {label: with_size_budget(replace(cfg, max_params=0), 3 * w * h).max_params for label, (w, h) in sizes.items()}
    rows.append({"setting": "max_params (from max_params_per_value)", "unit": "params per training view",
                 "rule": "max_params_per_value x 3 H W x training views, unless max_params is given; 0 = no budget",
                 "paper": cfg.max_params_per_value, "values": vals})
    for key in ITERATION_KEYS:
        vals = {label: schedule.at(replace(cfg, iterations=n), getattr(cfg, key)) for label, n in iterations.items()}
        rows.append({"setting": key, "unit": "iterations", "rule": "x iterations / 30000",
                     "paper": getattr(cfg, key), "values": vals})
    return rows


def preset_bounds(scene_dir: str, images: str) -> tuple[dict, list[dict]]:
    """(the scene's figures, one row per preset and method): what `ctgs train --preset P [--config 2dgs]` resolves
    for this scene's training views, as the trainer does (its pixels, observed values and view coverage)."""
    import numpy as np
    import torch

    from ctgs.scene.loader import load_scene
    from ctgs.train.loop.trainer import observed_values
    from ctgs.train.routines.kmin import view_coverage

    scene = load_scene(scene_dir, images=images, load_images=False)
    cams = [v.camera for v in scene.train]
    pixels = float(np.median([c.width * c.height for c in cams]))
    coverage = view_coverage(torch.from_numpy(np.asarray(scene.points, np.float32)), cams)
    values = observed_values(scene.train)
    info = {"views": len(cams), "size": f"{cams[0].width}x{cams[0].height}", "points": len(scene.points),
            "coverage": coverage}
    rows = []
    for preset in PRESETS:
        for method, path in (("content-aware", None), ("2dgs", config_path("2dgs"))):
            cfg = load_config(path, preset=preset)
            resolved, init_cap = for_scene(cfg, values, pixels, coverage)
            row = {"preset": preset, "method": method, "iterations": cfg.iterations,
                   "init": min(init_cap, len(scene.points)) if init_cap else len(scene.points),
                   "cap": resolved.max_primitives, "max_params": resolved.max_params}
            if method == "2dgs":
                every = schedule.at(cfg, cfg.densify_every * schedule.densify_stretch(cfg))
                window = schedule.at(cfg, cfg.densify_until) - schedule.at(cfg, cfg.densify_from)
                row.update(densify_every=every, densifications=int(window // every))
            rows.append(row)
    return info, rows


def fmt(v) -> str:
    if isinstance(v, float):
        if v.is_integer():
            return str(int(v))
        return f"{v:.3g}" if abs(v) < 1e-3 else f"{v:.1f}"
    return str(v)


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", action="append", default=[], metavar="NAME=SCENE_DIR[@IMAGES]",
                    help="also what each preset bounds on this scene (IMAGES: its image folder, default images)")
    args = ap.parse_args()
    if args.scene:
        print(scene_table(args.scene))
        return
    lines = ["# Scene-relative settings: rule -> value", "",
             "Written by `benchmarks/rule_table.py` from ctgs/train/config/rules.py and ctgs/train/config/schedule.py (no "
             "measurement: the rules themselves). Iteration counts are fractions of the run; pixel and texel "
             "settings follow the training image size H x W. At the paper's scale every rule is the identity.", ""]
    for title, cfg, its in (("The paper's recipe (`--config default`; `--preset paper` turns the pixel rules off)",
                             TrainConfig(), {"30k iterations": 30000, "3000 iterations": 3000}),
                            ("The `fast` preset", load_config(None, preset="fast"),
                             {"3000 iterations (fast)": 3000, "1000 iterations (preview)": 1000})):
        rows = rule_table(cfg, SIZES, its)
        cols = list(SIZES) + list(its)
        lines += [f"## {title}", "", "| setting | unit | rule | value as written | " + " | ".join(cols) + " |",
                  "| --- | --- | --- | --- | " + " | ".join("---" for _ in cols) + " |"]
        for r in rows:
            vals = [fmt(r["values"].get(c, "")) for c in cols]
            lines.append(f"| {r['setting']} | {r['unit']} | {r['rule']} | {fmt(r['paper'])} | " + " | ".join(vals) + " |")
        lines.append("")
    out = record.stem("rule_table", "rules") + ".md"
    with open(out, "w") as fh:
        fh.write("\n".join(lines))
    print(out)


def scene_table(specs: list[str]) -> str:
    lines = ["# What each preset bounds on real scenes", "",
             "Written by `benchmarks/rule_table.py --scene ...` from the scenes' cameras and SfM points and the presets "
             "as they resolve in `ctgs train` (ctgs/train/config/rules.py `for_scene`; no training). Initial points: "
             "the SfM points a run starts from (subsampled to the cap). Primitive cap: `primitives_per_pixel` "
             "(content-aware) or `baseline_primitives_per_pixel` (2dgs) x the median training view's pixels x the "
             "capture's view coverage (views' worth of scene: SfM points over the median a view sees), and a "
             "--max-params budget's cap; 0 = none. Size budget: `max_params_per_value` x the observed values. "
             "Densifications (2dgs): every `densify_every` paper iterations scaled to the run and spaced at least "
             "`densify_min_steps` steps apart, over the window densify_from..densify_until, at the preset's own "
             "length (a --time-budget run rescales the window with its plan and keeps the spacing floor).", ""]
    names = []
    for spec in specs:
        name, _, rest = spec.partition("=")
        scene_dir, _, images = rest.partition("@")
        info, rows = preset_bounds(scene_dir, images or "images")
        names.append(name)
        lines += [f"## {name}: {info['views']} training views at {info['size']} ({images or 'images'}), "
                  f"{info['points']:,} SfM points, view coverage {info['coverage']:.2f}", "",
                  "| preset | method | iterations | initial points | primitive cap | size budget (params) | "
                  "densify every (steps) | densifications |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for r in rows:
            dens = (f"{r['densify_every']:.0f} | {r['densifications']}" if "densify_every" in r else "- | -")
            lines.append(f"| {r['preset']} | {r['method']} | {r['iterations']} | {r['init']:,} | "
                         f"{r['cap']:,} | {r['max_params']:,} | {dens} |")
        lines.append("")
    out = record.stem("rule_table", "presets_" + "_".join(names)) + ".md"
    with open(out, "w") as fh:
        fh.write("\n".join(lines))
    return out


if __name__ == "__main__":
    main()
