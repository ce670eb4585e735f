"""Niantic's `.spz` (version 3): gzip-compressed, quantised 3D Gaussians, about a tenth of a 3DGS PLY.

The format (github.com/nianticlabs/spz, docs/SPZ.md there): a gzip stream holding a 16-byte little-endian
header (magic 0x5053474e "NGSP", version, number of points, SH degree, fractional bits, flags, reserved)
and then one array per attribute, every point's value in turn:

| array | bytes per point | encoding |
| --- | --- | --- |
| positions | 9 | x, y, z as 24-bit two's-complement fixed point with `fractional bits` bits after the point |
| alphas | 1 | round(255 * opacity) |
| colours | 3 | round(255 * (0.15 * dc + 0.5)): the DC SH coefficient, room for values past [0, 1] |
| scales | 3 | round(16 * (log scale + 10)): log standard deviations from -10 to 5.94 |
| rotations | 4 | the quaternion's three smallest components, 10 bits each (sign + 9-bit magnitude / sqrt(1/2)), and the largest's index in the top 2 bits (version 3; version 2 stored x, y, z in 3 bytes) |
| SH | 3 x (K - 1) | bands 1..degree, coefficient-major (r, g, b of each), round(128 x + 128) snapped to buckets of 8 (band 1) or 16 (bands 2-3) |

Frame: spz stores right-up-back (RUB, OpenGL) coordinates; a COLMAP / 3DGS PLY frame (ours) is
right-down-front (RDF). The two differ by a half turn about x (y and z change sign), which is applied to
positions, rotations and the SH bands, as Niantic's own ply-to-spz does, so spz viewers show the model upright
as they show any converted 3DGS capture.

What a surfel keeps is what the 3DGS PLY keeps (ctgs.formats.plain_ply): the texture folded into one colour, the
flat axis a third scale of FLAT_SCALE_RATIO x the smaller tangent one (spz's floor of e^-10 may thicken it);
then spz's quantisation on top. Fractional bits: Niantic's 12 unless the model needs finer steps (a step
above 1/64 of its median tangent scale: a model in small units) or coarser ones to fit 24 bits (a model in
large units); readers take the count from the header.
"""

from __future__ import annotations

import gzip
import math
import struct
import zlib

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.formats.plain_ply import FLAT_SCALE_RATIO, SH_C0, surfels_from_gaussians, texture_means
from ctgs.formats.splat import ALPHA_EPS  # 8-bit alphas of 0 or 255 read back this far inside (a finite logit)
from ctgs.model.surfels import SurfelModel
from ctgs.render.sh import sh_to_color

MAGIC = 0x5053474E
VERSION = 3
HEADER = struct.Struct("<IIIBBBB")
COLOR_SCALE = 0.15
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
MAX_POINTS = 10_000_000  # the reference reader refuses files with more
DEFAULT_FRACTIONAL_BITS = 12
STEPS_PER_SCALE = 64  # position step at most 1/64 of the median tangent standard deviation
LOG_SCALE_MIN, LOG_SCALE_MAX = -10.0, 255 / 16 - 10.0
FLIP = np.array([1.0, -1.0, -1.0])  # RDF <-> RUB: a half turn about x
SQRT1_2 = math.sqrt(0.5)
ROWS = 1 << 16  # points converted at a time


def sh_flips(degree: int, flip: np.ndarray = FLIP) -> np.ndarray:
    """[K - 1] sign of each SH band coefficient (1..degree) under the frame change diag(flip), a half turn about an
    axis (by default about x: RDF <-> RUB). Read off the renderer's own basis, not a table."""
    k = (degree + 1) ** 2
    if k == 1:
        return np.zeros(0)
    d = torch.tensor([[0.3, 0.5, 0.81]], dtype=torch.float64)
    d = d / d.norm()
    flipped = d * torch.from_numpy(np.asarray(flip, dtype=np.float64))
    basis = torch.eye(k, dtype=torch.float64)[:, :, None].expand(k, k, 3)  # one-hot coefficient per row
    a = sh_to_color(basis, d.expand(k, 3), degree)[:, 0] - 0.5
    b = sh_to_color(basis, flipped.expand(k, 3), degree)[:, 0] - 0.5
    signs = (b / a).numpy()[1:]
    assert np.allclose(np.abs(signs), 1.0), signs
    return np.round(signs)


