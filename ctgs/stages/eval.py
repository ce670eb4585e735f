"""`ctgs eval RUN_DIR [--model MODEL_DIR]` and `ctgs eval --table RUN_DIR... -o OUT`."""

from __future__ import annotations

import json
import os

import click

from ctgs.errors import UserError
from ctgs.evaluation.report import OPEN_ALPHA

# The worst test view gets a line when at least this share of its pixels is open.
OPEN_NOTE = 0.01
# ... and when one primitive centred outside it carries at least this share of its blending weight (a veil; over
# the training views of 24 herzjesu25 runs the largest was 12%: ctgs.evaluation.evaluate.veil_share).
VEIL_NOTE = 0.15
# a view whose photo is this much brighter or darker than the render (least-squares gain) gets a note: the capture's
# exposures differ, which no model of the scene can predict for a new view (ctgs.metrics.psnr.gain_matched_psnr)
GAIN_NOTE = 0.05


def _metrics_path(path: str) -> str:
    """RUN_DIR (-> RUN_DIR/eval/metrics.json), an eval folder, or a metrics.json itself."""
    for cand in (path, os.path.join(path, "metrics.json"), os.path.join(path, "eval", "metrics.json")):
        if os.path.isfile(cand):
            return cand
    raise UserError(f"{path}: no metrics.json (looked in it, and in eval/); run `ctgs eval {path}` first")


def _paper_rows(metrics: list[dict]) -> dict:
    """{(dataset, scene): the paper's row} for the scenes of `metrics` that a shipped manifest lists with one."""
    from ctgs.scene.manifests import available, load_manifest

    wanted = {(m.get("dataset"), m.get("scene")) for m in metrics}
    rows = {}
    for name in available():
        manifest = load_manifest(name)
        for scene, info in manifest["scenes"].items():
            if info.get("paper") and (manifest["name"], scene) in wanted:
                # the size the paper trained at where the manifest gives it, else the protocol's image folder
                rows[(manifest["name"], scene)] = {**info["paper"],
                                                   "resolution": info["paper"].get("resolution") or info["images"]}
    return rows


TABLE_FILES = ("table.md", "table.csv")


def _table(paths: tuple[str, ...], out: str) -> None:
    from ctgs.io import atomic, owner
    from ctgs.evaluation.report import METRICS_SCHEMA, build_table

    owner.check_ours(out, "table", "an earlier `ctgs eval --table` folder", legacy=owner.names_within(set(TABLE_FILES)))

    metrics = []
    for p in paths:
        mp = _metrics_path(p)
        try:
            with open(mp, encoding="utf-8") as f:
                m = json.load(f)
        except ValueError as exc:  # not JSON, not UTF-8: a damaged file
            raise UserError(f"{mp}: corrupt metrics.json ({' '.join(str(exc).split())[:120]}); run "
                            f"`ctgs eval {p}` again") from None
        if not isinstance(m, dict) or m.get("schema") != METRICS_SCHEMA:
            raise UserError(f"{mp}: not a ctgs metrics.json; pass run folders evaluated by `ctgs eval`")
        metrics.append(m)
    md, csv_text = build_table(metrics, _paper_rows(metrics))
    for name, text in zip(TABLE_FILES, (md, csv_text)):
        atomic.write_text(os.path.join(out, name), text)
    owner.mark(out, "table", list(TABLE_FILES))
    click.echo(md)


@click.command(name="eval")
@click.argument("run_dirs", nargs=-1, required=True, type=click.Path())
@click.option("--model", "model_dir", default=None, type=click.Path(),
              help="Evaluate this exported/compressed model folder instead of RUN_DIR/model.pt, or a Gaussian file "
                   "`ctgs export` wrote from it (.ply, .splat, .spz, .compressed.ply, .sog, .splats.glb), read back as "
                   "a Gaussian viewer reads it.")
@click.option("-o", "--output", "out_dir", default=None, type=click.Path(file_okay=False),
              help="Output folder (default RUN_DIR/eval, or RUN_DIR/eval-<model folder name> with --model; "
                   "with --table: where table.md and table.csv go).")
@click.option("--backend", default=None, type=click.Choice(["auto", "cpu", "cuda", "reference"]),
              help="Renderer backend (default: the run's config).")
@click.option("--device", default=None, help="torch device (default cuda when available, else cpu).")
@click.option("--lpips/--no-lpips", default=True, show_default=True, help="Compute LPIPS (VGG v0.1).")
@click.option("--lpips-weights", default=None, type=click.Path(dir_okay=False), envvar="CTGS_VGG16_WEIGHTS",
              help="VGG16 weights .pth (torchvision layout); see docs/reference/metrics.md for the lookup order.")
