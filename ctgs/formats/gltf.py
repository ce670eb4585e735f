"""Textured-quad glTF binary (.glb): one quad per surfel, its texture in an atlas, for Blender and three.js.

Each surfel becomes a flat quad spanning +-3 standard deviations along its tangent axes (the renderer's
cutoff, rho <= 9), whose RGBA tile in a texture atlas bakes everything view-independent:
- RGB = clamp(0.5 + C0 * dc + bilerp(texture), 0, 1) at the tile pixel's centre (the renderer's colour
  without the view-dependent SH bands, which a textured mesh cannot carry; the renderer clamps at 0
  only, an 8-bit texture also at 1);
- A = min(0.99, opacity * exp(-rho / 2)), 0 beyond rho = 9 or below 1/255 (the renderer's alpha: the
  Gaussian falloff lives in the texture, the quad itself is a plain rectangle).
Tiles hold one pixel per texel across the quad (TILE_MIN..TILE_MAX pixels per axis; untextured surfels
get TILE_MIN for the falloff alone), with a 1-pixel gutter that repeats the edge colour at alpha 0 so
bilinear filtering never mixes neighbouring tiles' colours. Tiles are shelf-packed into atlas pages of
at most ATLAS_MAX pixels; each page is one PNG, one material and one mesh.

Materials are unlit (KHR_materials_unlit: the baked colours are final, a viewer must not shade them),
alphaMode BLEND, double-sided, sampled LINEAR without mipmaps (a mipmap would average across tiles).
Vertex positions are the model's world coordinates, unchanged (COLMAP's frame: glTF viewers take +y as up,
so SfM scenes may appear upside down or tilted; nothing is transformed so the file stays metric and exact).
The file carries no sorting: a viewer that blends transparent triangles in buffer order shows order
artefacts where quads overlap; sort back to front per view for a faithful image.

The glTF structure is built with pygltflib (the Khronos-listed Python glTF library) rather than packed by
hand; `read_glb` reads it back (tests, benchmarks/export_formats.py).
"""

from __future__ import annotations

import errno
import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.render.geometry import quat_to_rotmat
from ctgs.model.surfels import SurfelModel

SH_C0 = 0.28209479177387814
EXTENT_SIGMA = 3.0  # quad half-size in standard deviations: the renderer's cutoff (CUTOFF_RHO = 9)
CUTOFF_RHO = EXTENT_SIGMA**2
MAX_ALPHA = 0.99  # renderer constants (kernels/include/ctgs/constants.h)
MIN_ALPHA = 1.0 / 255.0
# Tile pixels per axis. 8 samples across +-3 sigma keep the Gaussian falloff within ~1% after bilinear
# filtering; 64 caps a single surfel's share of the atlas (texels finer than that are averaged away).
TILE_MIN, TILE_MAX = 8, 64
GUTTER = 1  # pixels around each tile (edge colour, alpha 0)
ATLAS_MAX = 4096  # page size limit: the largest texture size every desktop and mobile GPU accepts
PNG_LEVEL = 9  # zlib level of the atlas PNGs (export is offline: smallest file)
BAKE_CHUNK = 1 << 21  # tile pixels baked at once (bounds the temporaries to ~100 MB)
GENERATOR = "ctgs glb export (textured quads)"
UNLIT = "KHR_materials_unlit"
# glTF enums (the spec's numeric codes).
FLOAT, UINT16, UINT32 = 5126, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, CLAMP_TO_EDGE = 9729, 33071


@dataclass
class Page:
    """One atlas page as read back: quads (4 corners each, corner order (-u,-v) (+u,-v) (+u,+v) (-u,+v))."""

    positions: np.ndarray  # [Q, 4, 3] float32 world units
    uvs: np.ndarray  # [Q, 4, 2] float32, glTF convention (0, 0) = top-left of the image
    indices: np.ndarray  # [Q, 6] triangle vertex indices into the page's [4Q] vertices
    image: np.ndarray  # [H, W, 4] uint8 RGBA atlas


@dataclass
class GlbModel:
    pages: list[Page]
    material: dict  # the first material as JSON (alphaMode, doubleSided, extensions, ...)
    extras: dict  # asset.extras written by ctgs (counts, tile limits), {} for foreign files

    @property
    def num_quads(self) -> int:
        return sum(len(p.positions) for p in self.pages)


