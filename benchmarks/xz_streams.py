"""The xz coder of `ctgs compress`: one stream per section (--jobs 1) against independent 16 MiB streams on N threads
(--jobs N), side by side in one run, on the section that dominates a large model: its texel indices.

    .venv/bin/python benchmarks/xz_streams.py --images /work/scenes/herzjesu25/images_2 --jobs 2 --name vm34
    .venv/bin/python benchmarks/xz_streams.py --model RUN/model --jobs 2 --name NAME

--model: an exported model's texel indices as `ctgs compress` makes them (the balanced target: 256-level scalar
codebook, primitives Morton-sorted). --images: a stand-in where no large model is at hand: the photos' pixels
through the same 256-level scalar codebook, one row of 3 indices per pixel (textures are patches of such photos;
their statistics are close, not equal). Writes benchmarks/results/xz_streams_NAME.md/.json: coded bytes, seconds,
and the round trip checked.
"""

from __future__ import annotations

import argparse
import glob
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from record import write_record  # noqa: E402

from ctgs.io import packed  # noqa: E402
from ctgs.io.packed import Section, decode_section, encode_section  # noqa: E402


def indices_from_images(folder: str) -> np.ndarray:
    import cv2

    from ctgs.io.kmeans import scalar_kmeans

    files = sorted(glob.glob(os.path.join(folder, "*.jpg")) + glob.glob(os.path.join(folder, "*.png")))
    if not files:
        raise SystemExit(f"xz_streams.py: no .jpg/.png in {folder}")
    px = np.concatenate([cv2.imread(f)[:, :, ::-1].reshape(-1, 3) for f in files]).astype(np.float64) / 127.5 - 1
    return scalar_kmeans(px.reshape(-1), 256).labels.astype(np.uint8).reshape(-1, 3)


def indices_from_model(model_dir: str) -> np.ndarray:
    from ctgs.io.compress import TARGETS, compress_model
    from ctgs.io.model_format import read_model

    model, _ = read_model(model_dir)
    sections = compress_model(model, TARGETS["balanced"]).sections
    return next(s.array for s in sections if s.name == "textures")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--images")
    src.add_argument("--model")
    ap.add_argument("--jobs", default="2", help="comma-separated thread counts to compare with one stream")
    ap.add_argument("--name", required=True)
    args = ap.parse_args()
    idx = indices_from_model(args.model) if args.model else indices_from_images(args.images)
    section = Section("textures", idx, {"kind": "codebook"})
    rows = []
    for jobs in [1] + [int(j) for j in args.jobs.split(",")]:
        t0 = time.perf_counter()
        coded, entry = encode_section(section, "xz", 0, jobs=jobs)
        t_code = time.perf_counter() - t0
        t0 = time.perf_counter()
        ok = bool(np.array_equal(decode_section(coded, entry, "bench"), idx))
        rows.append({"jobs": jobs, "streams": len(entry.get("streams", [1])), "bytes": len(coded),
                     "code_s": round(t_code, 2), "decode_s": round(time.perf_counter() - t0, 2), "round_trip": ok})
    base = rows[0]
    for r in rows:
        r["bytes_ratio"] = r["bytes"] / base["bytes"]
        r["speedup"] = base["code_s"] / r["code_s"]
    result = {"source": args.model or args.images, "kind": "model" if args.model else "images (stand-in)",
              "uncoded_bytes": int(idx.nbytes), "stream_bytes": packed.XZ_STREAM_BYTES, "rows": rows,
              "machine": f"{platform.node()} ({platform.machine()}, {os.cpu_count()} cpus)",
              "command": "benchmarks/xz_streams.py " + " ".join(sys.argv[1:])}

    def md(r: dict) -> str:
        lines = [f"# xz coding of texel indices: one stream vs parallel streams ({r['machine']})", "",
                 f"Command: `{r['command']}`. Source: {r['source']} ({r['kind']}), {r['uncoded_bytes'] / 1e6:.1f} MB "
                 f"of 1-byte indices; streams of {r['stream_bytes'] >> 20} MiB with --jobs > 1.", "",
                 "| --jobs | streams | coded MB | bytes vs one stream | code s | speed-up | decode s | round trip |",
                 "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
        for x in r["rows"]:
            lines.append(f"| {x['jobs']} | {x['streams']} | {x['bytes'] / 1e6:.3f} | {x['bytes_ratio']:.4f}x | "
                         f"{x['code_s']:.1f} | {x['speedup']:.2f}x | {x['decode_s']:.1f} | "
                         f"{'identical' if x['round_trip'] else 'DIFFERS'} |")
        return "\n".join(lines) + "\n"

    write_record(f"xz_streams_{args.name}", result, md)


if __name__ == "__main__":
    main()
