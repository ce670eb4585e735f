"""`ctgs compress MODEL_DIR -o OUT_DIR`: K-means texel codebook (+ optional float16 SH) of an exported model."""

from __future__ import annotations

import os

import click

from ctgs.errors import UserError


@click.command(name="compress")
@click.argument("model_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output model folder (replaced atomically).")
@click.option("--codebook-size", "-k", default=256, show_default=True,
              help="K, number of codebook colours (<= 256: uint8 indices, <= 65536: uint16).")
@click.option("--half/--no-half", default=True, show_default=True,
              help="Store SH coefficients and the codebook as float16 (positions/rotations/scales stay float32).")
@click.option("--seed", default=0, show_default=True, help="K-means random seed.")
def command(model_dir: str, out_dir: str, codebook_size: int, half: bool, seed: int) -> None:
    """Compress MODEL_DIR (from `ctgs export`) into OUT_DIR; `ctgs eval --model OUT_DIR` measures quality."""
    from ctgs.io.compress import kmeans_codebook
    from ctgs.io.model_format import read_model, write_model

    if os.path.abspath(model_dir) == os.path.abspath(out_dir):
        raise UserError(f"{out_dir}: output must differ from the input model folder")
    model, files = read_model(model_dir)
    if files.manifest.get("texture_encoding") != "raw" or "compression" in files.manifest:
        raise UserError(f"{model_dir}: already compressed; compress the exported model instead")
    before = files.bytes_on_disk
    info = {"source": os.path.abspath(model_dir), "codebook_size": codebook_size, "half": half, "bytes_before": before}
    if model.num_texels == 0:
        # Untextured models (2DGS baseline, runs stopped before texturing): nothing to cluster, only fp16.
        info.update(codebook_size=None, method="none (no texels)", rmse_activated=0.0, seconds=0.0)
        blob = None
    else:
        result = kmeans_codebook(model, codebook_size, seed=seed, half=half)
        blob = result.blob
        info.update(method=result.method, rmse_activated=result.rmse_activated, seconds=result.seconds)
    manifest = write_model(model, out_dir, blob=blob, half=half, plain_ply=False, extra={"compression": info})
    after = os.path.getsize(os.path.join(out_dir, "manifest.json")) + sum(manifest["file_bytes"].values())
    click.echo(f"{model_dir}: {before / 1e6:.3f} MB -> {out_dir}: {after / 1e6:.3f} MB "
               f"(x{before / max(after, 1):.2f} smaller); K={info['codebook_size']} ({info['method']}, "
               f"{info['seconds']:.1f} s), texel RMSE {info['rmse_activated']:.4f}")