# ---- baking ----------------------------------------------------------------------------------------------
def tile_sizes(model: SurfelModel) -> np.ndarray:
    """[N, 2] int (width along u, height along v) tile pixels: one per texel across the quad, clamped."""
    extent = 2 * EXTENT_SIGMA * model.scales.detach().double()  # [N, 2] world units
    per_texel = torch.ceil(extent / model.texel_size.detach().double())  # [N, 2]
    textured = (model.tex_res.long().prod(1) > 0) & (model.texture_mode != "none")
    sizes = torch.where(textured[:, None], per_texel.clamp(TILE_MIN, TILE_MAX), torch.full_like(extent, TILE_MIN))
    return sizes.long().numpy()


def _texture_at(model: SurfelModel, prim: torch.Tensor, lx: torch.Tensor, ly: torch.Tensor) -> torch.Tensor:
    """[P, 3] bilinear texture value at local coordinates (lx, ly) (world units) of primitives `prim`,
    exactly as the renderer samples it (docs/reference/renderer.md step 5): taps outside the grid read 0."""
    res = model.tex_res.long()[prim]  # [P, 2]
    k = model.texel_size.detach().double()[prim]  # [P, 2]
    uu = lx / k[:, 0] + (res[:, 0] - 1) / 2
    vv = ly / k[:, 1] + (res[:, 1] - 1) / 2
    ok = torch.isfinite(uu) & torch.isfinite(vv) & (uu > -1) & (vv > -1) & (uu < res[:, 0]) & (vv < res[:, 1])
    ok &= (res.prod(1) > 0) & (model.texture_mode != "none")
    uu, vv = torch.where(ok, uu, 0.0), torch.where(ok, vv, 0.0)
    u0, v0 = torch.floor(uu).long(), torch.floor(vv).long()
    fu, fv = uu - u0, vv - v0
    textures = model.textures.detach().double()
    base = model.tex_offset.long()[prim]
    out = torch.zeros(len(prim), 3, dtype=torch.float64)
    for du, dv, w in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        iu, iv = u0 + du, v0 + dv
        tap = ok & (iu >= 0) & (iv >= 0) & (iu < res[:, 0]) & (iv < res[:, 1])
        rows = torch.where(tap, base + iv * res[:, 0] + iu, 0)
        out += torch.where(tap, w, 0.0)[:, None] * (textures[rows] if len(textures) else 0.0)
    return out


def bake_at(model: SurfelModel, prim: torch.Tensor, lx: torch.Tensor, ly: torch.Tensor) -> torch.Tensor:
    """[P, 4] float64 RGBA in [0, 1] baked for primitives `prim` [P] at local coordinates (lx, ly) [P]
    (world units along tangent u, v): the renderer's view-independent colour and its alpha."""
    scales = model.scales.detach().double()[prim]  # [P, 2]
    rho = (lx / scales[:, 0]) ** 2 + (ly / scales[:, 1]) ** 2
    alpha = torch.clamp(model.opacities.detach().double()[prim] * torch.exp(-0.5 * rho), max=MAX_ALPHA)
    alpha = torch.where((rho <= CUTOFF_RHO) & (alpha >= MIN_ALPHA), alpha, 0.0)
    base = 0.5 + SH_C0 * model.sh.detach().double()[prim, 0, :]  # [P, 3] the DC band only
    colour = (base + _texture_at(model, prim, lx, ly)).clamp(0.0, 1.0)
    return torch.cat([colour, alpha[:, None]], 1)


