"""`ctgs fetch DATASET [SCENES...]`: download and extract benchmark scenes listed in data_manifests/."""

from __future__ import annotations

import click


@click.command(name="fetch")
@click.argument("dataset")
@click.argument("scenes", nargs=-1)
@click.option("--root", default=None, help="Data root (default: $CTGS_DATA_ROOT or ./data).")
@click.option("--manifest-dir", default=None,
              help="Folder of <dataset>.toml manifests (default: $CTGS_MANIFEST_DIR or data_manifests/).")
@click.option("--delete-archive", is_flag=True, help="Delete the downloaded archive after extraction.")
@click.option("--list", "list_only", is_flag=True, help="List the dataset's scenes and archives; download nothing.")
@click.option("--print-scene-dir", is_flag=True, help="Print DATA_ROOT/<dataset>/<scene> for each scene; no download.")
@click.option("--print-images-dir", is_flag=True,
              help="Print each scene's image folder name (the value for --images, e.g. images_4); no download.")
@click.option("--print-holdout", is_flag=True, help="Print each scene's test holdout (every N-th view); no download.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def command(dataset: str, scenes: tuple[str, ...], root: str | None, manifest_dir: str | None, delete_archive: bool,
            list_only: bool, print_scene_dir: bool, print_images_dir: bool, print_holdout: bool, quiet: bool) -> None:
    """Download DATASET (mipnerf360, tandt, deepblending, or a .toml path) and extract SCENES (default: all).

    Resumes partial downloads, verifies size and sha256, and skips scenes already extracted.
    """
    from ctgs.errors import UserError
    from ctgs.scene.manifests import load_manifest, scene_dir

    manifest = load_manifest(dataset, manifest_dir)
    names = list(scenes) or list(manifest["scenes"])
    for name in names:
        if name not in manifest["scenes"]:
            raise UserError(f"{manifest['path']}: unknown scene {name!r}; known: {', '.join(manifest['scenes'])}")
    if print_scene_dir or print_images_dir or print_holdout:
        for name in names:
            info = manifest["scenes"][name]
            fields = []
            if print_scene_dir:
                fields.append(str(scene_dir(manifest, name, root)))
            if print_images_dir:
                fields.append(info["images"])
            if print_holdout:
                fields.append(str(info["holdout"]))
            click.echo(" ".join(fields))
        return
    if list_only:
        for aname, archive in manifest["archives"].items():
            size = f"{archive['size'] / 1e9:.2f} GB" if archive["size"] else "size unknown"
            click.echo(f"archive {aname}: {archive['url']} ({size}, sha256 {archive['sha256'] or 'unknown'})")
        for name, info in manifest["scenes"].items():
            click.echo(f"scene {name}: archive {info['archive']}, images {info['images']}, holdout {info['holdout']}")
        return

    from rich.console import Console

    from ctgs.scene.fetch import fetch_dataset

    console = Console(stderr=True)
    for scene in fetch_dataset(dataset, names, root=root, manifest_dir=manifest_dir, delete_archive=delete_archive,
                               quiet=quiet):
        state = "already there" if scene.skipped else "fetched"
        console.print(f"{scene.dataset}/{scene.scene}: {state} -> {scene.path} (--images {scene.images}, "
                      f"holdout {scene.holdout})")