@click.option("--dataset", default=None, help="Dataset name for --table grouping (default: scene's parent folder).")
@click.option("--scene-name", default=None,
              help="The scene's name in tables (default: the scene folder's name), e.g. the benchmark's name for a "
                   "local copy stored under another folder name.")
@click.option("--split", type=click.Choice(["test", "train"]), default="test", show_default=True,
              help="Views to evaluate: the test views, or the views the run was trained on (how well it fits its "
                   "own photos; the gap to the test views is what did not generalise). Default output for train: "
                   "RUN_DIR/eval-train.")
@click.option("--scene", "scene_dir", default=None, type=click.Path(file_okay=False),
              help="This machine's copy of the scene the run trained on, when the run moved from the machine or "
                   "folder it trained on (default: the folder its model.pt names).")
@click.option("--table", is_flag=True, help="Aggregate the metrics.json of RUN_DIRS into the paper's table.")
def command(run_dirs, model_dir, out_dir, backend, device, lpips, lpips_weights, dataset, scene_name, split,
            scene_dir, table) -> None:
    """Render the test views of RUN_DIR (or its training views: --split train) and write metrics.json,
    per_image.csv, renders/ and strips/."""
    if table:
        if not out_dir:
            raise UserError("--table needs -o OUT (folder for table.md and table.csv)")
        _table(run_dirs, out_dir)
        return
    if len(run_dirs) != 1:
        raise UserError(f"eval takes one RUN_DIR (got {len(run_dirs)}); use --table to aggregate several")
    from ctgs.evaluation.evaluate import EvalOptions, evaluate

    run_dir = run_dirs[0]
    if out_dir is None:
        suffix = ("" if split == "test" else "-train") + (
            "" if model_dir is None else "-" + os.path.basename(os.path.normpath(model_dir)))
        out_dir = os.path.join(run_dir, "eval" + suffix)
    m = evaluate(run_dir, EvalOptions(out_dir=out_dir, model_dir=model_dir, backend=backend, device=device,
                                      lpips=lpips, lpips_weights=lpips_weights, dataset=dataset, split=split,
                                      scene_name=scene_name,
                                      scene_dir=scene_dir))
    lp = "n/a" if m["lpips"] is None else f"{m['lpips']:.4f}"
    views = f" ({m['num_views']} training views)" if split == "train" else ""
    click.echo(f"{out_dir}{views}: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, LPIPS {lp}, {m['points']} points, "
               f"{m['texels']} texels, {m['params']} params, {m['bytes_on_disk'] / 1e6:.3f} MB, "
               f"{m['fps']:.1f} FPS ({m['backend']}, {m['device']})")
    worst = max(m["per_image"], key=lambda r: r["open"])
    if worst["open"] >= OPEN_NOTE:  # say where the background shows: it can carry most of a view's error
        covered = "" if worst["psnr_covered"] is None else f", {worst['psnr_covered']:.2f} dB over the other pixels"
        click.echo(f"{worst['name']}: {100 * worst['open']:.1f}% of the pixels open (rendered alpha < {OPEN_ALPHA}: the "
                   f"background shows), PSNR {worst['psnr']:.2f} dB{covered}")
    veiled = max(m["per_image"], key=lambda r: r["veil"])
    if veiled["veil"] >= VEIL_NOTE:  # one surfel blended in front of the scene: docs/reference/renderer.md, Ordering
        click.echo(f"{veiled['name']}: one primitive centred outside the view carries {100 * veiled['veil']:.0f}% of "
                   f"its blending weight (a veil in front of the scene; docs/reference/renderer.md, Ordering), PSNR "
                   f"{veiled['psnr']:.2f} dB")
    off = max(m["per_image"], key=lambda r: abs(r["gain"] - 1) if r["gain"] is not None else 0.0)
    if off["gain"] is not None and abs(off["gain"] - 1) >= GAIN_NOTE:
        click.echo(f"{off['name']}: the photo is {off['gain']:.2f}x the render's brightness (least squares; the "
                   f"views span {m['gain_range'][0]:.2f}-{m['gain_range'][1]:.2f}): exposure differs between the "
                   f"photos; with each view's own gain PSNR would be {m['psnr_gain_matched']:.2f} dB (a diagnostic, "
                   "not the protocol's PSNR)")
    if m["lpips"] is None:
        click.echo(f"LPIPS {m['lpips_status']}")
