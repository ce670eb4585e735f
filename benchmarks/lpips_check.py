"""ctgs' LPIPS against the LPIPS authors' published distances (the check tests/eval/test_lpips_reference.py makes),
written as a record: results/lpips_check/reference_<commit>.md + .json.

Usage: .venv/bin/python benchmarks/lpips_check.py
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)
DATA = os.path.join(ROOT, "tests", "eval", "lpips_reference")
PUBLISHED = {"ex_p0.png": 0.569, "ex_p1.png": 0.422}  # the LPIPS README (net='vgg', v0.1, inputs in [-1, 1])


def main() -> None:
    import argparse

    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    import torch

    from ctgs.io.images import read_image
    from ctgs.metrics import lpips as lp

    net, status = lp.load_lpips()
    if net is None:
        sys.exit(f"error: LPIPS weights unavailable ({status.detail}); run `make lpips-weights`")

    def image(name):  # [1, 3, 64, 64] in [0, 1]
        return torch.as_tensor(read_image(os.path.join(DATA, name))[..., :3]).permute(2, 0, 1)[None].float()

    ref = image("ex_ref.png")
    rows = [{"image": n, "published": p, "ctgs": float(net(ref, image(n), normalize=True)[0])} for n, p in PUBLISHED.items()]
    out = record.stem("lpips_check", "reference")
    rec = {"command": "python benchmarks/lpips_check.py", "date": time.strftime("%Y-%m-%d %H:%M"),
           "machine": {"host": platform.node(), "machine": platform.machine(), "cpus": os.cpu_count()},
           "weights": status.detail, "rows": rows}
    json.dump(rec, open(out + ".json", "w"), indent=1)
    lines = [f"# LPIPS vs the authors' published distances ({rec['machine']['host']}, {rec['date']})", "",
             f"Command: `{rec['command']}`. Images: tests/eval/lpips_reference (the LPIPS repository's examples). "
             f"Weights: {status.detail}.", "", "| pair | published | ctgs | rounds to published |", "| --- | --- | --- | --- |"]
    lines += [f"| ex_ref vs {r['image']} | {r['published']:.3f} | {r['ctgs']:.4f} | {round(r['ctgs'], 3) == r['published']} |"
              for r in rows]
    open(out + ".md", "w").write("\n".join(lines) + "\n")
    print(out + ".md")


if __name__ == "__main__":
    main()
