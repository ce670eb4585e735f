"""Make helper: `python -m ctgs.scene.scene_vars SCENE` prints `DATASET IMAGES HOLDOUT PATH` for a scene (PATH: the
scene's folder inside the dataset's archive, e.g. db/playroom, where a data root laid out as the archive holds it).

The Makefile's per-scene rules read the dataset, image folder and holdout from data_manifests/ through
this, so the facts live in one place (ctgs.scene.manifests parses and validates the manifests). A scene
no manifest lists is an error naming the known scenes, never a guess: training an unknown scene on
`images/` with holdout 8 would give numbers that silently disagree with the paper's protocol.
"""

from __future__ import annotations

import sys

from ctgs.errors import UserError
from ctgs.scene.manifests import available, load_manifest, manifest_dir


def scene_vars(scene: str, manifests: str | None = None) -> tuple[str, str, int]:
    """(dataset, image folder, holdout) of `scene`; UserError if no manifest (or more than one) lists it."""
    return scene_facts(scene, manifests)[:3]


def scene_facts(scene: str, manifests: str | None = None) -> tuple[str, str, int, str]:
    """(dataset, image folder, holdout, folder inside the dataset's archive) of `scene`; UserError as scene_vars."""
    known: dict[str, list[str]] = {}  # scene -> datasets listing it
    found = []
    for name in available(manifests):
        manifest = load_manifest(name, manifests)
        for sname, info in manifest["scenes"].items():
            known.setdefault(sname, []).append(manifest["name"])
            if sname == scene:
                found.append((manifest["name"], info["images"], int(info["holdout"]), info["path"]))
    folder = manifest_dir(manifests)
    if not found:
        listing = ", ".join(sorted(known)) or "none"
        raise UserError(f"{folder}: no manifest lists a scene {scene!r}; known scenes: {listing} "
                        f"(add the scene to a data_manifests/<dataset>.toml to use it)")
    if len(found) > 1:
        raise UserError(f"{folder}: scene {scene!r} is listed by several datasets ({', '.join(known[scene])}); "
                        "rename it in one manifest")
    return found[0]


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m ctgs.scene.scene_vars SCENE", file=sys.stderr)
        return 2
    try:
        print(*scene_facts(argv[0]))
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
