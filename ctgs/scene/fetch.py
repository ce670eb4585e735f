"""`ctgs fetch`: download a manifest's archives and extract the requested scenes into the data root.

Layout: DATA_ROOT/.downloads/<archive file> (kept, so fetching another scene of the same archive does
not download it again; --delete-archive removes it), DATA_ROOT/<dataset>/<scene>/ (the scene folder:
images*/ and sparse/0/). A scene is extracted into a temporary sibling and renamed into place, then
marked with `.ctgs-fetched.json`; a re-run skips marked scenes without touching the network.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from urllib.parse import urlparse

from ctgs.errors import UserError
from ctgs.io import atomic, owner
from ctgs.io.download import download
from ctgs.scene.manifests import data_root, load_manifest

MARKER = ".ctgs-fetched.json"


@dataclass
class FetchedScene:
    dataset: str
    scene: str
    path: str  # DATA_ROOT/<dataset>/<scene>
    images: str  # image folder to train/evaluate on, e.g. "images_4"
    holdout: int
    skipped: bool  # already there from an earlier run


def _safe_relative(member: str, prefix: str) -> PurePosixPath | None:
    """Path of archive `member` relative to the scene folder `prefix`, or None if outside it.
    Rejects absolute paths and '..' (zip-slip) so nothing is written outside the scene folder."""
    path = PurePosixPath(member.replace("\\", "/"))
    parts = path.parts
    prefix_parts = PurePosixPath(prefix).parts
    if parts[:len(prefix_parts)] != prefix_parts or len(parts) == len(prefix_parts):
        return None
    rel = PurePosixPath(*parts[len(prefix_parts):])
    if rel.is_absolute() or ".." in rel.parts:
        raise UserError(f"archive member {member!r}: unsafe path; the archive is corrupt or malicious")
    return rel


def _extract(archive: str, fmt: str, prefixes: dict[str, str], staging: dict[str, Path], quiet: bool) -> set[str]:
    """Extract members under each scene's prefix into its staging folder; returns scenes that got files."""
    # rich only where a progress bar is drawn
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn

    found: set[str] = set()
    try:
        if fmt == "zip":
            opened = zipfile.ZipFile(archive)
            members = [(info.filename, info.file_size, info.is_dir(), info) for info in opened.infolist()]
        else:
            opened = tarfile.open(archive)
            members = [(m.name, m.size, m.isdir(), m) for m in opened.getmembers() if m.isfile() or m.isdir()]
    except (zipfile.BadZipFile, tarfile.TarError, OSError) as exc:
        raise UserError(f"{archive}: cannot open the archive ({exc}); delete it and run again") from None
    with opened, Progress(TextColumn("extract {task.description}"), BarColumn(), DownloadColumn(),
                          transient=True, disable=quiet) as bar:
        wanted = []
        for name, size, is_dir, handle in members:
            for scene, prefix in prefixes.items():
                rel = _safe_relative(name, prefix)
                if rel is not None:
                    wanted.append((scene, rel, size, is_dir, handle))
        task = bar.add_task(os.path.basename(archive), total=sum(w[2] for w in wanted))
        for scene, rel, size, is_dir, handle in wanted:
            target = staging[scene] / rel
            found.add(scene)
            if is_dir:
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            source = opened.open(handle) if fmt == "zip" else opened.extractfile(handle)
            with source, open(target, "wb") as out:
                shutil.copyfileobj(source, out, 1 << 20)
            bar.advance(task, size)
    return found


def _archive_file(url: str, archive_name: str, fmt: str) -> str:
    base = os.path.basename(urlparse(url).path)
    return base or f"{archive_name}.{fmt}"


def fetch_dataset(dataset: str, scenes: list[str] | None = None, *, root: str | None = None,
                  manifest_dir: str | None = None, delete_archive: bool = False,
                  quiet: bool = False) -> list[FetchedScene]:
    """Fetch `scenes` (default: all) of `dataset`; idempotent. UserError on any failure."""
    manifest = load_manifest(dataset, manifest_dir)
    names = list(scenes) if scenes else list(manifest["scenes"])
    unknown = [s for s in names if s not in manifest["scenes"]]
    if unknown:
        raise UserError(f"{manifest['path']}: unknown scene(s) {', '.join(unknown)}; known: "
                        f"{', '.join(manifest['scenes'])}")
    base = data_root(root)
    dataset_dir = base / manifest["name"]
    results: dict[str, FetchedScene] = {}
    todo: dict[str, list[str]] = {}
    for scene in names:
        info = manifest["scenes"][scene]
        target = dataset_dir / scene
        done = (target / MARKER).is_file()
        results[scene] = FetchedScene(manifest["name"], scene, str(target), info["images"], info["holdout"], done)
        if not done:
            # a folder there that no fetch finished is the user's (a fetch builds beside it and renames when whole)
            owner.check_ours(str(target), "fetch", f"a scene `ctgs fetch {manifest['name']}` made")
            todo.setdefault(info["archive"], []).append(scene)

    for archive_name, archive_scenes in todo.items():
        archive = manifest["archives"][archive_name]
        dest = base / ".downloads" / _archive_file(archive["url"], archive_name, archive["format"])
        fetched = download(archive["url"], str(dest), size=archive["size"], sha256=archive["sha256"], quiet=quiet)
        # Each scene is built in a temporary sibling and renamed into place only if every scene of this
        # archive extracted and checked out.
        with contextlib.ExitStack() as stack:
            staging = {s: Path(stack.enter_context(owner.owned_dir(str(dataset_dir / s), "fetch")))
                       for s in archive_scenes}
            prefixes = {s: manifest["scenes"][s]["path"] for s in archive_scenes}
            found = _extract(str(dest), archive["format"], prefixes, staging, quiet)
            for scene in archive_scenes:
                prefix = prefixes[scene]
                if scene not in found:
                    raise UserError(f"{dest}: no folder {prefix}/ in the archive; fix scenes.{scene}.path in "
                                    f"{manifest['path']}")
                images = manifest["scenes"][scene]["images"]
                if not (staging[scene] / images).is_dir():
                    raise UserError(f"{dest}: {prefix}/{images}/ is missing from the archive; fix "
                                    f"scenes.{scene}.images in {manifest['path']}")
                atomic.write_json(str(staging[scene] / MARKER), {
                    "dataset": manifest["name"], "scene": scene, "url": archive["url"], "sha256": fetched.sha256,
                    "size": fetched.size}, indent=1)
        if delete_archive:
            for path in (dest, Path(str(dest) + ".sha256")):
                if path.exists():
                    path.unlink()
    return [results[s] for s in names]
