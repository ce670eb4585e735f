"""The agreement table of the CUDA backend against the CPU backend, from a measuring run of its tests.

tests/render/test_cuda_backend.py appends every comparison's observed error to $CTGS_AGREEMENT_LOG (JSON
lines: test, kind, name, dtype, err, scale, tol). This script reads such a log and writes, per output and
per gradient input and dtype, the worst error observed over every test case (the renderer's test scenes
and the extremes sweep), the case where it occurred, the tolerance the test applies, and the tolerance
that the observed worst case times a margin gives (rounded up to 1, 2 or 5 x 10^k).

Errors as the test compares them: images max |cuda - cpu| / max(1, |cpu|) (absolute before commit aad8882:
the first H200 run); statistics absolute; gradients relative to the largest |CPU gradient| of that input in
that case; tile lists 0 (identical) or 1 (not); count: summed |difference| of per-primitive pixel counts;
preprocess: the kernels of kernels/cuda/dense.cu against their PyTorch definitions, relative as above.

    python benchmarks/cuda_agreement.py LOG.jsonl --machine machine.json -o benchmarks/results/cuda_agreement_X
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path

MARGIN = 10.0  # proposed tolerance = observed worst case x MARGIN, rounded up to 1/2/5 x 10^k


def round_up_125(x: float) -> float:
    """Smallest 1, 2 or 5 x 10^k that is >= x (x > 0)."""
    k = math.floor(math.log10(x))
    for m in (1, 2, 5, 10):
        v = m * 10.0 ** k
        if v >= x * (1 - 1e-12):
            return float(f"{v:.6g}")
    return float(f"{10.0 ** (k + 1):.6g}")


def proposed(worst: float, kind: str) -> float | None:
    """The tolerance the observed worst case gives, or None where the comparison is exact by design."""
    if kind in ("bins",) or (kind == "stats" and worst == 0.0):
        return None
    if worst == 0.0 or not math.isfinite(worst):
        return None
    return round_up_125(worst * MARGIN)


def summarise(records: list[dict]) -> list[dict]:
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        groups[(r["kind"], r["name"], r["dtype"])].append(r)
    order = {"bins": 0, "image": 1, "stats": 2, "grad": 3}
    rows = []
    for (kind, name, dtype), rs in sorted(groups.items(), key=lambda kv: (kv[0][2], order.get(kv[0][0], 9),
                                                                          kv[0][1])):
        worst = max(rs, key=lambda r: (r["err"] if not math.isnan(r["err"]) else math.inf))
        tols = sorted({r["tol"] for r in rs})
        rows.append({"kind": kind, "name": name, "dtype": dtype, "cases": len(rs), "worst": worst["err"],
                     "worst_case": worst["test"].split("::")[-1], "tolerance": tols[0] if len(tols) == 1 else tols,
                     "failed_cases": sum(1 for r in rs if not (r["err"] <= r["tol"])),
                     "proposed": proposed(worst["err"], kind)})
    return rows


def to_markdown(rows: list[dict], machine: dict, log_name: str, note: str = "") -> str:
    lines = ["# CUDA backend vs CPU backend: observed worst errors", ""]
    if machine:
        lines += [f"Machine: {machine.get('gpu', '?')} (driver {machine.get('driver', '?')}), torch "
                  f"{machine.get('torch', '?')}, CUDA {machine.get('cuda', '?')}, Python {machine.get('python', '?')}; "
                  f"command: `{machine.get('command', '?')}`; commit {machine.get('commit', '?')}.", ""]
    if note:
        lines += [note, ""]
    lines += [f"From `{log_name}` (tests/render/test_cuda_backend.py with CTGS_AGREEMENT_LOG). Errors as the test "
              "compares them: images max |cuda - cpu| / max(1, |cpu|) (absolute in the first H200 run, before commit "
              "aad8882), statistics absolute, gradients relative to the largest |CPU gradient| of that input in that "
              "case, tile lists 0 = identical, count = summed |difference| of per-primitive pixel counts, preprocess "
              "= the kernels of kernels/cuda/dense.cu against their PyTorch definitions (relative as images). "
              f"'from observed' = worst x {MARGIN:g}, rounded up to 1/2/5 x 10^k.", "",
              "| dtype | kind | output / input | cases | worst observed | in case | tolerance in the test | "
              "cases over it | from observed |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        tol = r["tolerance"]
        tol_s = ", ".join(f"{t:.3g}" for t in tol) if isinstance(tol, list) else f"{tol:.3g}"
        prop = "exact" if r["proposed"] is None and r["worst"] == 0 else (
            "-" if r["proposed"] is None else f"{r['proposed']:.3g}")
        lines.append(f"| {r['dtype']} | {r['kind']} | {r['name']} | {r['cases']} | {r['worst']:.3g} | "
                     f"`{r['worst_case']}` | {tol_s} | {r['failed_cases']} | {prop} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--machine", type=Path, help="JSON with gpu, driver, torch, cuda, python, command, commit")
    ap.add_argument("-o", "--output", type=Path, required=True, help="output path without suffix (.md and .json)")
    ap.add_argument("--note", default="", help="a paragraph for the top of the table")
    args = ap.parse_args()
    records = [json.loads(line) for line in args.log.read_text().splitlines() if line.strip()]
    machine = json.loads(args.machine.read_text()) if args.machine and args.machine.is_file() else {}
    rows = summarise(records)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix(".json").write_text(json.dumps({"machine": machine, "rows": rows}, indent=1) + "\n")
    md = to_markdown(rows, machine, args.log.name, args.note)
    args.output.with_suffix(".md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
