"""PlayCanvas's two Gaussian formats, what SuperSplat, the PlayCanvas engine and `splat-transform` read.

Both hold what the 3DGS PLY holds (ctgs.formats.plain_ply: the texture folded into one colour per surfel, the flat axis
a third scale of FLAT_SCALE_RATIO x the smaller tangent one), quantised, in the same frame as the 3DGS PLY (the
COLMAP frame, right-down-front: no axis change), and both are tagged as 2DGS models (`SplatRenderMode: 2dgs` in the
PLY header, Brush's convention; `"model": "2dgs"` in SOG's meta.json), which tells a viewer that knows 2DGS to
ignore the third scale. Splats are written in Morton order of their centres (what the formats' own writers do:
neighbours in the file are neighbours in space, so each chunk's bounds are tight and the images compress).

Compressed PLY (`.compressed.ply`, 16 bytes per splat plus the SH bands at 1 byte per coefficient): three PLY
elements, `chunk` (per 256 splats, float bounds: min/max of x y z, of the three log scales and of the DC colour
0.5 + C0 * dc), `vertex` (four uint32 per splat) and, with SH, `sh` (uchar f_rest_*, channel-major as in the 3DGS
PLY, the rendered bands only):

| word | bits | value |
| --- | --- | --- |
| packed_position | 11 / 10 / 11 | x, y, z within the chunk's bounds |
| packed_rotation | 2 + 3 x 10 | index of the largest of (w, x, y, z), made positive; the other three x 1/sqrt2 + 0.5 |
| packed_scale | 11 / 10 / 11 | the three log scales within the chunk's bounds |
| packed_color | 8 / 8 / 8 / 8 | DC colour within the chunk's bounds, then sigmoid(opacity) |
| f_rest_i | 8 | floor(256 (v / 8 + 0.5)), read back as (b + 0.5) / 256 (0 and 255: the ends) |

SOG (`.sog`, version 2: a zip of meta.json and lossless WebP images, one pixel per splat in each):
`means_l` / `means_u` the low and high bytes of 16-bit x y z, each the log transform sign(x) ln(1 + |x|) within
meta's mins / maxs; `quats` the smallest three of (w, x, y, z) as 8-bit (q sqrt2 + 1) / 2 with 252 + the largest's
index in alpha; `scales` three indices into a 256-entry codebook of log scales; `sh0` three indices into a 256-entry
codebook of DC coefficients and 8-bit sigmoid(opacity); with SH, `shN_labels` a 16-bit index per splat into a
palette of SH rows (K-means, up to 64k entries), stored in `shN_centroids` as indices into a third 256-entry
codebook. The codebooks are 1-D K-means (ctgs.formats.kmeans.scalar_kmeans). The palette holds the distinct SH rows
themselves while they fit its 65,536 entries (no K-means, no loss beyond the codebook; a baked model's texel splats
share their surfel's SH rows), else a vector K-means of them into 65,536 (ctgs.formats.kmeans.vector_kmeans). Lossless WebP keeps every pixel, except the colour of a splat whose 8-bit opacity
is 0 (the encoder may drop colour under zero alpha): such a splat draws nothing, whatever its colour.

The readers here give the model back as untextured surfels (what a viewer gets); tests/formats/test_playcanvas.py
checks both files against PlayCanvas's own reader (`splat-transform`).
"""

from __future__ import annotations

import json
import math
import os
import zipfile

import numpy as np
import torch

from ctgs import __version__
from ctgs.errors import UserError
from ctgs.formats.kmeans import scalar_kmeans, vector_kmeans
from ctgs.formats.plain_ply import SH_C0, gaussian_view, surfels_from_gaussians
from ctgs.formats.splat import ALPHA_EPS
from ctgs.io import atomic
from ctgs.model.surfels import SurfelModel

CHUNK = 256  # splats per compressed-PLY chunk
CHUNK_PROPS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
               "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
               "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
