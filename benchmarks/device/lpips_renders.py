"""Score the test renders a device call brought back (renders_NAME.tar, written by lib.sh's finish_run) against this
machine's copy of the scene's photos: PSNR, SSIM and LPIPS (VGG v0.1, the eval's convention), mean over the views.

The device has no VGG weights, so its eval skips LPIPS; the renders are 8-bit PNGs, so PSNR and SSIM here differ
from the device's float ones in the second decimal at most (both are printed where the device's metrics.json is
given).

    .venv/bin/python benchmarks/device/lpips_renders.py renders_paper.tar --scene ../shared/data/bonsai252 \\
        [--images images] [--device-metrics pipe_paper/eval_metrics.json] [-o lpips_paper.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tarfile
import tempfile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from ctgs.io.images import IMAGE_EXTENSIONS, read_rgb  # noqa: E402
from ctgs.metrics.lpips import load_lpips, lpips_hwc  # noqa: E402
from ctgs.metrics.psnr import psnr  # noqa: E402
from ctgs.metrics.ssim import ssim  # noqa: E402


def ground_truth(images_dir: str, stem: str) -> str:
    for name in os.listdir(images_dir):
        base, ext = os.path.splitext(name)
        if base == stem and ext.lower() in IMAGE_EXTENSIONS:
            return os.path.join(images_dir, name)
    raise SystemExit(f"{images_dir}: no photo named {stem}.* for the render {stem}.png; pass the scene it trained on")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("renders", help="renders_NAME.tar or a renders/ folder")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--images", default="images")
    ap.add_argument("--device-metrics", help="the device's eval metrics.json, to print its figures beside these")
    ap.add_argument("-o", "--output", help="JSON of the means and per-view figures")
    args = ap.parse_args()

    import torch

    net, status = load_lpips(None, "cpu")
    if net is None:
        raise SystemExit(f"LPIPS {status.detail}; see docs/reference/metrics.md for the VGG weights' lookup")
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.renders
        if os.path.isfile(folder):
            with tarfile.open(folder) as tf:
                tf.extractall(tmp, filter="data")
            folder = os.path.join(tmp, "renders")
        rows = []
        for name in sorted(os.listdir(folder)):
            stem = os.path.splitext(name)[0]
            rgb = torch.as_tensor(read_rgb(os.path.join(folder, name)))
            gt = torch.as_tensor(read_rgb(ground_truth(os.path.join(args.scene, args.images), stem)))
            if gt.shape != rgb.shape:
                raise SystemExit(f"{name}: render {list(rgb.shape)} but photo {list(gt.shape)}; pass --images")
            with torch.no_grad():
                rows.append({"name": stem, "psnr": float(psnr(rgb, gt)), "ssim": float(ssim(rgb, gt)),
                             "lpips": lpips_hwc(net, rgb, gt)})
    mean = {k: sum(r[k] for r in rows) / len(rows) for k in ("psnr", "ssim", "lpips")}
    out = {"renders": os.path.basename(args.renders), "views": len(rows), **mean, "per_view": rows}
    print(f"{len(rows)} views: PSNR {mean['psnr']:.2f} dB (8-bit renders), SSIM {mean['ssim']:.3f}, "
          f"LPIPS {mean['lpips']:.3f}")
    if args.device_metrics:
        dev = json.load(open(args.device_metrics))
        print(f"device eval (float renders): PSNR {dev['psnr']:.2f} dB, SSIM {dev['ssim']:.3f}")
        out["device"] = {k: dev.get(k) for k in ("psnr", "ssim", "fps", "num_primitives")}
    if args.output:
        with open(args.output, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
