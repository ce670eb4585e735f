"""`ctgs demo-scene OUT_DIR`: render the built-in synthetic scene (COLMAP layout, true cameras)."""

from __future__ import annotations

import time

import click


@click.command(name="demo-scene")
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--views", "num_views", default=40, show_default=True, help="Number of cameras on the arc.")
@click.option("--width", default=256, show_default=True, help="Image width, pixels.")
@click.option("--height", default=192, show_default=True, help="Image height, pixels.")
@click.option("--seed", default=0, show_default=True, help="Seed of the camera jitter and point sampling.")
@click.option("--points", default=5000, show_default=True, help="Surface-sampled SfM points written.")
@click.option("--supersample", default=3, show_default=True, help="Sub-pixel rays per axis (antialiasing).")
@click.option("--force", is_flag=True,
              help="Replace OUT_DIR when it holds a demo scene made with other options (a folder of other files is "
                   "never replaced).")
def command(out_dir: str, num_views: int, width: int, height: int, seed: int, points: int, supersample: int,
            force: bool) -> None:
    """Generate the demo scene: OUT_DIR/images, OUT_DIR/sparse/0 (true PINHOLE cameras), demo_meta.json."""
    from rich.console import Console

    from ctgs.scene.demo import make_demo_scene

    console = Console(stderr=True)
    start = time.perf_counter()
    with console.status(f"rendering {num_views} views at {width}x{height}..."):
        path = make_demo_scene(out_dir, num_views=num_views, width=width, height=height, seed=seed, points=points,
                               supersample=supersample, overwrite=force)
    console.print(f"demo scene: {path} ({num_views} views, {points} points, {time.perf_counter() - start:.1f} s)")