VERTEX_PROPS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
MODEL_COMMENT = "SplatRenderMode: 2dgs"
SCALE_CLAMP = 20.0  # PlayCanvas's writer clamps chunk scale bounds to +-20 (log units): so do we
TINY_RANGE = 1e-5  # below this a chunk's range is taken as empty (every value at its min), as PlayCanvas does
SOG_VERSION = 2
SOG_FILES = {"means": ["means_l.webp", "means_u.webp"], "quats": ["quats.webp"], "scales": ["scales.webp"],
             "sh0": ["sh0.webp"], "shN": ["shN_centroids.webp", "shN_labels.webp"]}
SH_REST = {0: 0, 1: 3, 2: 8, 3: 15}  # SH coefficients per channel past the DC, by degree
PALETTE_MAX = 64 * 1024


# ---------------------------------------------------------------- what both formats hold

def gaussian_table(model: SurfelModel) -> dict:
    """ctgs.formats.plain_ply.gaussian_view of `model` (what both formats hold), in Morton order of the centres."""
    g = gaussian_view(model)
    order = morton_order(g["means"])
    return {key: value if key == "degree" else value[order] for key, value in g.items()}


def morton_order(points: np.ndarray) -> np.ndarray:
    """[N] permutation putting `points` [N, 3] in Morton (Z-curve) order over their bounding box, 21 bits per axis."""
    lo, hi = points.min(0), points.max(0)
    cells = np.round((points - lo) / np.where(hi > lo, hi - lo, 1.0) * (2**21 - 1)).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(21):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def _smallest_three(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions [N, 4] -> (index of the largest |component| [N], the other three in order [N, 3]), the sign
    chosen so that the largest is positive (q and -q are one rotation)."""
    largest = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    keep = np.ones_like(q, dtype=bool)
    keep[np.arange(len(q)), largest] = False
    return largest, q[keep].reshape(-1, 3)


def _from_smallest_three(largest: np.ndarray, three: np.ndarray) -> np.ndarray:
    """The inverse of _smallest_three: [N, 4] quaternions (w, x, y, z), the largest rebuilt as sqrt(1 - rest^2)."""
    q = np.zeros((len(largest), 4))
    keep = np.ones_like(q, dtype=bool)
    keep[np.arange(len(q)), largest] = False
    q[keep] = three.reshape(-1)
    q[np.arange(len(q)), largest] = np.sqrt(np.clip(1.0 - (three**2).sum(1), 0.0, None))
    return q


def _surfels(means, log_scales, quats, opacity, dc, rest) -> SurfelModel:
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    alpha = np.clip(opacity, ALPHA_EPS, 1 - ALPHA_EPS)
    return surfels_from_gaussians(t(means), t(log_scales), t(quats), t(np.log(alpha / (1 - alpha))),
                                  t(np.concatenate([dc[:, None], rest], 1)))


# ---------------------------------------------------------------- compressed PLY

def _unorm(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: int) -> np.ndarray:
    """x within [lo, hi] (broadcast) as round((x - lo) / (hi - lo) * (2^bits - 1)); a range under TINY_RANGE -> 0."""
    span = hi - lo
    t = np.where(span < TINY_RANGE, 0.0, (x - lo) / np.where(span < TINY_RANGE, 1.0, span))
    top = (1 << bits) - 1
    return np.clip(np.floor(np.clip(t, 0.0, 1.0) * top + 0.5), 0, top).astype(np.uint32)


def _chunk_bounds(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x [N, C] -> min and max [chunks, C] over each CHUNK rows."""
    n = len(x)
    pad = (-n) % CHUNK
    padded = np.concatenate([x, np.repeat(x[-1:], pad, 0)]) if pad else x  # the last splat repeated, as PlayCanvas
    blocks = padded.reshape(-1, CHUNK, x.shape[1])
    return blocks.min(1), blocks.max(1)


def compressed_ply_bytes(model: SurfelModel, origin=None) -> tuple[bytes, dict]:
    """The .compressed.ply file of `model`, and {"splats", "sh_degree"}. origin: as in the 3DGS PLY
    (ctgs.formats.plain_ply.write_plain_ply), a header comment `world_origin X Y Z` for a recentred scene."""
    g = gaussian_table(model)
    n, degree = len(g["means"]), g["degree"]
    colour = 0.5 + SH_C0 * g["dc"]
    chunk_of = np.arange(n) // CHUNK
    pmin, pmax = _chunk_bounds(g["means"])
    smin, smax = _chunk_bounds(g["log_scales"])
    smin, smax = np.clip(smin, -SCALE_CLAMP, SCALE_CLAMP), np.clip(smax, -SCALE_CLAMP, SCALE_CLAMP)
    cmin, cmax = _chunk_bounds(colour)
    chunks = np.concatenate([pmin, pmax, smin, smax, cmin, cmax], 1).astype("<f4")

    def pack111011(x, lo, hi):
        u = [_unorm(x[:, i], lo[chunk_of, i], hi[chunk_of, i], b) for i, b in enumerate((11, 10, 11))]
        return (u[0] << 21) | (u[1] << 11) | u[2]

    largest, three = _smallest_three(g["quats"])
    rot = largest.astype(np.uint32)
    for i in range(3):
        rot = (rot << 10) | _unorm(three[:, i] / math.sqrt(2.0) + 0.5, np.zeros(1), np.ones(1), 10)
    rgba = [_unorm(colour[:, i], cmin[chunk_of, i], cmax[chunk_of, i], 8) for i in range(3)]
    rgba.append(_unorm(g["opacity"], np.zeros(1), np.ones(1), 8))
    vertex = np.stack([pack111011(g["means"], pmin, pmax), rot, pack111011(g["log_scales"], smin, smax),
                       (rgba[0] << 24) | (rgba[1] << 16) | (rgba[2] << 8) | rgba[3]], 1).astype("<u4")
    r = SH_REST[degree]
    rest = g["rest"].transpose(0, 2, 1).reshape(n, 3 * r)  # channel-major, as f_rest_* in the 3DGS PLY
    sh = np.clip(np.floor((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)
    header = ["ply", "format binary_little_endian 1.0", "comment ctgs: textures folded into one colour per surfel",
              f"comment {MODEL_COMMENT}"]
    if origin is not None and any(origin):
        header.append("comment world_origin " + " ".join(repr(float(x)) for x in origin))
    header.append(f"element chunk {len(chunks)}")
    header += [f"property float {p}" for p in CHUNK_PROPS]
    header += [f"element vertex {n}"] + [f"property uint {p}" for p in VERTEX_PROPS]
    if r:
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * r)]
    header.append("end_header")
    data = ("\n".join(header) + "\n").encode("ascii") + chunks.tobytes() + vertex.tobytes() + (sh.tobytes() if r else b"")
    return data, {"splats": n, "sh_degree": degree}


def write_compressed_ply(model: SurfelModel, path: str, origin=None) -> dict:
    """Write `model` as PlayCanvas's compressed PLY (atomically). Returns {"bytes", "splats", "sh_degree"}."""
    data, info = compressed_ply_bytes(model, origin=origin)
    with atomic.atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
    return {"bytes": len(data), **info}


def _ply_elements(path: str, raw: bytes) -> tuple[dict[str, tuple[int, list[tuple[str, str]]]], int, list[str]]:
    """Header of a binary little-endian PLY: ({element: (count, [(type, name)])}, data offset, comments)."""
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise UserError(f"{path}: not a PLY file (no 'ply' / 'end_header'); pass a .compressed.ply file")
    elements: dict[str, tuple[int, list[tuple[str, str]]]] = {}
    comments, current = [], None
    for line in raw[:end].decode("ascii", "replace").splitlines()[1:]:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format" and parts[1:2] != ["binary_little_endian"]:
            raise UserError(f"{path}: PLY format {' '.join(parts[1:])}; compressed PLY is binary_little_endian")
        if parts[0] == "comment":
            comments.append(line[len("comment "):])
        elif parts[0] == "element":
            current = parts[1]
            elements[current] = (int(parts[2]), [])
        elif parts[0] == "property" and current is not None:
            if parts[1] == "list":
                raise UserError(f"{path}: PLY list property {parts[-1]}: not a compressed PLY")
            elements[current][1].append((parts[1], parts[2]))
    return elements, end + len(b"end_header\n"), comments


def read_compressed_ply(path: str) -> SurfelModel:
    """A PlayCanvas compressed PLY (ours or SuperSplat's) as untextured surfels; UserError naming the file when it is
    not one."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise UserError(f"{path}: cannot read compressed PLY ({exc.strerror}); check the path") from exc
    elements, offset, _ = _ply_elements(path, raw)
    chunk_props = [p for _, p in elements.get("chunk", (0, []))[1]]
    # SuperSplat's first files had no colour bounds (12 chunk properties, colour a plain 8-bit unorm)
    want = {"chunk": ("float", CHUNK_PROPS if len(chunk_props) >= 18 else CHUNK_PROPS[:12]),
            "vertex": ("uint", VERTEX_PROPS)}
    for name, (kind, props) in want.items():
        got = elements.get(name, (0, []))[1]
        if [p for _, p in got][:len(props)] != props or any(t not in (kind, kind + "32") for t, _ in got):
            raise UserError(f"{path}: no `{name}` element of {kind} {', '.join(props[:2])}...: not a compressed PLY "
                            "(a plain 3DGS PLY reads with --format ply)")
    n, n_chunks = elements["vertex"][0], elements["chunk"][0]
    if n_chunks != -(-n // CHUNK):
        raise UserError(f"{path}: {n_chunks} chunks for {n} splats ({-(-n // CHUNK)} expected); not a compressed PLY")
    sizes = {"chunk": 4 * len(elements["chunk"][1]), "vertex": 4 * len(elements["vertex"][1])}
    rest_n = 0
    if "sh" in elements:
        rest_n = len(elements["sh"][1])
        if rest_n not in (9, 24, 45) or elements["sh"][0] != n or any(t not in ("uchar", "uint8")
                                                                         for t, _ in elements["sh"][1]):
            raise UserError(f"{path}: `sh` element of {rest_n} properties for {elements['sh'][0]} splats; expected "
                            f"9, 24 or 45 uchar f_rest_* for {n}")
        sizes["sh"] = rest_n
    order = list(elements)
    expected = offset + sum(elements[e][0] * sizes.get(e, 0) for e in order)
    if set(order) - set(sizes) or len(raw) != expected:
        raise UserError(f"{path}: {len(raw)} bytes, {expected} expected from its header: truncated or not a "
                        "compressed PLY; re-export it")
    arrays, at = {}, offset
    for e in order:
        count, props = elements[e]
        dtype = "<f4" if e == "chunk" else ("<u4" if e == "vertex" else "u1")
        arrays[e] = np.frombuffer(raw, dtype, count * len(props), at).reshape(count, len(props))
        at += count * sizes[e]
    ch = arrays["chunk"].astype(np.float64)
    v = arrays["vertex"][:, :4].astype(np.int64)
    c = np.arange(n) // CHUNK

    def unpack111011(word, lo_col):
        t = [((word >> 21) & 2047) / 2047, ((word >> 11) & 1023) / 1023, (word & 2047) / 2047]
        return np.stack([ch[c, lo_col + i] + (ch[c, lo_col + 3 + i] - ch[c, lo_col + i]) * t[i] for i in range(3)], 1)

    means = unpack111011(v[:, 0], 0)
    log_scales = unpack111011(v[:, 2], 6)
    three = np.stack([((v[:, 1] >> s) & 1023) / 1023 for s in (20, 10, 0)], 1)
    quats = _from_smallest_three((v[:, 1] >> 30) & 3, (three - 0.5) * math.sqrt(2.0))
    u8 = np.stack([((v[:, 3] >> s) & 255) / 255 for s in (24, 16, 8, 0)], 1)
    if ch.shape[1] >= 18:
        colour = ch[c, 12:15] + (ch[c, 15:18] - ch[c, 12:15]) * u8[:, :3]
    else:  # older files: colour as a plain 8-bit unorm
        colour = u8[:, :3]
    dc = (colour - 0.5) / SH_C0
    r = rest_n // 3
    if r:
        b = arrays["sh"].astype(np.float64)
        nrm = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256))
        rest = ((nrm - 0.5) * 8.0).reshape(n, 3, r).transpose(0, 2, 1)
    else:
        rest = np.zeros((n, 0, 3))
    return _surfels(means, log_scales, quats, u8[:, 3], dc, rest)


# ---------------------------------------------------------------- SOG

def _log_transform(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.log1p(np.abs(x))


def _inv_log_transform(v: np.ndarray) -> np.ndarray:
    return np.sign(v) * np.expm1(np.abs(v))


def _webp(pixels: np.ndarray, width: int, height: int) -> bytes:
    """[M, 4] RGBA bytes (M <= width * height, the rest zero) -> a lossless WebP image of width x height."""
    # OpenCV takes a while to import: loaded only where an image is coded
    import cv2

    img = np.zeros((width * height, 4), np.uint8)
    img[:len(pixels)] = pixels
    img = img.reshape(height, width, 4)[..., [2, 1, 0, 3]]  # OpenCV writes BGRA
    ok, buf = cv2.imencode(".webp", img, [cv2.IMWRITE_WEBP_QUALITY, 101])  # above 100: lossless
    if not ok:
        raise UserError("OpenCV could not encode a WebP image (its build lacks libwebp?): export --format spz or ply")
    return buf.tobytes()


def _decode_webp(path: str, name: str, data: bytes) -> np.ndarray:
    """A WebP image -> [H, W, 4] RGBA bytes; UserError naming the bundle when it is not one."""
    # OpenCV takes a while to import: loaded only where an image is coded
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 3 or img.shape[2] not in (3, 4):
        raise UserError(f"{path}: {name} is not a colour WebP image; not a SOG file, re-export it")
    if img.shape[2] == 3:
        img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], 2)
    return img[..., [2, 1, 0, 3]]


def _codebook(values: np.ndarray) -> tuple[list[float], np.ndarray]:
    """256-entry 1-D K-means codebook of `values` (any shape) and every value's index (uint8, the same shape)."""
    centres = scalar_kmeans(values, 256).centres  # sorted
    # every value to its nearest entry of the final codebook (K-means' last step moved the centres after assigning)
    labels = np.searchsorted((centres[1:] + centres[:-1]) / 2, np.asarray(values, dtype=np.float64))
    return [float(x) for x in centres], labels.astype(np.uint8)


def palette_size(n: int) -> int:
    """How many SH rows SOG's palette holds for n splats: all of them up to the 65,536 its 16-bit labels address.
    PlayCanvas's writer uses 1024 entries per 1-2k splats, doubling with the count, to 65,536; keeping the distinct
    rows instead runs no K-means below 65,536 rows. On herzjesu25's 20k surfels (384 px `fast`): 0.6 s against 129 s
    of K-means into 16k entries, a slightly smaller file (428 kB against 430), the same PSNR to 0.01 dB
    (benchmarks/results/archive/sog_palette/herzjesu25_384_34667a3.md, 2-core VM)."""
    return min(n, PALETTE_MAX)


def sog_files(model: SurfelModel, seed: int = 0) -> tuple[dict[str, bytes], dict]:
    """{file name: bytes} of the SOG bundle of `model` (meta.json and the images), and what was written."""
    g = gaussian_table(model)
    n, degree = len(g["means"]), g["degree"]
    width = int(math.ceil(math.sqrt(n) / 4) * 4)
    height = int(math.ceil(n / width / 4) * 4)
    files: dict[str, bytes] = {}
    lt = _log_transform(g["means"])
    mins, maxs = lt.min(0), lt.max(0)
    m16 = np.round((lt - mins) / np.where(maxs > mins, maxs - mins, 1.0) * 65535).astype(np.uint32)
    ones = np.full((n, 1), 255, np.uint8)
    files["means_l.webp"] = _webp(np.concatenate([(m16 & 255).astype(np.uint8), ones], 1), width, height)
    files["means_u.webp"] = _webp(np.concatenate([(m16 >> 8).astype(np.uint8), ones], 1), width, height)
    largest, three = _smallest_three(g["quats"])
    q8 = np.clip(np.round((three * math.sqrt(2.0) * 0.5 + 0.5) * 255), 0, 255).astype(np.uint8)
    files["quats.webp"] = _webp(np.concatenate([q8, (252 + largest).astype(np.uint8)[:, None]], 1), width, height)
    scale_book, scale_idx = _codebook(g["log_scales"])
    files["scales.webp"] = _webp(np.concatenate([scale_idx, ones], 1), width, height)
    dc_book, dc_idx = _codebook(g["dc"])
    alpha = np.clip(np.round(g["opacity"] * 255), 0, 255).astype(np.uint8)[:, None]
    files["sh0.webp"] = _webp(np.concatenate([dc_idx, alpha], 1), width, height)
    meta = {"version": SOG_VERSION, "asset": {"generator": f"ctgs {__version__}"}, "count": n, "model": "2dgs",
            "means": {"mins": [float(x) for x in mins], "maxs": [float(x) for x in maxs], "files": SOG_FILES["means"]},
            "scales": {"codebook": scale_book, "files": SOG_FILES["scales"]},
            "quats": {"files": SOG_FILES["quats"]},
            "sh0": {"codebook": dc_book, "files": SOG_FILES["sh0"]}}
    info = {"splats": n, "sh_degree": degree, "palette": 0, "width": width, "height": height}
    r = SH_REST[degree]
    if r:
        rows = g["rest"].transpose(0, 2, 1).reshape(n, 3 * r)  # channel-major, as f_rest_*
        k = palette_size(n)
        distinct, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        if len(distinct) <= k:  # every distinct row fits (baked models: a surfel's texels share its SH): no K-means
            order = np.argsort(first)  # entries in the order splats first use them: labels mostly count up (Morton)
            rank = np.empty_like(order)
            rank[order] = np.arange(len(order))
            k, centres, labels = len(distinct), distinct[order], rank[inverse.reshape(-1)]
        else:  # K-means of the distinct rows (a baked model repeats each surfel's row per texel), labels per splat
            book = vector_kmeans(distinct, k, seed=seed)
            centres, labels = book.centres, book.labels[inverse.reshape(-1)]  # [K, 3r], [N]
        sh_book, sh_idx = _codebook(centres)  # [K, 3r] indices
        pix = sh_idx.reshape(k, 3, r).transpose(0, 2, 1)  # [K, r, 3]: pixel j of entry i = coefficient j's r, g, b
        cen = np.concatenate([pix.reshape(k * r, 3), np.full((k * r, 1), 255, np.uint8)], 1)
        files["shN_centroids.webp"] = _webp(cen, 64 * r, math.ceil(k / 64))
        lab = labels.astype(np.uint32)
        files["shN_labels.webp"] = _webp(np.stack([lab & 255, lab >> 8, np.zeros(n, np.uint32),
                                                   np.full(n, 255, np.uint32)], 1).astype(np.uint8), width, height)
        meta["shN"] = {"count": k, "bands": degree, "codebook": sh_book, "files": SOG_FILES["shN"]}
        info["palette"] = k
    files = {"meta.json": json.dumps(meta).encode("utf-8"), **files}
    return files, info


def write_sog(model: SurfelModel, path: str, seed: int = 0) -> dict:
    """Write `model` as a bundled SOG (a zip, atomically). Returns {"bytes", "splats", "sh_degree", "palette", ...}."""
    files, info = sog_files(model, seed=seed)
    with atomic.atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:  # WebP is compressed already
            for name, data in files.items():
                z.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data)
        size = os.path.getsize(tmp)
    return {"bytes": size, **info}


