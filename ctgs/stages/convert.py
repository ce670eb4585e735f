"""`ctgs convert SCENE --to nerfstudio|colmap -o OUT`: a scene written in another layout."""

from __future__ import annotations

import click


@click.command(name="convert")
@click.argument("scene_dir", type=click.Path(file_okay=False))
@click.option("--to", "to", required=True, type=click.Choice(["nerfstudio", "colmap"]),
              help="nerfstudio: transforms.json (as ns-process-data writes it); colmap: sparse/0 (gsplat's examples, "
                   "3DGS).")
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Scene folder to write (images/, masks/ where the source has masks).")
@click.option("--force", is_flag=True, help="Replace OUT if it holds an earlier converted scene.")
def command(scene_dir: str, to: str, out_dir: str, force: bool) -> None:
    """Write SCENE_DIR (COLMAP, transforms.json or Blender synthetic) in another layout, cameras and points
    unchanged; distorted photos are written undistorted."""
    from ctgs.scene.convert import convert_scene

    summary = convert_scene(scene_dir, out_dir, to, force=force)
    click.echo(f"{summary['layout']}: {summary['views']} views, {summary['points']} points"
               + (f", {summary['masks']} masks" if summary["masks"] else "")
               + (f", {summary['undistorted']} photos undistorted" if summary["undistorted"] else "")
               + (f", levels {' '.join(summary['levels'])}" if summary["levels"] else "")
               + f" -> {out_dir}")
    if summary["note"]:
        click.echo(f"note: {summary['note']}")
