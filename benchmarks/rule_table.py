"""Write results/rule_table/rules_<commit>.md: every scene-relative rule (ctgs/train/config/rules.py, ctgs/train/config/schedule.py) with
its value at the paper's scale and at 200 px wide images, for the paper's recipe and the fast preset.

Usage: .venv/bin/python benchmarks/rule_table.py
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
from ctgs.train.config.rules import ITERATION_KEYS, MIN_TEXTURE_CAP, resolve, with_size_budget  # noqa: E402

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


def fmt(v) -> str:
    if isinstance(v, float):
        if v.is_integer():
            return str(int(v))
        return f"{v:.3g}" if abs(v) < 1e-3 else f"{v:.1f}"
    return str(v)


def main() -> None:
    import argparse

    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
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


if __name__ == "__main__":
    main()