def read_sog(path: str) -> SurfelModel:
    """A bundled SOG file (version 2; ours or splat-transform's) as untextured surfels; UserError naming the file when
    it is not one."""
    try:
        with zipfile.ZipFile(path) as z:
            files = {name: z.read(name) for name in z.namelist()}
    except FileNotFoundError as exc:
        raise UserError(f"{path}: no such file; check the path") from exc
    except (zipfile.BadZipFile, OSError) as exc:
        raise UserError(f"{path}: not a SOG bundle (not a zip file: {exc}); re-export it") from exc
    if "meta.json" not in files:
        raise UserError(f"{path}: no meta.json in the bundle; not a SOG file")
    try:
        meta = json.loads(files["meta.json"])
    except ValueError as exc:
        raise UserError(f"{path}: meta.json is not JSON ({exc}); not a SOG file") from exc
    if meta.get("version") != SOG_VERSION:
        raise UserError(f"{path}: SOG version {meta.get('version')}; this reader reads version 2 (convert older files "
                        "with `splat-transform`)")
    n = int(meta["count"])

    def image(key: str, i: int = 0) -> np.ndarray:
        """The file meta.json names at meta[key]["files"][i], decoded: [H, W, 4] RGBA."""
        name = meta[key]["files"][i]
        if name not in files:
            raise UserError(f"{path}: {name} (named in meta.json) is missing from the bundle; re-export it")
        return _decode_webp(path, name, files[name])

    def pixels(key: str, i: int = 0) -> np.ndarray:
        """The first n pixels of that image, [n, 4], one per splat."""
        px = image(key, i).reshape(-1, 4)
        if len(px) < n:
            raise UserError(f"{path}: {meta[key]['files'][i]} holds {len(px)} pixels for {n} splats; not a SOG file")
        return px[:n]

    lo, hi = pixels("means", 0).astype(np.int64), pixels("means", 1).astype(np.int64)
    mins, maxs = np.array(meta["means"]["mins"], float), np.array(meta["means"]["maxs"], float)
    means = _inv_log_transform(mins + (maxs - mins) * ((lo[:, :3] | (hi[:, :3] << 8)) / 65535))
    qp = pixels("quats").astype(np.int64)
    if ((qp[:, 3] < 252) | (qp[:, 3] > 255)).any():
        raise UserError(f"{path}: quats.webp alpha outside 252-255; not a SOG version 2 file")
    quats = _from_smallest_three(qp[:, 3] - 252, (qp[:, :3] / 255 * 2 - 1) / math.sqrt(2.0))
    log_scales = np.array(meta["scales"]["codebook"], float)[pixels("scales")[:, :3]]
    sh0 = pixels("sh0")
    dc = np.array(meta["sh0"]["codebook"], float)[sh0[:, :3]]
    rest = np.zeros((n, 0, 3))
    if "shN" in meta:
        bands = int(meta["shN"]["bands"])
        r = SH_REST.get(bands, 0)
        palette = image("shN", 0)  # [rows, 64 r, 4]: entry i is pixels i r .. i r + r - 1, coefficient-wise
        if not r or palette.shape[1] != 64 * r:
            raise UserError(f"{path}: shN palette {palette.shape[1]} pixels wide for {bands} SH bands "
                            f"({64 * r} expected); not a SOG file, re-export it")
        entries = palette.reshape(-1, r, 4)[:, :, :3]  # [rows * 64, r, 3] codebook indices
        lab = pixels("shN", 1).astype(np.int64)
        label = lab[:, 0] | (lab[:, 1] << 8)
        count = min(int(meta["shN"]["count"]), len(entries))
        if (label >= count).any():
            raise UserError(f"{path}: shN labels past the palette's {count} entries; not a SOG file, re-export it")
        rest = np.array(meta["shN"]["codebook"], float)[entries[label]]  # [n, r, 3]
    return _surfels(means, log_scales, quats, sh0[:, 3] / 255.0, dc, rest)
