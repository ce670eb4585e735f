"""The web bundle that `ctgs view` serves (spec: docs/reference/model_format.md, "Web bundle").

A folder of plain little-endian arrays a browser can upload to WebGL2 textures without parsing:
bundle.json (layout, cameras), surfels.bin (per-surfel arrays, activated values), atlas_NNN.bin (the
jagged textures packed into square power-of-two pages, one texel = 3 signed 8-bit or 3 half floats).

`write_web_bundle` writes one from a SurfelModel; `read_web_bundle` decodes one back into renderer
inputs (textures as stored, i.e. quantised), so the bundle can be checked against the model without a
browser.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io import atomic, owner
from ctgs.io.versioned import VersionedJson
from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.render.types import SurfelInputs
from ctgs.scene.loader import load_scene

BUNDLE_FORMAT = "ctgs-web"
BUNDLE_VERSION = 1
BUNDLE_JSON = "bundle.json"
SURFELS_BIN = "surfels.bin"
WEB_SUBDIR = "web"  # `ctgs export --format web` puts the bundle in MODEL_DIR/web
# 2048 is the largest texture side every WebGL2 implementation must support (MAX_TEXTURE_SIZE >= 2048).
DEFAULT_PAGE_SIZE = 2048
# Texel encodings: signed normalised bytes (q/127, q in [-127, 127]; 0 exact, step 1/127, so at most
# 1/254 off) or IEEE half floats (relative 2^-11, at most ~4.9e-4 off in [-1, 1]).
TEXEL_FORMATS = {8: "snorm8", 16: "float16"}
SNORM8_MAX = 127
# Arrays start on 8-byte boundaries so any typed-array view (Float32Array, Uint16Array) can alias them.
ALIGN = 8


@dataclass
class AtlasLayout:
    """Where each surfel's texture lies in the atlas: texel (iu, iv) of surfel i is at column x[i] + iu,
    row y[i] + iv of page page[i]."""

    pos: np.ndarray  # [N, 3] int64 (x, y, page); zeros for surfels without texture
    page_rows: list[int]  # rows used on each page (pages are stored only up to that row)
    page_size: int


def pack_atlas(res: np.ndarray, page_size: int = DEFAULT_PAGE_SIZE) -> AtlasLayout:
    """Pack the rectangles res [N, 2] (res_u = width, res_v = height, texels) into square pages.

    Shelves with columns: rectangles come tallest first; each opens a column on the current shelf (a
    new shelf, or a new page, when the row is full), and shorter ones that follow stack inside the open
    column while they fit its width and the shelf's height. Textures are small (tens to a few hundred
    texels), so this leaves little more than the shelves' ragged tops unused.
    """
    res = np.asarray(res, dtype=np.int64).reshape(-1, 2)
    used = (res[:, 0] > 0) & (res[:, 1] > 0)
    too_big = used & ((res[:, 0] > page_size) | (res[:, 1] > page_size))
    if too_big.any():
        i = int(np.flatnonzero(too_big)[0])
        raise UserError(f"surfel {i}: texture of {res[i, 0]}x{res[i, 1]} texels does not fit an atlas page of "
                        f"{page_size}x{page_size}; pass a larger --page-size (a power of two)")
    pos = np.zeros((len(res), 3), dtype=np.int64)
    order = np.lexsort((-res[:, 0], -res[:, 1]))  # height desc, then width desc
    order = order[used[order]]
    page_rows: list[int] = []
    page = -1
    shelf_y = shelf_h = 0  # current shelf: top row, height
    x = 0  # first free column of the shelf
    col_x = col_w = col_y = 0  # open column: left, width, rows used
    for i in order.tolist():
        w, h = int(res[i, 0]), int(res[i, 1])
        if page >= 0 and w <= col_w and col_y + h <= shelf_h:  # stack in the open column
            pos[i] = (col_x, shelf_y + col_y, page)
            col_y += h
            continue
        if page < 0 or x + w > page_size:  # next shelf
            shelf_y += shelf_h
            x, shelf_h = 0, h
            if page < 0 or shelf_y + h > page_size:  # next page
                page += 1
                page_rows.append(0)
                shelf_y = 0
        col_x, col_w, col_y = x, w, h
        pos[i] = (x, shelf_y, page)
        x += w
        page_rows[page] = max(page_rows[page], shelf_y + h)
    return AtlasLayout(pos=pos, page_rows=page_rows, page_size=page_size)


def _encode_texels(values: np.ndarray, bits: int) -> np.ndarray:
    """Activated texel offsets [..., 3] in [-1, 1] -> stored texels (int8 snorm or float16)."""
    if bits == 8:
        return np.clip(np.rint(values * SNORM8_MAX), -SNORM8_MAX, SNORM8_MAX).astype(np.int8)
    return values.astype(np.float16)


def _decode_texels(stored: np.ndarray) -> np.ndarray:
    if stored.dtype == np.int8:
        return stored.astype(np.float32) / SNORM8_MAX
    return stored.astype(np.float32)


def atlas_pages(textures: np.ndarray, res: np.ndarray, offsets: np.ndarray, layout: AtlasLayout,
                bits: int) -> list[np.ndarray]:
    """The atlas pages [rows_p, page_size, 3] (stored dtype) holding textures [T, 3] (activated).

    Vectorised over texels: texel j of surfel i (iu = j % res_u, iv = j // res_u) goes to
    (page_i, y_i + iv, x_i + iu). Texels of no surfel (gaps in the jagged array) are dropped.
    """
    res = res.astype(np.int64)
    sizes = res[:, 0] * res[:, 1]
    owner = np.repeat(np.arange(len(res)), sizes)  # [T'] surfel of each used texel
    local = np.arange(len(owner)) - np.repeat(np.cumsum(sizes) - sizes, sizes)  # index inside its texture
    src = offsets.astype(np.int64)[owner] + local
    iu, iv = local % res[owner, 0], local // res[owner, 0]
    page = layout.pos[owner, 2]
    row = layout.pos[owner, 1] + iv
    col = layout.pos[owner, 0] + iu
    stored = _encode_texels(textures[src], bits)
    pages = []
    for p, rows in enumerate(layout.page_rows):
        buf = np.zeros((rows, layout.page_size, 3), dtype=stored.dtype)
        sel = page == p
        buf[row[sel], col[sel]] = stored[sel]
        pages.append(buf)
    return pages


def cameras_from_views(views: list, split: str) -> list[dict]:
    """ctgs.scene View list -> bundle cameras (intrinsics in pixels, viewmat world->camera row-major)."""
    out = []
    for v in views:
        c = v.camera
        out.append({"name": v.name, "split": split, "width": int(c.width), "height": int(c.height),
                    "fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy),
                    "near": float(c.near),
                    "viewmat": [float(a) for a in c.viewmat.detach().cpu().double().reshape(-1).tolist()]})
    return out


def scene_cameras(scene_dir: str, images: str = "images", holdout: int = 8) -> list[dict]:
    """Every training and test camera of a scene folder, training first, at the size of `images`."""
    if not os.path.isdir(os.path.join(scene_dir, images)):
        images = "images"  # a scene moved elsewhere may lack the downscaled folder the run trained on
    scene = load_scene(scene_dir, images=images, holdout=holdout, load_images=False)
    return cameras_from_views(scene.train, "train") + cameras_from_views(scene.test, "test")


def _surfel_arrays(model: SurfelModel, layout: AtlasLayout, res: np.ndarray) -> dict[str, np.ndarray]:
    """name -> array, activated values (what the renderer consumes), in bundle dtypes."""
    with torch.no_grad():
        q = model.quats.detach().double()
        q = q / q.norm(dim=-1, keepdim=True)
        k = (int(model.sh_degree) + 1) ** 2
        arrays = {
            "means": model.means.detach().float().cpu().numpy(),  # [N, 3] float32
            "quats": q.float().cpu().numpy(),  # [N, 4] float32, unit (w, x, y, z)
            "scales": model.scales.detach().float().cpu().numpy(),  # [N, 2] float32
            "opacities": model.opacities.detach().float().cpu().numpy(),  # [N] float32
            "texel_size": model.texel_size.detach().float().cpu().numpy(),  # [N, 2] float32
            "tex_res": res.astype(np.uint16),  # [N, 2] uint16
            "atlas_pos": layout.pos.astype(np.uint16),  # [N, 3] uint16 (x, y, page)
            "sh": model.sh[:, :k].detach().cpu().numpy().astype(np.float16),  # [N, K, 3] float16
        }
    if not np.isfinite(arrays["sh"]).all():
        raise UserError("the model's SH coefficients exceed the float16 range of the web bundle")
    return {name: np.ascontiguousarray(a) for name, a in arrays.items()}


def write_web_bundle(model: SurfelModel, out_dir: str, cameras: list[dict], *, texel_bits: int = 8,
                     page_size: int = DEFAULT_PAGE_SIZE, background=(0.0, 0.0, 0.0),
                     extra: dict | None = None) -> dict:
    """Write the bundle folder `out_dir` (replaced atomically). Returns bundle.json's content."""
    if texel_bits not in TEXEL_FORMATS:
        raise UserError(f"texel bits must be one of {sorted(TEXEL_FORMATS)}, got {texel_bits}")
    if page_size < 1 or page_size & (page_size - 1) or page_size > 16384:
        raise UserError(f"atlas page size must be a power of two <= 16384, got {page_size}")
    model.validate()
    n = model.num_primitives
    res = model.tex_res.detach().cpu().numpy().astype(np.int64)
    if model.texture_mode == "none":
        res = np.zeros_like(res)
    res[(res[:, 0] <= 0) | (res[:, 1] <= 0)] = 0
    layout = pack_atlas(res, page_size)
    if len(layout.page_rows) > np.iinfo(np.uint16).max:
        raise UserError(f"{len(layout.page_rows)} atlas pages exceed 65535; pass a larger --page-size")
    textures = model.textures.detach().float().cpu().numpy()  # [T, 3] activated, [-1, 1]
    pages = atlas_pages(textures, res, model.tex_offset.detach().cpu().numpy(), layout, texel_bits)
    arrays = _surfel_arrays(model, layout, res)

    owner.check_ours(out_dir, "web", "an earlier ctgs web bundle", legacy=_legacy_bundle)
    # Built in a hidden sibling that replaces OUT_DIR whole when complete, with the modes of every other output
    # (the bundle is served to a browser and may be copied to a web server: readable by others, not 0700).
    with owner.owned_dir(out_dir, "web") as tmp:
        layout_json, offset = {}, 0
        with open(os.path.join(tmp, SURFELS_BIN), "wb") as f:
            for name, a in arrays.items():
                pad = (-offset) % ALIGN
                f.write(b"\0" * pad)
                offset += pad
                layout_json[name] = {"offset": offset, "dtype": str(a.dtype), "shape": list(a.shape)}
                f.write(a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes())
                offset += a.nbytes
        page_json = []
        for p, buf in enumerate(pages):
            name = f"atlas_{p:03d}.bin"
            with open(os.path.join(tmp, name), "wb") as f:
                f.write(buf.astype(buf.dtype.newbyteorder("<"), copy=False).tobytes())
            page_json.append({"file": name, "rows": int(buf.shape[0]), "bytes": int(buf.nbytes)})
        used_texels = int((res[:, 0] * res[:, 1]).sum())
        atlas_bytes = sum(p["bytes"] for p in page_json)
        means = arrays["means"].astype(np.float64)
        center = np.median(means, 0) if n else np.zeros(3)
        bundle = {
            "format": BUNDLE_FORMAT,
            "version": BUNDLE_VERSION,
            "num_surfels": n,
            "num_texels": used_texels,
            "sh_degree": int(model.sh_degree),
            "texture_mode": model.texture_mode,
            "background": [float(b) for b in background],
            "surfels": {"file": SURFELS_BIN, "bytes": offset, "arrays": layout_json},
            "atlas": {"page_size": page_size, "texel_format": TEXEL_FORMATS[texel_bits], "channels": 3,
                      "pages": page_json, "bytes": atlas_bytes,
                      "fill": used_texels / max(1, sum(page_size * p["rows"] for p in page_json))},
            "cameras": cameras,
            "center": [float(c) for c in center],
            "bytes_per_surfel": offset / max(1, n),
            "bytes_per_texel": atlas_bytes / max(1, used_texels),
            **(extra or {}),
        }
        with open(os.path.join(tmp, BUNDLE_JSON), "w") as f:
            json.dump(bundle, f, indent=1)
        for name in os.listdir(tmp):
            os.chmod(os.path.join(tmp, name), atomic.FILE_MODE)
    return bundle


_ATLAS_PAGE = re.compile(r"^atlas_\d{3,}\.bin$")


def is_bundle(folder: str) -> bool:
    """Whether `folder` is a web bundle ctgs wrote (marked, or from before folders were marked: its names only)."""
    if not os.path.isdir(folder):
        return False
    return owner.kind_of(folder) == "web" or _legacy_bundle(os.listdir(folder))


def _legacy_bundle(names: list[str]) -> bool:
    return BUNDLE_JSON in names and all(n in (BUNDLE_JSON, SURFELS_BIN) or _ATLAS_PAGE.match(n) for n in names)


BUNDLE_FILE = VersionedJson(
    BUNDLE_JSON, BUNDLE_FORMAT, (BUNDLE_VERSION,),
    missing=f"{{folder}}: no {BUNDLE_JSON}; write one with `ctgs export RUN_DIR --format web`",
    unreadable="{path}: unreadable ({exc}); re-export with `ctgs export --format web`",
    other_format="{path}: not a ctgs web bundle; re-export with `ctgs export --format web`",
    other_version=f"{{path}}: web bundle version {{version}}, this ctgs reads {BUNDLE_VERSION}; "
                  "re-export with `ctgs export --format web`")


def read_bundle_json(bundle_dir: str) -> dict:
    bundle = BUNDLE_FILE.read(bundle_dir)
    _check_bundle_files(bundle_dir, bundle, os.path.join(bundle_dir, BUNDLE_JSON))
    return bundle


def _check_bundle_files(bundle_dir: str, bundle: dict, path: str) -> None:
    """UserError naming the file when a data file is missing, or not the size bundle.json gives it (cut short, or
    from another export): the browser would otherwise fail on it with a message the user never sees."""
    try:
        files = [(bundle["surfels"]["file"], int(bundle["surfels"]["bytes"]))]
        files += [(p["file"], int(p["bytes"])) for p in bundle["atlas"]["pages"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: incomplete bundle description ({type(exc).__name__}: {exc}); re-export with "
                        "`ctgs export --format web`") from None
    for name, size in files:
        if not isinstance(name, str) or os.path.basename(name) != name or name.startswith("."):
            raise UserError(f"{path}: names the data file {name!r}, not a file of the bundle folder; re-export with "
                            "`ctgs export --format web`")
        file = os.path.join(bundle_dir, name)
        if not os.path.isfile(file):
            raise UserError(f"{file}: missing from the web bundle; re-export with `ctgs export --format web`")
        if os.path.getsize(file) != size:
            raise UserError(f"{file}: {os.path.getsize(file)} bytes, {BUNDLE_JSON} says {size}: cut short or from "
                            "another export; re-export with `ctgs export --format web`")


def read_web_bundle(bundle_dir: str) -> tuple[SurfelInputs, dict]:
    """Decode a bundle into renderer inputs (float32; textures as stored, jagged in surfel order)."""
    bundle = read_bundle_json(bundle_dir)
    with open(os.path.join(bundle_dir, bundle["surfels"]["file"]), "rb") as f:
        raw = f.read()
    arr = {}
    for name, spec in bundle["surfels"]["arrays"].items():
        dt = np.dtype(spec["dtype"]).newbyteorder("<")
        count = int(np.prod(spec["shape"]))
        arr[name] = np.frombuffer(raw, dtype=dt, count=count, offset=spec["offset"]).reshape(spec["shape"])
    atlas = bundle["atlas"]
    dt = np.int8 if atlas["texel_format"] == "snorm8" else np.float16
    pages = []
    for p in atlas["pages"]:
        data = np.fromfile(os.path.join(bundle_dir, p["file"]), dtype=np.dtype(dt).newbyteorder("<"))
        pages.append(data.reshape(p["rows"], atlas["page_size"], 3))
    res = arr["tex_res"].astype(np.int64)
    sizes = res[:, 0] * res[:, 1]
    owner = np.repeat(np.arange(len(res)), sizes)
    local = np.arange(len(owner)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    pos = arr["atlas_pos"].astype(np.int64)
    rows, cols, page = pos[owner, 1] + local // res[owner, 0], pos[owner, 0] + local % res[owner, 0], pos[owner, 2]
    textures = np.zeros((len(owner), 3), dtype=np.float32)
    for p, buf in enumerate(pages):
        sel = page == p
        textures[sel] = _decode_texels(buf[rows[sel], cols[sel]])
    tres = torch.from_numpy(res.astype(np.int32))
    f32 = lambda a: torch.from_numpy(np.array(a, dtype=np.float32))  # noqa: E731
    inputs = SurfelInputs(means=f32(arr["means"]), quats=f32(arr["quats"]), scales=f32(arr["scales"]),
                          opacities=f32(arr["opacities"]), sh=f32(arr["sh"]), texel_size=f32(arr["texel_size"]),
                          textures=torch.from_numpy(textures), tex_res=tres, tex_offset=jagged_offsets(tres))
    return inputs, bundle
