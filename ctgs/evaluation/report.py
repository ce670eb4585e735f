"""Eval artifacts: metrics.json (schema in docs/reference/metrics.md), per-image CSV, strips, the paper's table."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass

import numpy as np

from ctgs.io import atomic

METRICS_SCHEMA = "ctgs-metrics"
METRICS_VERSION = 1
# A pixel is open where the model's rendered alpha is below this: the background (the protocol's black) shows
# through, which against a bright sky costs a view much of its PSNR. `ctgs eval` reports the open share of every test
# view and the PSNR over the other pixels; the benchmarks' open-pixel figures use the same threshold.
OPEN_ALPHA = 0.9
# The error panel of a strip shows |gt - render| per channel times this gain (clipped to 1), so small
# errors stay visible.
ERROR_GAIN = 4.0
# Columns of the paper's per-scene table (Tab. per-scene), in order: header, metrics key, format.
# Mem is the model's storage as the paper counts it (4 bytes per parameter) for an uncompressed model, and
# the bytes of its files for a compressed one (`storage_bytes`); Disk is what loading reads in either case
# (model.pt of a run, or the model folder's files).
TABLE_COLUMNS = [
    ("SSIM", "ssim", "{:.3f}"), ("PSNR", "psnr", "{:.2f}"), ("LPIPS", "lpips", "{:.3f}"),
    ("Points", "points", "count"), ("Texels", "texels", "count"), ("Params", "params", "count"),
    ("FPS", "fps", "{:.0f}"), ("Mem", "storage_bytes", "bytes"), ("Disk", "bytes_on_disk", "bytes"),
    ("Texels/Primitive", "texels_per_primitive", "{:.1f}"), ("Train min", "train_minutes", "{:.1f}"),
]


@dataclass
class ImageMetrics:
    name: str
    psnr: float  # dB
    ssim: float
    lpips: float | None  # None when LPIPS is unavailable
    render_ms: float  # render only, synchronised
    open: float = float("nan")  # share of the pixels whose rendered alpha is below OPEN_ALPHA
    psnr_covered: float | None = None  # PSNR over the other pixels (None: every pixel open)
    # the largest share of the view's blending weight (sum of alpha T over its pixels) that one primitive whose
    # centre lies outside the view carries: a veil blended in front of the scene (docs/reference/renderer.md, Ordering)
    veil: float = float("nan")
    # exposure: the least-squares gain photo ~ gain x render, and PSNR after it (ctgs.metrics.psnr.gain_matched_psnr;
    # a diagnostic, not the protocol's PSNR: a new view's exposure is unknown to any method)
    gain: float = float("nan")
    psnr_gain: float = float("nan")


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
    w.writerow(["name", "psnr", "ssim", "lpips", "render_ms", "open", "psnr_covered", "veil", "gain", "psnr_gain"])
    for r in rows:
        d = asdict(r)
        w.writerow([d["name"], f"{r.psnr:.4f}", f"{r.ssim:.5f}", "" if r.lpips is None else f"{r.lpips:.5f}",
                    f"{r.render_ms:.3f}", f"{r.open:.5f}", "" if r.psnr_covered is None else f"{r.psnr_covered:.4f}",
                    f"{r.veil:.5f}", f"{r.gain:.5f}", f"{r.psnr_gain:.4f}"])
    atomic.write_text(path, buf.getvalue())


def strip(gt: np.ndarray, render: np.ndarray, texels: np.ndarray | None = None) -> np.ndarray:
    """[H, 3W, 3] side-by-side ground truth | render | ERROR_GAIN * |gt - render|, values in [0, 1]; with `texels`
    (a textured model's texel-size map, ctgs.render.texel_map), [H, 4W, 3] with it on the right."""
    err = np.clip(ERROR_GAIN * np.abs(gt - render), 0.0, 1.0)
    panels = [gt, np.clip(render, 0.0, 1.0), err] + ([np.clip(texels, 0.0, 1.0)] if texels is not None else [])
    return np.concatenate(panels, axis=1).astype(np.float32)


# ---- table ---------------------------------------------------------------------------------------
def _fmt(value, how: str) -> str:
    if value is None:
        return "n/a"
    if how == "count":
        return f"{value / 1e6:.1f}M" if value >= 1e6 else f"{value / 1e3:.0f}K" if value >= 1e3 else f"{value:.0f}"
    if how == "bytes":  # three significant digits: a 1.1 MB compressed model must not read "1MB"
        for scale, unit in ((1e9, "GB"), (1e6, "MB"), (1e3, "KB")):
            if value >= scale:
                v = value / scale
                return f"{v:.{2 if v < 10 else 1 if v < 100 else 0}f}{unit}"
        return f"{value:.0f}B"
    return how.format(value)


def _mean(values: list):
    vals = [v for v in values if v is not None]
    # A dataset mean over some scenes only would be misleading: n/a unless every scene has the value.
    return sum(vals) / len(vals) if vals and len(vals) == len(values) else None


def variant(m: dict) -> str:
    """"" for an uncompressed model on its test views, else how it was compressed (e.g. "compressed balanced: scalar
    K=256") or exported ("exported .sog") and, evaluated on its training views (`ctgs eval --split train`), "training
    views"."""
    views = "training views" if m.get("split") == "train" else ""
    if m.get("exported_file"):  # `ctgs eval --model FILE`: what a Gaussian viewer gets from an exported file
        return (views + ", " if views else "") + f"exported {m['exported_file']}"
    if not (m.get("compressed") or m.get("codebook_size")):
        return views
    target = m.get("compression_target")
    enc = m.get("texture_encoding")
    mode = "" if enc in (None, "codebook") else enc  # "codebook": the first ctgs compress (vector, v1 folders)
    k = f"K={m['codebook_size']}" if m.get("codebook_size") else ""
    detail = " ".join(x for x in (mode, k) if x)
    return (views + ", " if views else "") + "compressed" + (f" {target}" if target else "") + (
        f": {detail}" if detail else "")


def storage_bytes(m: dict):
    """The Mem column: bytes on disk for a compressed model, 4 bytes x params (the paper's Mem) otherwise."""
    return m.get("bytes_on_disk") if variant(m) else m.get("model_memory_bytes")


def _resolution(m: dict) -> str:
    res = m.get("resolution")
    return f"{res[0]}x{res[1]}" if isinstance(res, (list, tuple)) and len(res) == 2 else (res or "n/a")


def paper_row(paper: dict) -> dict:
    """A manifest's `paper` table (ctgs.scene.manifests.PAPER_KEYS) as a metrics dict the table can print."""
    return {**paper, "storage_bytes": paper.get("mem_mb", 0) * 1e6 if "mem_mb" in paper else None,
            "resolution": paper.get("resolution")}


def build_table(metrics_list: list[dict], references: dict | None = None) -> tuple[str, str]:
    """(markdown, csv): scenes grouped by dataset and variant (uncompressed, or one compression setting),
    each group followed by its mean row, so a model is never averaged with its own compressed copy.

    references: {(dataset, scene): the paper's row (a manifest's `paper` table)}, printed under the scene's own
    uncompressed row and labelled with the size the paper used where the manifest gives it; never in a mean."""
    references = references or {}
    groups: dict[tuple[str, str], list[dict]] = {}
    for m in metrics_list:
        m = {**m, "storage_bytes": storage_bytes(m),
             "train_minutes": m["train_seconds"] / 60 if m.get("train_seconds") is not None else None}
        groups.setdefault((m.get("dataset") or "unknown", variant(m)), []).append(m)
    header = ["Dataset", "Scene", "Resolution"] + [c[0] for c in TABLE_COLUMNS]
    md = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * len(TABLE_COLUMNS)) + "|"]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    for dataset, var in sorted(groups):
        rows = sorted(groups[(dataset, var)], key=lambda m: m.get("scene", ""))
        suffix = f" ({var})" if var else ""
        for m in rows:
            label = m.get("scene", "?") + suffix
            lines = [(label, m)]
            ref = references.get((dataset, m.get("scene"))) if not var else None
            if ref:
                lines.append((f"{m.get('scene', '?')} (paper, all photos)", paper_row(ref)))
            for name, row in lines:
                res = _resolution(row)
                md.append("| " + " | ".join([dataset, name, res] + [_fmt(row.get(k), f) for _, k, f in TABLE_COLUMNS])
                          + " |")
                w.writerow([dataset, name, res] + ["" if row.get(k) is None else row.get(k)
                                                   for _, k, _ in TABLE_COLUMNS])
        means = {k: _mean([m.get(k) for m in rows]) for _, k, _ in TABLE_COLUMNS}
        md.append("| " + " | ".join([f"**{dataset}**", f"**mean{suffix} ({len(rows)})**", ""] +
                                    [_fmt(means[k], f) for _, k, f in TABLE_COLUMNS]) + " |")
        w.writerow([dataset, "mean" + suffix, ""] + ["" if means[k] is None else means[k] for _, k, _ in TABLE_COLUMNS])
    return "\n".join(md) + "\n", buf.getvalue()
