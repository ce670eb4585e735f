"""`ctgs compress MODEL_DIR -o OUT_DIR`: texel codebook + attribute quantisation + xz of an exported model."""

from __future__ import annotations

import os

import click

from ctgs.errors import UserError

TARGET_HELP = ("Preset, a measured point of the size-quality curve (benchmarks/results/compress_curve/demo_c42d198.md): "
               "lossless-ish, balanced (default; <= 0.1 dB PSNR on the demo), small.")


@click.command(name="compress")
@click.argument("model_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output model folder (replaced atomically).")
@click.option("--target", type=click.Choice(["lossless-ish", "balanced", "small"]), default="balanced",
              show_default=True, help=TARGET_HELP)
@click.option("--texels", type=click.Choice(["scalar", "vector", "f16", "f32"]), default=None,
              help="Texel storage (overrides the target): scalar = 1-D codebook, 1 byte per channel (the "
                   "paper's); vector = RGB codebook, one index per texel; f16/f32 = raw values.")
@click.option("--codebook-size", "-k", type=int, default=None,
              help="K of the texel codebook (overrides the target; scalar <= 256 keeps 1-byte indices).")
@click.option("--attr", "attrs", multiple=True, metavar="NAME=CODEC",
              help="Per-primitive attribute codec (repeatable, overrides the target): means=f32|f16|q16, "
                   "scales=f32|f16|q16|q8, quats=f32|f16|q8, opacity=f32|f16|q8, sh_dc=f32|f16|q8, "
                   "sh_rest=f32|f16|q8|kmeans:K, k_min=f32|f16, sh_degree=0..3 (drop higher SH bands).")
@click.option("--coder", type=click.Choice(["xz", "zlib", "none"]), default=None,
              help="Lossless coder of every section (default: the target's, xz).")
@click.option("--sort/--no-sort", default=None,
              help="Morton-sort primitives so neighbours share bytes (default: the target's, on).")
@click.option("--seed", default=0, show_default=True, help="K-means random seed.")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=1, show_default=True,
              help="Threads for the xz coder: sections above 16 MiB are then coded as independent 16 MiB streams, "
                   "about N times faster for about 2% more bytes (1: one stream per section, the smallest file).")
def command(model_dir: str, out_dir: str, target: str, texels: str | None, codebook_size: int | None,
            attrs: tuple[str, ...], coder: str | None, sort: bool | None, seed: int, jobs: int) -> None:
    """Compress MODEL_DIR (from `ctgs export`) into OUT_DIR; `ctgs eval RUN --model OUT_DIR` measures quality."""
    import time
    from dataclasses import asdict, replace

    from ctgs.formats.compress import TARGETS, compress_model
    from ctgs.formats.model_format import check_replaceable, read_model, write_packed_model
    from ctgs.formats.packed import XZ_STREAM_BYTES
    from ctgs.io import lock

    if os.path.abspath(model_dir) == os.path.abspath(out_dir):
        raise UserError(f"{out_dir}: output must differ from the input model folder")
    check_replaceable(out_dir)  # before the work: OUT_DIR must be absent, empty or an earlier model folder
    model, files = read_model(model_dir)
    if files.manifest.get("texture_encoding") != "raw" or "compression" in files.manifest:
        raise UserError(f"{model_dir}: already compressed; compress the exported model (`ctgs export`) instead")
    spec = TARGETS[target]
    changes = {k: v for k, v in (("texels", texels), ("codebook_size", codebook_size), ("coder", coder),
                                 ("sort", sort)) if v is not None}
    if texels is not None and codebook_size is None and texels != spec.texels:
        changes["codebook_size"] = 256  # the other texel mode's K is not meant for this one
    spec = replace(spec, **changes).with_overrides(list(attrs))
    if codebook_size is None and spec.texels == "vector" and 0 < model.num_texels < spec.codebook_size:
        spec = replace(spec, codebook_size=model.num_texels)  # a target's K on a tiny model: one entry per texel
    packed = compress_model(model, spec, seed=seed)
    before = files.bytes_on_disk
    big = max((s.array.nbytes for s in packed.sections), default=0)
    if spec.coder == "xz" and jobs == 1 and big > 2 * XZ_STREAM_BYTES:
        click.echo(f"coding {big / 1e6:.0f} MB in one xz stream (about 1-2 MB/s): --jobs {min(os.cpu_count() or 1, 8)} "
                   "codes it on that many threads for about 2% more bytes", err=True)
    info = {"target": target, "spec": asdict(spec), "source_model": os.path.abspath(model_dir),
            "bytes_before": before, "jobs": jobs, **packed.stats}
    extra = {"compression": info}
    if "source" in files.manifest:
        extra["source"] = files.manifest["source"]
    t_code = time.perf_counter()
    with lock.inside_run(out_dir):  # never while a training writes the run folder OUT_DIR is in
        manifest = write_packed_model(packed, out_dir, extra=extra, jobs=jobs)
    t_code = time.perf_counter() - t_code
    after = os.path.getsize(os.path.join(out_dir, "manifest.json")) + sum(manifest["file_bytes"].values())
    tex = packed.stats["texels"]
    k = f", K={tex['codebook_size']}" if tex.get("codebook_size") else ""
    rmse = f", texel RMSE {tex['rmse_activated']:.4f}" if "rmse_activated" in tex else ""
    click.echo(f"{model_dir}: {before / 1e6:.3f} MB -> {out_dir}: {after / 1e6:.3f} MB "
               f"(x{before / max(after, 1):.2f} smaller); target {target}, texels {tex['mode']}{k}{rmse} "
               f"({packed.stats['seconds']:.1f} s to encode, {t_code:.1f} s to code and write)")
    span = lambda m: f"{[f'{x:.4g}' for x in m['range'][0]]} to {[f'{x:.4g}' for x in m['range'][1]]}"  # noqa: E731
    fb, far = packed.stats.get("means_fallback"), packed.stats.get("means_outliers")
    if fb:
        click.echo(f"positions stored as f32, not {fb['asked']}: {fb['outliers']} of {packed.header['num_primitives']} "
                   f"primitives would move by more than {fb['limit_px']} px of their closest training camera in "
                   f"{fb['asked']} (the model spans {span(fb)})")
    elif far:
        click.echo(f"positions {far['asked']}, {far['outliers']} primitive(s) stored apart as f32: the model spans "
                   f"{span(far)}, and one {far['asked']} range over all of it would move primitives by up to "
                   f"{far['full_range_shift_px']:.2f} px (limit {far['limit_px']} px of the closest training camera; "
                   f"now {far['max_shift_px']:.3f} px)")
