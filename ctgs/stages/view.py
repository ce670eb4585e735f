"""`ctgs view MODEL_DIR|RUN_DIR [--scene SCENE_DIR] [--mesh MESH] [--port N] [--no-browser]`: the WebGL2 viewer on
127.0.0.1; a run folder is followed while it trains (ctgs.viewer.live)."""

from __future__ import annotations

import os
import tempfile

import click


def resolve_bundle(model_dir: str, scene_dir: str | None, tmp_root: str) -> tuple[str, list[dict] | None, str]:
    """(bundle folder, cameras to serve instead of the bundle's or None, how it was found).

    MODEL_DIR may be a bundle folder, a model folder with a web/ bundle (`ctgs export --format web`), or
    a plain model folder, whose bundle is then built into tmp_root (the model folder is left untouched).
    """
    from ctgs.errors import UserError
    from ctgs.formats.model_format import MANIFEST, read_manifest, read_model
    from ctgs.formats.web_bundle import BUNDLE_JSON, WEB_SUBDIR, read_bundle_json, scene_cameras, write_web_bundle

    cameras = scene_cameras(scene_dir) if scene_dir else None
    if os.path.isfile(os.path.join(model_dir, BUNDLE_JSON)):
        read_bundle_json(model_dir)
        return model_dir, cameras, "bundle"
    web = os.path.join(model_dir, WEB_SUBDIR)
    if os.path.isfile(os.path.join(web, BUNDLE_JSON)):
        read_bundle_json(web)
        return web, cameras, "model/web"
    if not os.path.isfile(os.path.join(model_dir, MANIFEST)):
        raise UserError(f"{model_dir}: neither a model folder nor a web bundle; pass a folder written by "
                        "`ctgs export` (ideally with --format web)")
    manifest = read_manifest(model_dir)
    model, _ = read_model(model_dir)
    if cameras is None:
        src = manifest.get("source") or {}
        sd = src.get("scene_dir")
        if sd and os.path.isdir(sd):
            cameras = scene_cameras(sd, src.get("images", "images"), int(src.get("holdout", 8)))
        else:
            cameras = []
            click.echo(f"note: the model's scene ({sd or 'unknown'}) is not on disk; pass --scene SCENE_DIR "
                       "to jump to its cameras", err=True)
    out = os.path.join(tmp_root, "web")
    write_web_bundle(model, out, cameras)
    return out, None, "built from the model folder"


@click.command(name="view")
@click.argument("model_dir", metavar="MODEL_DIR|RUN_DIR", type=click.Path(file_okay=False))
@click.option("--scene", "scene_dir", default=None, type=click.Path(file_okay=False),
              help="Scene folder whose training and test cameras the viewer can jump to "
                   "(default: the cameras stored in the bundle, i.e. of the scene the model was trained on).")
@click.option("--mesh", "mesh_path", default=None, type=click.Path(dir_okay=False),
              help="A mesh written by `ctgs mesh` (.ply, .obj or .glb) to show instead of the surfels at a keystroke (M).")
@click.option("--port", default=8765, show_default=True, type=click.IntRange(0, 65535),
              help="Port on 127.0.0.1 (0 = any free port).")
@click.option("--no-browser", is_flag=True, help="Only serve; do not open a browser window.")
def command(model_dir: str, scene_dir: str | None, mesh_path: str | None, port: int, no_browser: bool) -> None:
    """Serve MODEL_DIR's web viewer on http://127.0.0.1:PORT/ (WebGL2; every script ships with ctgs). RUN_DIR, a
    run folder of `ctgs train`, training or finished: its newest model, reloaded as checkpoints land, and its progress
    (iteration, loss, test PSNR, time left) from its log."""
    import webbrowser

    from ctgs.errors import UserError
    from ctgs.viewer.live import LiveRun, is_run_folder
    from ctgs.viewer.server import ViewerServer

    if not os.path.isdir(model_dir):
        raise UserError(f"{model_dir}: model folder not found; write one with `ctgs export RUN_DIR --format web`, or "
                        "pass a run folder of `ctgs train`")
    live = is_run_folder(model_dir)
    if live and mesh_path:
        raise UserError(f"{model_dir}: a run folder is shown as it trains, without a mesh; pass the model folder "
                        "`ctgs export` wrote with --mesh")
    mesh = None
    if mesh_path:
        from ctgs.formats.mesh import read_mesh, viewer_mesh

        mesh = viewer_mesh(*read_mesh(mesh_path))
    with tempfile.TemporaryDirectory(prefix="ctgs-view-") as tmp:
        if live:
            from ctgs.formats.web_bundle import scene_cameras

            run = LiveRun(model_dir, tmp, scene_cameras(scene_dir) if scene_dir else None)
        try:
            if live:
                server = ViewerServer(port=port, quiet=True, live=run)
                bundle_dir, how = model_dir, "a run folder, followed as it trains"
            else:
                bundle_dir, cameras, how = resolve_bundle(model_dir, scene_dir, tmp)
                server = ViewerServer(bundle_dir, port=port, cameras=cameras, quiet=True, mesh=mesh)
        except OSError as exc:
            raise UserError(f"127.0.0.1:{port}: cannot listen ({exc.strerror}); pass another --port "
                            "(0 = any free port)") from exc
        for note in run.notes if live else ():
            click.echo(f"note: {note}", err=True)
        click.echo(f"serving {bundle_dir} ({how}) at {server.url}  (Ctrl-C stops)")
        if not no_browser:
            webbrowser.open(server.url)
        try:
            server.serve_forever()
        except KeyboardInterrupt:  # Ctrl-C (`kill`: ctgs.errors.Terminated, exit 143): the bundle goes either way
            pass
        finally:
            server.close()
