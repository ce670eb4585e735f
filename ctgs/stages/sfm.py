"""`ctgs sfm IMAGES_DIR -o SCENE_DIR`: pycolmap structure from motion -> undistorted COLMAP scene."""

from __future__ import annotations

import click


@click.command(name="sfm")
@click.argument("images_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "scene_dir", required=True, type=click.Path(file_okay=False),
              help="Scene folder to write (images/, sparse/0/, images_2/4/8/, sfm_report.json).")
@click.option("--matcher", type=click.Choice(["exhaustive", "sequential"]), default="exhaustive", show_default=True,
              help="exhaustive: every pair (photo collections); sequential: neighbours in name order (video).")
@click.option("--max-image-size", default=3200, show_default=True, help="Longest side seen by SIFT, pixels.")
@click.option("--threads", default=-1, show_default=True, help="CPU threads (-1: all cores).")
@click.option("--force", is_flag=True, help="Redo every step, replacing a finished SCENE_DIR.")
@click.option("--verbose", is_flag=True, help="Show COLMAP's own log lines.")
def command(images_dir: str, scene_dir: str, matcher: str, max_image_size: int, threads: int, force: bool,
            verbose: bool) -> None:
    """Reconstruct cameras and sparse points from a folder of photos (CPU, pycolmap).

    Re-running skips finished steps; an interrupted run resumes from its work folder.
    """
    from rich.console import Console
    from rich.table import Table

    from ctgs.scene.sfm import SfmOptions, run_sfm

    console = Console(stderr=True)
    opts = SfmOptions(matcher=matcher, max_image_size=max_image_size, threads=threads, force=force)
    with console.status("sfm: starting") as spinner:
        report, ran = run_sfm(images_dir, scene_dir, opts, status=lambda msg: spinner.update(f"sfm: {msg}"),
                             quiet=not verbose)
    if not ran:
        console.print(f"{report.scene_dir}: already reconstructed (pass --force to redo)")
    table = Table(title=f"sfm: {report.scene_dir}", show_header=False)
    table.add_row("images registered / given", f"{report.registered} / {report.given}")
    table.add_row("3D points", str(report.points))
    table.add_row("mean reprojection error", f"{report.mean_reprojection_error_px:.3f} px")
    table.add_row("mean track length", f"{report.mean_track_length:.2f}")
    table.add_row("camera", f"{report.camera_model} {report.width}x{report.height} f=({report.fx:.1f}, {report.fy:.1f})")
    if report.seconds:
        table.add_row("time", ", ".join(f"{k} {v:.1f} s" for k, v in report.seconds.items()))
    if report.unregistered:
        table.add_row("not registered", ", ".join(report.unregistered[:10]) + (" ..." if len(report.unregistered) > 10 else ""))
    console.print(table)
