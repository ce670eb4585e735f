"""Renderer benchmark: C++ CPU backend vs the pure-PyTorch reference, forward and forward+backward.

Scenes: N textured surfels (textures res 8..64 per axis, random), random log-normal sizes, random
orientations, spread through the view frustum of a W x H camera. Times are wall-clock medians.

The dense reference evaluates every (pixel, primitive) pair, so its cost is linear in the number of pixel
rows and independent of the content: it is timed on a band of `--ref-rows` rows through the image centre
(a camera cropped to those rows: the same pairs the full image would evaluate there) and scaled by
H / rows. `--ref-full` times it on whole images instead (hours at 512x512/100k on 2 cores).

Writes benchmarks/results/bench_render/render_cpu_<commit>.json and .md (machine info inside).

    python benchmarks/bench_render.py                 # the full table (~15-30 min on 2 shared cores)
    python benchmarks/bench_render.py --quick         # 256x256/20k only
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import socket
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
import record  # noqa: E402 (benchmarks/record.py: where records go and how they are named)

from ctgs.render import Camera, SurfelInputs, render  # noqa: E402
from ctgs.ops.ext import load_cpu  # noqa: E402


def make_scene(n: int, width: int, height: int, seed: int = 0, dtype=torch.float32) -> tuple[SurfelInputs, Camera]:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    focal = 1.0 * width
    depth = 2.0 + 4.0 * r(n)  # world units in front of the camera
    x = (r(n) - 0.5) * 1.1 * depth * width / focal  # slightly wider than the view: partly off-screen
    y = (r(n) - 0.5) * 1.1 * depth * height / focal
    means = torch.stack([x, y, depth], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    # Log-normal sizes, the same world sizes at every resolution: sigma ~2 px at 256x256, depth 4.
    scales = 0.03 * torch.exp(0.6 * torch.randn(n, 2, generator=g, dtype=torch.float64))
    opacities = 0.1 + 0.85 * r(n)
    sh = torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * 0.2
    res = torch.randint(8, 65, (n, 2), generator=g, dtype=torch.int32)
    sizes = res[:, 0].long() * res[:, 1].long()
    offset = torch.cumsum(sizes, 0) - sizes
    textures = torch.rand(int(sizes.sum()), 3, generator=g, dtype=torch.float32) - 0.5
    texel = (6.0 * scales / res.to(torch.float64)).max(1).values  # the grid covers +-3 sigma
    s = SurfelInputs(means=means.to(dtype), quats=quats.to(dtype), scales=scales.to(dtype),
                     opacities=opacities.to(dtype), sh=sh.to(dtype), texel_size=texel.to(dtype),
                     textures=textures.to(dtype), tex_res=res, tex_offset=offset)
    cam = Camera(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height,
                 viewmat=torch.eye(4, dtype=dtype))
    return s, cam


def _leaves(s: SurfelInputs) -> SurfelInputs:
    names = ("means", "quats", "scales", "opacities", "sh", "textures")
    return replace(s, **{k: getattr(s, k).detach().requires_grad_(True) for k in names})


def time_render(s: SurfelInputs, cam: Camera, backend: str, backward: bool, reps: int) -> float:
    """Median wall-clock seconds of one render (and one backward of a random-cotangent loss)."""
    times = []
    for _ in range(reps):
        sg = _leaves(s) if backward else s
        t0 = time.perf_counter()
        if backward:
            out = render(sg, cam, backend=backend)
            (out.rgb.sum() + 0.5 * out.alpha.sum()).backward()
        else:
            with torch.no_grad():
                render(sg, cam, backend=backend)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def band_camera(cam: Camera, rows: int) -> Camera:
    """The rows [r0, r0 + rows) of `cam`'s image through its centre, as a camera of its own."""
    r0 = (cam.height - rows) // 2
    return replace(cam, height=rows, cy=cam.cy - r0)