def bake_tiles(model: SurfelModel, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All tiles, row-major per surfel, concatenated: ([P, 4] uint8 RGBA, [N] start of each tile).
    Tile pixel (px, py) of a w x h tile samples local ((2px+1)/w - 1, (2py+1)/h - 1) * 3 sigma."""
    n = model.num_primitives
    counts = torch.from_numpy(sizes[:, 0] * sizes[:, 1])  # [N] pixels per tile
    starts = torch.cumsum(counts, 0) - counts
    total = int(counts.sum())
    rgba = np.zeros((total, 4), np.uint8)
    half = EXTENT_SIGMA * model.scales.detach().double()  # [N, 2] quad half-size, world units
    w_all, h_all = torch.from_numpy(sizes[:, 0]), torch.from_numpy(sizes[:, 1])
    prim_all = torch.repeat_interleave(torch.arange(n), counts)  # [P]
    for lo in range(0, total, BAKE_CHUNK):
        prim = prim_all[lo: lo + BAKE_CHUNK]
        local = torch.arange(lo, lo + len(prim)) - starts[prim]
        w, h = w_all[prim], h_all[prim]
        lx = ((2 * (local % w) + 1) / w - 1) * half[prim, 0]
        ly = ((2 * (local // w) + 1) / h - 1) * half[prim, 1]
        rgba[lo: lo + len(prim)] = torch.round(255 * bake_at(model, prim, lx, ly)).numpy()
    return rgba, starts.numpy()


# ---- packing ---------------------------------------------------------------------------------------------
def pack_shelves(cells: np.ndarray, width: int, max_height: int) -> tuple[np.ndarray, list[int]]:
    """Shelf packing of [N, 2] (w, h) cells into pages `width` wide and at most `max_height` high.

    Returns ([N, 3] (page, x, y) of each cell, height used on each page). Tallest cells first, so each
    shelf wastes little height.
    """
    order = np.lexsort((np.arange(len(cells)), -cells[:, 1]))
    place = np.zeros((len(cells), 3), np.int64)
    heights: list[int] = []
    page, x, y, shelf = 0, 0, 0, 0
    for i in order:
        w, h = int(cells[i, 0]), int(cells[i, 1])
        if x + w > width:  # next shelf
            x, y, shelf = 0, y + shelf, 0
        if y + h > max_height:  # next page
            heights.append(y)
            page, x, y, shelf = page + 1, 0, 0, 0
        place[i] = (page, x, y)
        x, shelf = x + w, max(shelf, h)
    heights.append(y + shelf)
    return place, heights


def _pow2(v: int) -> int:
    return 1 << max(0, math.ceil(math.log2(max(v, 1))))


def atlas_pages(model: SurfelModel) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Bake and pack: (page images [H, W, 4] uint8, [N, 3] (page, x, y) of each tile's first pixel,
    [N, 2] tile sizes)."""
    sizes = tile_sizes(model)
    rgba, starts = bake_tiles(model, sizes)
    cells = sizes + 2 * GUTTER
    width = min(ATLAS_MAX, _pow2(math.ceil(math.sqrt(float((cells[:, 0] * cells[:, 1]).sum())))))
    width = max(width, int(cells[:, 0].max()) if len(cells) else 1)
    place, heights = pack_shelves(cells, width, ATLAS_MAX)
    pages = [np.zeros((min(ATLAS_MAX, _pow2(h)), width, 4), np.uint8) for h in heights]
    for i, (page, x, y) in enumerate(place):
        w, h = sizes[i]
        tile = rgba[starts[i]: starts[i] + w * h].reshape(h, w, 4)
        cell = np.pad(tile, ((GUTTER, GUTTER), (GUTTER, GUTTER), (0, 0)), mode="edge")
        cell[:GUTTER, :, 3] = cell[-GUTTER:, :, 3] = cell[:, :GUTTER, 3] = cell[:, -GUTTER:, 3] = 0
        pages[page][y: y + h + 2 * GUTTER, x: x + w + 2 * GUTTER] = cell
    return pages, place + np.array([0, GUTTER, GUTTER]), sizes


def quad_corners(model: SurfelModel) -> np.ndarray:
    """[N, 4, 3] float32 corners (-u,-v) (+u,-v) (+u,+v) (-u,+v) at +-3 sigma, world units."""
    r = quat_to_rotmat(model.quats.detach().double())  # [N, 3, 3]
    half = EXTENT_SIGMA * model.scales.detach().double()  # [N, 2]
    du, dv = r[:, :, 0] * half[:, :1], r[:, :, 1] * half[:, 1:]  # [N, 3]
    m = model.means.detach().double()
    return torch.stack([m - du - dv, m + du - dv, m + du + dv, m - du + dv], 1).to(torch.float32).numpy()


# ---- writing ---------------------------------------------------------------------------------------------
def _encode_png(image: np.ndarray) -> bytes:
    # OpenCV takes a while to import: loaded only where an image is coded
    import cv2

    ok, buf = cv2.imencode(".png", image[..., [2, 1, 0, 3]], [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
    if not ok:
        raise RuntimeError("PNG encoding of the texture atlas failed")
    return buf.tobytes()


class _Blob:
    """The GLB binary chunk, built view by view (each view 4-byte aligned, as glTF requires)."""

    def __init__(self, gltf) -> None:
        self.gltf, self.parts, self.size = gltf, [], 0

    def view(self, data: bytes, target: int | None = None) -> int:
        # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
        import pygltflib as g

        pad = (-self.size) % 4
        self.parts.append(b"\0" * pad)
        self.size += pad
        self.gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=self.size, byteLength=len(data),
                                                  target=target))
        self.parts.append(data)
        self.size += len(data)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, component: int, kind: str, target: int, minmax: bool = False) -> int:
        # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
        import pygltflib as g

        view = self.view(array.tobytes(), target)
        extra = {"min": array.min(0).tolist(), "max": array.max(0).tolist()} if minmax else {}
        self.gltf.accessors.append(g.Accessor(bufferView=view, componentType=component, count=len(array),
                                              type=kind, **extra))
        return len(self.gltf.accessors) - 1

    def bytes(self) -> bytes:
        return b"".join(self.parts) + b"\0" * ((-self.size) % 4)


