"""Eval artifacts: metrics.json (schema in docs/metrics.md), per-image CSV, strips, the paper's table."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass

import numpy as np

from ctgs.io import atomic

METRICS_SCHEMA = "ctgs-metrics"
METRICS_VERSION = 1
# The error panel of a strip shows |gt - render| per channel times this gain (clipped to 1), so small
# errors stay visible.
ERROR_GAIN = 4.0
# Columns of the paper's per-scene table (Tab. per-scene), in order: header, metrics.json key, format.
TABLE_COLUMNS = [
    ("SSIM", "ssim", "{:.3f}"), ("PSNR", "psnr", "{:.2f}"), ("LPIPS", "lpips", "{:.3f}"),
    ("Points", "points", "count"), ("Texels", "texels", "count"), ("Params", "params", "count"),
    ("FPS", "fps", "{:.0f}"), ("Mem", "model_memory_bytes", "bytes"),
    ("Texels/Primitive", "texels_per_primitive", "{:.1f}"),
]


@dataclass
class ImageMetrics:
    name: str
    psnr: float  # dB
    ssim: float
    lpips: float | None  # None when LPIPS is unavailable
    render_ms: float  # render only, synchronised


def _finite(x):
    """JSON has no NaN/inf: non-finite numbers become null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x


def write_metrics_json(path: str, metrics: dict) -> None:
    atomic.write_json(path, _finite(metrics))


def write_per_image_csv(path: str, rows: list[ImageMetrics]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["name", "psnr", "ssim", "lpips", "render_ms"])
    for r in rows:
        d = asdict(r)
        w.writerow([d["name"], f"{r.psnr:.4f}", f"{r.ssim:.5f}", "" if r.lpips is None else f"{r.lpips:.5f}",
                    f"{r.render_ms:.3f}"])
    atomic.write_text(path, buf.getvalue())


def strip(gt: np.ndarray, render: np.ndarray) -> np.ndarray:
    """[H, 3W, 3] side-by-side ground truth | render | ERROR_GAIN * |gt - render|, values in [0, 1]."""
    err = np.clip(ERROR_GAIN * np.abs(gt - render), 0.0, 1.0)
    return np.concatenate([gt, np.clip(render, 0.0, 1.0), err], axis=1).astype(np.float32)


# ---- table ---------------------------------------------------------------------------------------
def _fmt(value, how: str) -> str:
    if value is None:
        return "n/a"
    if how == "count":
        return f"{value / 1e6:.1f}M" if value >= 1e6 else f"{value / 1e3:.0f}K" if value >= 1e3 else f"{value:.0f}"
    if how == "bytes":
        return f"{value / 1e6:.0f}MB" if value >= 1e6 else f"{value / 1e3:.0f}KB"
    return how.format(value)


def _mean(values: list):
    vals = [v for v in values if v is not None]
    # A dataset mean over some scenes only would be misleading: n/a unless every scene has the value.
    return sum(vals) / len(vals) if vals and len(vals) == len(values) else None


def build_table(metrics_list: list[dict]) -> tuple[str, str]:
    """(markdown, csv) per scene grouped by dataset, each group followed by its mean row."""
    groups: dict[str, list[dict]] = {}
    for m in metrics_list:
        groups.setdefault(m.get("dataset") or "unknown", []).append(m)
    header = ["Dataset", "Scene"] + [c[0] for c in TABLE_COLUMNS]
    md = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * len(TABLE_COLUMNS)) + "|"]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    for dataset in sorted(groups):
        rows = sorted(groups[dataset], key=lambda m: m.get("scene", ""))
        for m in rows:
            label = m.get("scene", "?")
            if m.get("compressed") or m.get("codebook_size"):
                label += f" (compressed, K={m['codebook_size']})" if m.get("codebook_size") else " (compressed)"
            md.append("| " + " | ".join([dataset, label] + [_fmt(m.get(k), f) for _, k, f in TABLE_COLUMNS]) + " |")
            w.writerow([dataset, label] + ["" if m.get(k) is None else m.get(k) for _, k, _ in TABLE_COLUMNS])
        means = {k: _mean([m.get(k) for m in rows]) for _, k, _ in TABLE_COLUMNS}
        md.append("| " + " | ".join([f"**{dataset}**", f"**mean ({len(rows)})**"] +
                                    [_fmt(means[k], f) for _, k, f in TABLE_COLUMNS]) + " |")
        w.writerow([dataset, "mean"] + ["" if means[k] is None else means[k] for _, k, _ in TABLE_COLUMNS])
    return "\n".join(md) + "\n", buf.getvalue()
