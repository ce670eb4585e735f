"""`ctgs mesh RUN_DIR -o OUT.ply|.obj|.glb`: a coloured triangle mesh of a trained run (TSDF fusion of its depth)."""

from __future__ import annotations

import time

import click


class _Bars:
    """The rich progress bars of the two long steps: views fused, regions meshed."""

    def __init__(self) -> None:
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        self.progress = Progress(TextColumn("{task.description}"), BarColumn(bar_width=30), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True))
        self.tasks: dict[str, int] = {}

    def __enter__(self) -> _Bars:
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    def step(self, name: str):
        def update(done: int, total: int) -> None:
            if name not in self.tasks:
                self.tasks[name] = self.progress.add_task(name, total=total)
            self.progress.update(self.tasks[name], completed=done, total=total)
        return update


@click.command(name="mesh")
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False),
              help="The mesh file: .ply (binary, vertex colours), .obj (v x y z r g b) or .glb (glTF binary, COLOR_0); "
                   "replaced atomically.")
@click.option("--bound", type=click.Choice(["cameras", "contract"]), default="cameras", show_default=True,
              help="cameras: the surfaces within --depth-trunc of the training cameras, in a box around them (a room, "
                   "an object and its surroundings); contract: all of space, with voxels growing beyond the cameras' "
                   "sphere as in 2DGS's unbounded meshing (Mip-NeRF 360 backgrounds).")
@click.option("--resolution", default=None, type=click.IntRange(min=8),
              help="Voxels across the scene extent (twice the cameras' median distance from the point they look at); "
                   "default: voxels of 2 pixels at that distance, what the photos resolve, coarser where the volume "
                   "would not fit in --max-memory.")
@click.option("--voxel-size", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Voxel size in world units (default: see --resolution).")
@click.option("--depth", "depth_kind", type=click.Choice(["median", "mean"]), default="median", show_default=True,
              help="The rendered depth fused: median, the surfel where the transmittance falls below 0.5; mean, the "
                   "expected depth (depth / alpha), which surfels far along the ray pull off the surface.")
@click.option("--depth-trunc", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Depth beyond which rendered pixels are not fused, world units (default: with --bound cameras the "
                   "scene extent, with --bound contract none).")
@click.option("--sdf-trunc", type=click.FloatRange(min=0, min_open=True), default=None,
              help="TSDF truncation distance, world units (default: 5 voxels).")
@click.option("--pieces", default=50, show_default=True, type=click.IntRange(min=0),
              help="Keep the largest connected pieces: those with as many triangles as the N-th largest (and 50 at "
                   "least), as 2DGS's post-processing does; 0 keeps every piece.")
@click.option("--views", type=click.Choice(["train", "all"]), default="train", show_default=True,
              help="Which of the scene's cameras to fuse (train: the training views, as 2DGS does).")
@click.option("--max-memory", type=click.FloatRange(min=0, min_open=True), default=None, metavar="GB",
              help="Memory the volume and mesh may take (default: 80% of the memory free on the device).")
@click.option("--backend", type=click.Choice(["auto", "cpu", "cuda", "reference"]), default="auto",
              show_default=True, help="Renderer backend for the depth and colour of every view.")
@click.option("--scene", "scene_dir", default=None, type=click.Path(file_okay=False),
              help="This machine's copy of the scene the run trained on, when the run moved from the machine or "
                   "folder it trained on (default: the folder its model.pt names).")
def command(run_dir: str, out: str, bound: str, resolution: int | None, voxel_size: float | None, depth_kind: str,
            depth_trunc: float | None, sdf_trunc: float | None, pieces: int, views: str, max_memory: float | None,
            backend: str, scene_dir: str | None) -> None:
    """Fuse RUN_DIR's rendered depth over the training cameras into a TSDF and write its surface with vertex colours."""
    import torch

    from ctgs.errors import UserError
    from ctgs.formats.mesh import mesh_suffix, write_mesh
    from ctgs.fusion.pipeline import MeshOptions, extract, fuse, plan_volume
    from ctgs.runs import load_run, run_scene, with_scene
    from ctgs.scene.loader import check_same_frame

    mesh_suffix(out)
    device = torch.device("cuda" if backend == "cuda" or (backend == "auto" and torch.cuda.is_available()) else "cpu")
    run = with_scene(load_run(run_dir, device=device), scene_dir)
    scene = run_scene(run, load_images=False)
    check_same_frame(run.world_origin, scene, run.run_dir)
    chosen = scene.train if views == "train" else scene.train + scene.test
    cameras = [v.camera for v in chosen]
    if not cameras:
        raise UserError(f"{run.scene_dir}: no {views} views to fuse; pass --views all")
    opts = MeshOptions(bound=bound, resolution=resolution, voxel_size=voxel_size, depth_trunc=depth_trunc,
                       sdf_trunc=sdf_trunc, pieces=pieces,
                       max_memory=None if max_memory is None else max_memory * 1e9, depth=depth_kind)
    start = time.perf_counter()
    with _Bars() as bars:
        plan = plan_volume(run.model, cameras, scene.points, opts, backend, what=run_dir,
                           progress=bars.step(f"rendering {len(cameras)} views"))
        d = plan.domain
        reach = "all of space, contracted" if d.contract else f"depth <= {plan.depth_trunc:.3g}"
        if plan.coarsened_from is not None:
            reach += f" (voxels of {plan.coarsened_from:.3g} would not fit in {plan.limit / 1e9:.3g} GB)"
        bars.progress.console.print(f"volume: {plan.voxels / 1e6:.1f}M voxels of {d.voxel:.3g} around the cameras' "
                                    f"sphere (radius {d.radius:.3g}), {reach}, about {plan.bytes / 1e9:.2f} GB; "
                                    f"{plan.depth} depth",
                                    soft_wrap=True, markup=False, highlight=False)
        volume = fuse(run.model, cameras, plan, backend, bars.step(f"fusing {len(cameras)} views"))
        mesh, dropped = extract(volume, pieces, bars.step("marching cubes"))
    del volume
    if not mesh.num_faces:
        raise UserError(f"{run_dir}: no surface found in the fused depth; check --depth-trunc and --bound (a scene "
                        "beyond the box around the cameras needs --bound contract)")
    size = write_mesh(out, mesh.vertices, mesh.faces, mesh.colors, origin=run.world_origin)
    click.echo(f"{out}: {mesh.num_vertices} vertices, {mesh.num_faces} triangles ({dropped} small pieces dropped), "
               f"{size / 1e6:.1f} MB, {time.perf_counter() - start:.0f} s")