def build_gltf(model: SurfelModel, origin=None):
    """The pygltflib.GLTF2 document (with its binary blob set) of `model`. origin: [3] where the model's frame has its
    origin in the scene's COLMAP frame (a recentred scene): a root node translates the quads there (glTF keeps node
    translations as JSON numbers, so the full precision survives; the vertices stay float32 near the origin)."""
    # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
    import pygltflib as g

    pages, place, sizes = atlas_pages(model)
    corners = quad_corners(model)
    gltf = g.GLTF2(asset=g.Asset(generator=GENERATOR, version="2.0"), scene=0, extensionsUsed=[UNLIT],
                   samplers=[g.Sampler(magFilter=LINEAR, minFilter=LINEAR, wrapS=CLAMP_TO_EDGE, wrapT=CLAMP_TO_EDGE)])
    gltf.asset.extras = {"ctgs": {"quads": model.num_primitives, "tile_min": TILE_MIN, "tile_max": TILE_MAX,
                                  "extent_sigma": EXTENT_SIGMA, "pages": len(pages),
                                  "texture_mode": model.texture_mode}}
    blob = _Blob(gltf)
    nodes = []
    sign = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)  # corner -> (u, v) side of the tile
    for p, image in enumerate(pages):
        sel = np.nonzero(place[:, 0] == p)[0]
        h_img, w_img = image.shape[:2]
        uv = (place[sel, None, 1:] + sign[None] * sizes[sel, None, :]) / np.array([w_img, h_img])  # [Q, 4, 2]
        quads = len(sel)
        index_type, np_index = (UINT16, np.uint16) if 4 * quads <= 65535 else (UINT32, np.uint32)
        tri = (np.arange(quads)[:, None] * 4 + np.array([0, 1, 2, 0, 2, 3])).astype(np_index)  # [Q, 6]
        pos_acc = blob.accessor(corners[sel].reshape(-1, 3), FLOAT, "VEC3", ARRAY_BUFFER, minmax=True)
        uv_acc = blob.accessor(uv.reshape(-1, 2).astype(np.float32), FLOAT, "VEC2", ARRAY_BUFFER)
        idx_acc = blob.accessor(tri.reshape(-1), index_type, "SCALAR", ELEMENT_ARRAY_BUFFER)
        gltf.images.append(g.Image(bufferView=blob.view(_encode_png(image)), mimeType="image/png"))
        gltf.textures.append(g.Texture(sampler=0, source=p))
        gltf.materials.append(g.Material(
            name=f"surfels_{p}", alphaMode=g.BLEND, doubleSided=True, extensions={UNLIT: {}},
            pbrMetallicRoughness=g.PbrMetallicRoughness(baseColorTexture=g.TextureInfo(index=p),
                                                        metallicFactor=0.0, roughnessFactor=1.0)))
        gltf.meshes.append(g.Mesh(name=f"surfels_{p}", primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=pos_acc, TEXCOORD_0=uv_acc), indices=idx_acc, material=p)]))
        gltf.nodes.append(g.Node(mesh=p, name=f"surfels_{p}"))
        nodes.append(p)
    return finish(gltf, blob, nodes, origin)


