"""`ctgs sfm IMAGES_DIR -o SCENE_DIR`: pycolmap structure from motion -> undistorted COLMAP scene."""

from __future__ import annotations

import click


class _Bars:
    """One rich progress bar per sfm step (photos extracted, pairs matched, photos registered, ...), with the
    time left; `status` names the step that starts next."""

    def __init__(self, console) -> None:
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                                   TimeElapsedColumn, TimeRemainingColumn)

        self.progress = Progress(SpinnerColumn(finished_text="[green]✓"), TextColumn("{task.description}"),
                                 BarColumn(bar_width=24), MofNCompleteColumn(), TextColumn("{task.fields[note]}"),
                                 TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("left"), console=console)
        self.tasks: dict[str, int] = {}
        self.next_description = ""

    def __enter__(self) -> _Bars:
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    def status(self, message: str) -> None:
        self.next_description = message

    def update(self, step: str, done: int, total: int | None, note: str) -> None:
        if step not in self.tasks:
            self.tasks[step] = self.progress.add_task(self.next_description or step, total=total, note=note)
        self.progress.update(self.tasks[step], completed=done, total=total, note=note)


@click.command(name="sfm")
@click.argument("images_dir", metavar="IMAGES_DIR|VIDEO", type=click.Path())
@click.option("-o", "--output", "scene_dir", required=True, type=click.Path(file_okay=False),
              help="Scene folder to write (images/, sparse/0/, images_2/4/8/, sfm_report.json).")
@click.option("--matcher", type=click.Choice(["auto", "exhaustive", "sequential", "retrieval"]), default="auto",
              show_default=True,
              help="Which photo pairs to match. exhaustive: every pair; retrieval: each photo with its 20 most similar "
                   "photos (a vocabulary made from the capture's own features) and its next 3 in name order; "
                   "sequential: video frames, neighbours in name order plus loop closure; auto: exhaustive up to "
                   "50 photos, retrieval above.")
@click.option("--mapper", type=click.Choice(["auto", "incremental", "global"]), default="auto", show_default=True,
              help="incremental: COLMAP's, photo by photo; global: GLOMAP's (pycolmap.global_mapping), all photos at "
                   "once, faster on large captures; auto: incremental up to 50 photos, global above.")
@click.option("--max-features", default=0, show_default=True,
              help="SIFT features per photo at most; 0: 8192 up to 50 photos, 4096 above.")
@click.option("--max-image-size", default=3200, show_default=True, help="Longest side seen by SIFT, pixels.")
@click.option("--threads", default=-1, show_default=True, help="CPU threads (-1: all cores).")
@click.option("--frames", "frames", default=150, show_default=True,
              help="From a VIDEO: how many frames to keep (the sharpest of each of N equal spans); they go to "
                   "SCENE_DIR/input with SCENE_DIR/video_frames.json.")
@click.option("--force", is_flag=True, help="Redo every step, replacing a finished SCENE_DIR.")
@click.option("--verbose", is_flag=True, help="Show COLMAP's own log lines.")
def command(images_dir: str, scene_dir: str, matcher: str, mapper: str, max_features: int, max_image_size: int,
            threads: int, frames: int, force: bool, verbose: bool) -> None:
    """Reconstruct cameras and sparse points from a folder of photos, or from a video's frames (pycolmap; SIFT
    features by OpenCV on the CPU, by COLMAP on the GPU when pycolmap has CUDA).

    Re-running skips finished steps; an interrupted run resumes from its work folder.
    """
    from rich.console import Console
    from rich.table import Table

    from ctgs.scene.sfm import SfmOptions, run_sfm
    from ctgs.scene.video import extract_frames, is_video

    console = Console(stderr=True)
    if is_video(images_dir):
        with console.status(f"picking {frames} frames of {images_dir}..."):
            images_dir, record = extract_frames(images_dir, scene_dir, frames, force=force)
        console.print(f"{len(record['frames'])} of {record['frames_in_video']} frames -> {images_dir} "
                      f"({record['method']}; video_frames.json)")
        matcher = "sequential" if matcher == "auto" else matcher  # frames in time order
    opts = SfmOptions(matcher=matcher, mapper=mapper, max_features=max_features, max_image_size=max_image_size,
                      threads=threads, force=force)
    if console.is_terminal and not verbose:
        with _Bars(console) as bars:
            report, ran = run_sfm(images_dir, scene_dir, opts, status=bars.status, quiet=True, progress=bars.update)
    else:
        report, ran = run_sfm(images_dir, scene_dir, opts, quiet=not verbose)
    if not ran:
        console.print(f"{report.scene_dir}: already reconstructed (pass --force to redo)")
    table = Table(title=f"sfm: {report.scene_dir}", show_header=False)
    table.add_row("images registered / given", f"{report.registered} / {report.given}")
    table.add_row("3D points", str(report.points))
    table.add_row("mean reprojection error", f"{report.mean_reprojection_error_px:.3f} px")
    table.add_row("mean track length", f"{report.mean_track_length:.2f}")
    table.add_row("camera", f"{report.camera_model} {report.width}x{report.height} f=({report.fx:.1f}, {report.fy:.1f})")
    table.add_row("pairs, mapper", f"{report.matcher}: {report.pairs} pairs, {report.mapper} mapping, "
                                   f"{report.max_features} features per photo at most")
    if report.seconds:
        table.add_row("time", ", ".join(f"{k} {v:.1f} s" for k, v in report.seconds.items()))
    if report.unregistered:
        table.add_row("not registered", ", ".join(report.unregistered[:10]) + (" ..." if len(report.unregistered) > 10 else ""))
    console.print(table)