def machine_info() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"hostname": socket.gethostname(), "cpu_model": cpu, "logical_cores": os.cpu_count(),
            "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"), "python": platform.python_version(),
            "load_average_at_start": os.getloadavg(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="256,512", help="square image sizes (pixels)")
    ap.add_argument("--counts", default="20000,100000", help="numbers of surfels")
    ap.add_argument("--reps", type=int, default=2, help="repetitions per timing (median)")
    ap.add_argument("--ref-rows", type=int, default=4, help="rows of the band the reference is timed on")
    ap.add_argument("--ref-full", action="store_true", help="time the reference on whole images")
    ap.add_argument("--no-ref", action="store_true", help="skip the reference")
    ap.add_argument("--ref-bwd-max-surfels", type=int, default=20000,
                    help="skip the reference's backward above this many surfels: each checkpointed chunk of its "
                         "backward materialises a dense [T, 3] texel gradient (13+ GB at 100k surfels)")
    ap.add_argument("--quick", action="store_true", help="256x256 / 20k only")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "bench_render"))
    args = ap.parse_args()
    sizes = [256] if args.quick else [int(v) for v in args.sizes.split(",")]
    counts = [20000] if args.quick else [int(v) for v in args.counts.split(",")]
    load_cpu()  # build outside the timings
    info = machine_info()
    rows = []
    for n in counts:
        for size in sizes:
            s, cam = make_scene(n, size, size)
            with torch.no_grad():
                out = render(s, cam, backend="cpu")
            row = {"width": size, "height": size, "surfels": n, "texels": int(s.textures.shape[0]),
                   "mean_alpha": round(float(out.alpha.mean()), 3)}
            time_render(s, cam, "cpu", True, 1)  # warm-up (allocator, page faults)
            row["cpu_fwd_ms"] = 1e3 * time_render(s, cam, "cpu", False, args.reps)
            row["cpu_fwdbwd_ms"] = 1e3 * time_render(s, cam, "cpu", True, args.reps)
            if not args.no_ref:
                if args.ref_full:
                    rcam, scale, how = cam, 1.0, "full image"
                else:
                    rcam = band_camera(cam, args.ref_rows)
                    scale, how = cam.height / args.ref_rows, f"{args.ref_rows}-row band x {cam.height / args.ref_rows:g}"
                row["ref_fwd_ms"] = 1e3 * scale * time_render(s, rcam, "reference", False, 1)
                row["ref_timing"] = how
                row["speedup_fwd"] = row["ref_fwd_ms"] / row["cpu_fwd_ms"]
                if n <= args.ref_bwd_max_surfels:
                    row["ref_fwdbwd_ms"] = 1e3 * scale * time_render(s, rcam, "reference", True, 1)
                    row["speedup_fwdbwd"] = row["ref_fwdbwd_ms"] / row["cpu_fwdbwd_ms"]
                else:
                    row["ref_timing"] += " (fwd only: backward does not fit in memory)"
            rows.append(row)
            print(json.dumps(row), flush=True)
            del s, out
    result = {"machine": info, "load_average_at_end": os.getloadavg(), "reps": args.reps, "dtype": "float32",
              "rows": rows}
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = out_dir / f"render_cpu_{record.commit()}"
    tmp = stem.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, stem.with_suffix(".json"))
    md = [f"# Renderer benchmark on {info['hostname']}", "",
          f"{info['cpu_model']}, {info['logical_cores']} logical cores, torch {info['torch']}, "
          f"{info['torch_threads']} threads, float32, median of {args.reps}; load average at start "
          f"{', '.join(f'{v:.1f}' for v in info['load_average_at_start'])} ({info['date_utc']}).", "",
          "| image | surfels | texels | CPU fwd ms | CPU fwd+bwd ms | ref fwd ms | ref fwd+bwd ms | fwd x | fwd+bwd x | ref timed on |",
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        ref = [f"{r[k]:.0f}" if k in r else "-" for k in ("ref_fwd_ms", "ref_fwdbwd_ms")]
        sp = [f"{r[k]:.1f}" if k in r else "-" for k in ("speedup_fwd", "speedup_fwdbwd")]
        md.append(f"| {r['width']}x{r['height']} | {r['surfels']} | {r['texels']} | {r['cpu_fwd_ms']:.0f} | "
                  f"{r['cpu_fwdbwd_ms']:.0f} | {ref[0]} | {ref[1]} | {sp[0]} | {sp[1]} | {r.get('ref_timing', '-')} |")
    tmp = stem.with_suffix(".md.tmp")
    tmp.write_text("\n".join(md) + "\n")
    os.replace(tmp, stem.with_suffix(".md"))
    print("\n".join(md))


if __name__ == "__main__":
    main()
