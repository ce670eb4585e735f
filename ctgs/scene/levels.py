"""Image levels a scene lacks: `--images images_N` made from `images/` the way `ctgs sfm` makes its pyramid.

A benchmark scene often ships some levels only (Mip-NeRF 360 has images_2/4/8; a local copy may have fewer), and a
run asks for the one the protocol or the machine needs. The level is made once, by the same resampling as `ctgs sfm`
(OpenImageIO's antialiased Lanczos-3 filter, ctgs.io.images.resize_image, to round(W / N) x round(H / N), same file
names and bit depth), and kept: in the scene folder when it is writable, else in the cache (CTGS_CACHE_DIR,
~/.cache/ctgs) under a key of the scene's path and photos. It is written under a temporary name and renamed when
complete, so a killed run leaves no half level, and two runs that make the same level at once both use the one
renamed into place first.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
import tempfile

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.io.images import image_info, list_images, read_image, resize_image, write_image
from ctgs.resources import cache_dir

LEVEL = re.compile(r"^images_([1-9][0-9]*)$")


def _cached_dir(scene_dir: str, names: list[str], src: str) -> str:
    """The cache folder of this scene's levels: keyed by its path and its photos (name, size, mtime)."""
    h = hashlib.sha256(os.path.abspath(scene_dir).encode())
    for name in names:
        st = os.stat(os.path.join(src, name))
        h.update(f"{name}\0{st.st_size}\0{int(st.st_mtime)}\n".encode())
    return os.path.join(cache_dir(), "levels", f"{os.path.basename(os.path.abspath(scene_dir))}-{h.hexdigest()[:16]}")


def _writable(folder: str) -> bool:
    try:
        probe = tempfile.mkdtemp(prefix=".ctgs-probe-", dir=folder)
    except OSError:
        return False
    os.rmdir(probe)
    return True


def make_level(src: str, dst: str, factor: int, names: list[str]) -> None:
    """dst/<name> for each photo of src, shrunk by `factor`; written to a hidden sibling (ctgs.io.atomic: swept when a
    killed run left it), renamed when complete."""
    with atomic.atomic_dir(dst, replace=False) as tmp:
        for name in names:
            path = os.path.join(src, name)
            bits = 16 if image_info(path).format == "uint16" else 8
            pixels = read_image(path)
            h, w = pixels.shape[:2]
            small = resize_image(pixels, max(1, round(w / factor)), max(1, round(h / factor)))
            write_image(os.path.join(tmp, name), small, bits=bits)


def level_dir(scene_dir: str, images: str, quiet: bool = False) -> str | None:
    """The folder holding `images` for this scene: scene_dir/images if it exists; for a missing images_N with an
    images/ folder beside it, the level made from images/ (in the scene if writable, else in the cache; made now if
    not made before). None when neither applies (the caller says what is missing)."""
    direct = os.path.join(scene_dir, images)
    if os.path.isdir(direct):
        return direct
    m = LEVEL.match(images)
    src = os.path.join(scene_dir, "images")
    if m is None or not os.path.isdir(src):
        return None
    factor = int(m.group(1))
    names = list_images(src)
    if not names:
        raise UserError(f"{src}: no images to make {images} from; restore the photos or pass an existing --images")
    dst = direct if _writable(scene_dir) else os.path.join(_cached_dir(scene_dir, names, src), images)
    if not os.path.isdir(dst):
        if not quiet:
            print(f"ctgs: {scene_dir} has no {images}: making it from images/ ({len(names)} photos shrunk {factor}x, "
                  f"as `ctgs sfm` does) in {dst}", file=sys.stderr)
        try:
            make_level(src, dst, factor, names)  # a full disk or a read-only cache: the CLI's one line names dst
        except FileExistsError:
            if not os.path.isdir(dst):
                raise
            # another run made it first (two trainings started together on a scene lacking the level): that one is
            # complete, since levels appear only by a rename, and made from the same photos the same way
    return dst