def fractional_bits(positions: np.ndarray, tangent_sigma: np.ndarray) -> int:
    """How many of the 24 bits go after the point (module docstring). UserError when no count fits."""
    extent = float(np.abs(positions).max()) if positions.size else 0.0
    fit = 23 if extent == 0 else min(23, math.floor(math.log2((2**23 - 1) / extent)))
    if fit < 0:
        raise UserError(f"positions reach {extent:.3g} units from the origin, past .spz's 24-bit range "
                        f"(8.4e6 units): export --format ply instead")
    sigma = float(np.median(tangent_sigma)) if tangent_sigma.size else 1.0
    need = math.ceil(math.log2(STEPS_PER_SCALE / sigma)) if sigma > 0 else 23
    return min(fit, max(DEFAULT_FRACTIONAL_BITS, need))


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def pack_smallest_three(q_xyzw: np.ndarray) -> np.ndarray:
    """[N, 4] normalised quaternions (x, y, z, w) -> [N, 4] bytes of spz version 3."""
    q = q_xyzw / np.linalg.norm(q_xyzw, axis=1, keepdims=True)
    largest = np.abs(q).argmax(1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        keep = largest != i
        neg = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = np.floor(511.0 * np.abs(q[:, i]) / SQRT1_2 + 0.5).astype(np.uint32)
        comp = np.where(keep, (comp << 10) | (neg << 9) | np.minimum(mag, 511), comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def unpack_smallest_three(b: np.ndarray) -> np.ndarray:
    """[N, 4] bytes of spz version 3 -> [N, 4] quaternions (x, y, z, w)."""
    comp = b.astype(np.uint8).reshape(-1, 4).copy().view("<u4")[:, 0].astype(np.int64)
    largest = comp >> 30
    q = np.zeros((len(comp), 4))
    for i in (3, 2, 1, 0):
        keep = largest != i
        mag = (comp & 511) / 511.0 * SQRT1_2
        val = np.where((comp >> 9) & 1, -mag, mag)
        q[:, i] = np.where(keep, val, 0.0)
        comp = np.where(keep, comp >> 10, comp)
    rows = np.arange(len(q))
    q[rows, largest] = np.sqrt(np.clip(1.0 - (q**2).sum(1), 0.0, None))
    return q


def quantise_sh(x: np.ndarray, bucket: np.ndarray) -> np.ndarray:
    """SH coefficients -> bytes, round(128 x + 128) snapped to multiples of `bucket` (broadcast)."""
    q = np.round(x * 128.0) + 128.0
    return np.clip(np.floor((q + bucket // 2) / bucket) * bucket, 0, 255).astype(np.uint8)


def spz_bytes(model: SurfelModel) -> tuple[bytes, dict]:
    """The uncompressed spz stream (header + arrays) of `model`, and what the encoding clipped. Converted ROWS
    points at a time into the byte arrays (baked models run to millions)."""
    n = model.num_primitives
    if n > MAX_POINTS:
        raise UserError(f"{n} primitives: .spz readers refuse more than {MAX_POINTS}; "
                        "export --format ply instead")
    degree = min(int(model.sh_degree), 3, int(round(model.sh.shape[1] ** 0.5)) - 1)
    k = (degree + 1) ** 2
    fb = fractional_bits(model.means.detach().cpu().double().numpy() * FLIP,
                         np.exp(model.log_scales.detach().cpu().double().numpy()))
    positions, alphas = np.zeros((n, 9), np.uint8), np.zeros(n, np.uint8)  # 3 x 24-bit per point
    colours, scales, rotations = np.zeros((n, 3), np.uint8), np.zeros((n, 3), np.uint8), np.zeros((n, 4), np.uint8)
    sh_q = np.zeros((n, k - 1, 3), np.uint8)
    dc_tex = (texture_means(model) / SH_C0).numpy()  # [N, 3]
    flips = sh_flips(degree)[None, :, None]
    buckets = np.array([8] * min(3, k - 1) + [16] * max(0, k - 4), dtype=np.int64)[None, :, None]  # 5 / 4 bits
    clipped = {"fractional_bits": fb, "sh_degree": degree, "tangent_scales_clipped": 0, "colours_clipped": 0,
               "sh_clipped": 0}
    for start in range(0, n, ROWS):
        rows = slice(start, min(n, start + ROWS))
        means = model.means.detach().cpu()[rows].double().numpy() * FLIP
        fixed = np.round(means * 2.0**fb).astype(np.int64).reshape(-1)
        positions[rows] = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).reshape(-1, 9)
        alphas[rows] = _u8(torch.sigmoid(model.opacity_logits.detach().cpu()[rows]).double().numpy() * 255.0)
        sh = model.sh.detach().cpu()[rows, :k].double().numpy()  # [M, K, 3]
        colours_f = (sh[:, 0, :] + dc_tex[rows]) * (COLOR_SCALE * 255.0) + 127.5
        colours[rows] = _u8(colours_f)
        log_s = model.log_scales.detach().cpu()[rows].double().numpy()  # [M, 2]
        scales_f = (np.concatenate([log_s, (log_s.min(1) + math.log(FLAT_SCALE_RATIO))[:, None]], 1) + 10.0) * 16.0
        scales[rows] = _u8(scales_f)
        q = torch.nn.functional.normalize(model.quats.detach().cpu()[rows].double(), dim=1).numpy()  # (w, x, y, z)
        rotations[rows] = pack_smallest_three(np.concatenate([q[:, 1:] * FLIP, q[:, :1]], 1))
        rest = sh[:, 1:k, :] * flips  # [M, K-1, 3], coefficient-major
        sh_q[rows] = quantise_sh(rest, buckets)
        clipped["tangent_scales_clipped"] += int(((scales_f[:, :2] < -0.5) | (scales_f[:, :2] > 255.5)).sum())
        clipped["colours_clipped"] += int(((colours_f < -0.5) | (colours_f > 255.5)).sum())
        clipped["sh_clipped"] += int((np.abs(rest) > 127.5 / 128).sum())
    header = HEADER.pack(MAGIC, VERSION, n, degree, fb, 0, 0)
    body = b"".join(a.tobytes() for a in (positions, alphas, colours, scales, rotations, sh_q))
    return header + body, clipped


def write_spz(model: SurfelModel, path: str) -> dict:
    """Write `model` as .spz (atomically). Returns {"bytes": file size, **what spz_bytes reports}."""
    raw, info = spz_bytes(model)
    data = gzip.compress(raw, compresslevel=9, mtime=0)
    atomic.write_bytes(path, data)
    return {"bytes": len(data), **info}


def read_spz(path: str) -> SurfelModel:
    """A .spz file (version 2 or 3) as untextured surfels in the RDF (COLMAP) frame; UserError naming the
    file when it is not one."""
    try:
        with open(path, "rb") as f:
            packed = f.read()
    except OSError as exc:
        raise UserError(f"{path}: cannot read .spz file ({exc.strerror}); check the path") from exc
    try:
        raw = gzip.decompress(packed)
    except (OSError, EOFError, zlib.error) as exc:
        raise UserError(f"{path}: not a .spz file (not a gzip stream: {exc}); re-export it") from exc
    if len(raw) < HEADER.size:
        raise UserError(f"{path}: {len(raw)} bytes, shorter than the 16-byte .spz header; re-export it")
    magic, version, n, degree, fb, flags, _ = HEADER.unpack_from(raw)
    if magic != MAGIC:
        raise UserError(f"{path}: magic {magic:#010x} is not .spz's {MAGIC:#010x} (NGSP); not a .spz file")
    if version not in (2, 3):
        raise UserError(f"{path}: .spz version {version}; this reader reads versions 2 and 3")
    if flags & FLAG_EXTENSIONS:
        raise UserError(f"{path}: uses .spz extensions (flags {flags:#04x}), which this reader does not parse; "
                        "convert it with Niantic's spz tools first")
    if degree > 3 or n > MAX_POINTS:
        raise UserError(f"{path}: SH degree {degree} / {n} points: not a .spz file this reader accepts")
    k = (degree + 1) ** 2
    rot_bytes = 4 if version == 3 else 3
    sizes = [n * 9, n, n * 3, n * 3, n * rot_bytes, n * (k - 1) * 3]
    if len(raw) != HEADER.size + sum(sizes):
        raise UserError(f"{path}: {len(raw)} bytes after decompression, {HEADER.size + sum(sizes)} expected for "
                        f"{n} points of SH degree {degree}: truncated or not a .spz file; re-export it")
    arrays, at = [], HEADER.size
    for size in sizes:
        arrays.append(np.frombuffer(raw, np.uint8, size, at))
        at += size
    pos_b, alpha_b, colour_b, scale_b, rot_b, sh_b = arrays
    p = pos_b.reshape(-1, 3).astype(np.int64)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.reshape(n, 3) / 2.0**fb * FLIP
    log_scales = scale_b.reshape(n, 3) / 16.0 - 10.0
    if version == 3:
        xyzw = unpack_smallest_three(rot_b)
    else:
        xyz = rot_b.reshape(n, 3) / 127.5 - 1.0
        xyzw = np.concatenate([xyz, np.sqrt(np.clip(1 - (xyz**2).sum(1), 0, None))[:, None]], 1)
    quats = np.concatenate([xyzw[:, 3:], xyzw[:, :3] * FLIP], 1)  # (w, x, y, z) in RDF
    alpha = np.clip(alpha_b / 255.0, ALPHA_EPS, 1 - ALPHA_EPS)
    dc = (colour_b.reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
    rest = (sh_b.reshape(n, k - 1, 3) - 128.0) / 128.0 * sh_flips(degree)[None, :, None]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return surfels_from_gaussians(t(means), t(log_scales), t(quats), t(np.log(alpha / (1 - alpha))),
                                  t(np.concatenate([dc[:, None], rest], 1)))
