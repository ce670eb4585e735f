"""Write results/rule_table/rules_<commit>.md: every scene-relative rule (ctgs/train/config/rules.py, ctgs/train/config/schedule.py) with
its value at the paper's scale and at 200 px wide images, for the paper's recipe and the fast preset.

Usage: .venv/bin/python benchmarks/rule_table.py
"""

from __future__ import annotations

import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

from ctgs.train.config import TrainConfig, load_config  # noqa: E402
from ctgs.train.config.rules import rule_table  # noqa: E402

SIZES = {"paper scale (1000x1000)": (1000, 1000), "200x150": (200, 150)}


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