def finish(gltf, blob: _Blob, nodes: list[int], origin=None):
    """Close a document: its scene of `nodes` (under a root node translating them to `origin`, a recentred scene's
    origin in the file's frame, when there is one) and its binary chunk. Returns the document."""
    # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
    import pygltflib as g

    if origin is not None and any(origin):
        gltf.nodes.append(g.Node(name="world_origin", translation=[float(x) for x in origin], children=nodes))
        nodes = [len(gltf.nodes) - 1]
    gltf.scenes = [g.Scene(nodes=nodes)]
    data = blob.bytes()
    gltf.buffers = [g.Buffer(byteLength=len(data))]
    gltf.set_binary_blob(data)
    return gltf


def write_glb(model: SurfelModel, path: str, origin=None) -> int:
    """Write `model` as a .glb (atomically: a temporary name, then renamed). Returns its bytes."""
    if model.num_primitives == 0:
        raise UserError(f"{path}: the model has no surfels; nothing to export")
    gltf = build_gltf(model, origin)
    with atomic.atomic_path(path) as tmp:
        # pygltflib reports a failed write by returning False, not by raising
        if not gltf.save_binary(tmp) or os.path.getsize(tmp) == 0:
            raise OSError(errno.EIO, "pygltflib could not write the file", path)
    return os.path.getsize(path)


# ---- reading ---------------------------------------------------------------------------------------------
def read_glb(path: str) -> GlbModel:
    """The quads, UVs and atlases of a .glb written by `write_glb` (every mesh primitive with POSITION,
    TEXCOORD_0, indices and a base colour texture); UserError naming the file otherwise."""
    # OpenCV takes a while to import: loaded only where an image is coded
    import cv2
    import pygltflib as g

    try:
        gltf = g.GLTF2().load(path)
    except Exception as exc:  # pygltflib raises bare Exceptions of several kinds on foreign bytes
        raise UserError(f"{path}: not a readable glTF binary ({type(exc).__name__}: {exc})") from exc
    blob = gltf.binary_blob()
    if blob is None:
        raise UserError(f"{path}: no binary chunk; pass a .glb written by `ctgs export --format glb`")
    np_types = {FLOAT: np.float32, UINT16: np.uint16, UINT32: np.uint32}
    widths = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}

    def accessor(i: int) -> np.ndarray:
        a = gltf.accessors[i]
        v = gltf.bufferViews[a.bufferView]
        dtype = np.dtype(np_types[a.componentType])
        start = (v.byteOffset or 0) + (a.byteOffset or 0)
        arr = np.frombuffer(blob, dtype, count=a.count * widths[a.type], offset=start)
        return arr.reshape(a.count, widths[a.type]) if widths[a.type] > 1 else arr

    pages = []
    for mesh in gltf.meshes:
        for prim in mesh.primitives:
            if prim.attributes.POSITION is None or prim.attributes.TEXCOORD_0 is None or prim.indices is None:
                raise UserError(f"{path}: a mesh primitive lacks POSITION, TEXCOORD_0 or indices; not a ctgs .glb")
            tex = gltf.materials[prim.material].pbrMetallicRoughness.baseColorTexture.index
            view = gltf.bufferViews[gltf.images[gltf.textures[tex].source].bufferView]
            png = blob[(view.byteOffset or 0): (view.byteOffset or 0) + view.byteLength]
            image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
            if image is None or image.ndim != 3 or image.shape[2] != 4:
                raise UserError(f"{path}: texture {tex} is not an RGBA PNG; not a ctgs .glb")
            pos = accessor(prim.attributes.POSITION)
            uvs = accessor(prim.attributes.TEXCOORD_0)
            pages.append(Page(positions=pos.reshape(-1, 4, 3), uvs=uvs.reshape(-1, 4, 2),
                              indices=accessor(prim.indices).reshape(-1, 6), image=image[..., [2, 1, 0, 3]]))
    material = gltf.materials[0].to_dict() if gltf.materials else {}
    extras = (gltf.asset.extras or {}).get("ctgs", {}) if isinstance(gltf.asset.extras, dict) else {}
    return GlbModel(pages=pages, material=material, extras=extras)
