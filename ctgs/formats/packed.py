"""The packed container of compressed models (`model.bin`): named arrays, each losslessly coded.

A section is one array [rows] or [rows, cols] of a fixed little-endian dtype. Its bytes are laid out
row-major or column-major (one column after another), optionally byte-shuffled (byte 0 of every
element, then byte 1, ...: the high bytes of quantised or float16 values repeat far more than the low
ones, which LZMA then finds), then coded with xz/LZMA (or zlib, or stored). The writer tries the
layouts and keeps the smallest; the manifest records what was chosen, the byte range in `model.bin`,
and a CRC-32 of the decoded bytes. The full specification is docs/reference/model_format.md.

Coder: LZMA (Python's `lzma`, the .xz format) at preset 9e. Measured on a demo model (1.1M texels,
256-level scalar indices): xz 1.05 MB, zstd level 19/22 1.18 MB (zstandard 0.25), zlib 9 1.46 MB;
on float16 SH and positions xz was also the smallest. zstd is faster but not smaller, so no new
dependency: xz is in the standard library and every platform has a reader. A delta filter before LZMA (distance 3:
one RGB texel back) shrank photos' 256-level indices by 22% but grew real texel indices by 8% (the demo model and a
herzjesu25 model): textures are offsets around the SH colour, not images, so it is not used.

One xz stream codes at about 1-2 MB/s (one core), so a paper-scale model's texel indices (75 MB for 25M texels)
take a minute or more. With jobs > 1 (`ctgs compress --jobs N`) a section above XZ_STREAM_BYTES is cut into
independent xz streams of that size, coded on N threads (lzma releases the GIL) and concatenated: still one valid
.xz file (a reader that ignores the entry's `streams` decodes it whole), about 2% larger, since each stream starts
with an empty dictionary and fresh probabilities (benchmarks/results/archive/xz_streams/herzjesu25_images_2d9476d.md).
"""

from __future__ import annotations

import lzma
import os
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ctgs.errors import UserError

CODERS = ("xz", "zlib", "none")
DTYPES = ("u1", "i1", "<u2", "<i2", "<u4", "<i4", "<f2", "<f4", "<f8")
XZ_PRESET = 9 | lzma.PRESET_EXTREME
XZ_MAX_DICT = 64 << 20  # preset 9's dictionary
XZ_MIN_DICT = 4096  # LZMA2's smallest
ZLIB_LEVEL = 9
# Sections larger than this (bytes) only try their natural layout (row-major, no shuffle for 1-byte
# types): each extra trial is one more full LZMA pass over the biggest payloads.
TRY_LAYOUTS_BELOW = 1 << 22
# With jobs > 1: uncoded bytes per xz stream of a larger section (larger streams lose less to each stream's cold
# start, smaller ones give more threads work).
XZ_STREAM_BYTES = 16 << 20


@dataclass
class Section:
    name: str
    array: np.ndarray  # [rows] or [rows, cols]
    encoding: dict  # how the stored values become model quantities (ctgs.formats.compress; docs/reference/model_format.md)


def _code(data: bytes, coder: str) -> bytes:
    if coder == "xz":
        # Preset 9e with the dictionary cut to the data: same output for small sections, without preset 9's
        # 64 MiB dictionary (~670 MiB of encoder memory) allocated for every few-kilobyte section.
        dict_size = min(XZ_MAX_DICT, max(XZ_MIN_DICT, len(data)))
        return lzma.compress(data, format=lzma.FORMAT_XZ,
                             filters=[{"id": lzma.FILTER_LZMA2, "preset": XZ_PRESET, "dict_size": dict_size}])
    if coder == "zlib":
        return zlib.compress(data, ZLIB_LEVEL)
    return data


def _decode(data: bytes, coder: str, where: str) -> bytes:
    try:
        if coder == "xz":
            return lzma.decompress(data, format=lzma.FORMAT_XZ)
        if coder == "zlib":
            return zlib.decompress(data)
    except (lzma.LZMAError, zlib.error) as exc:
        raise UserError(f"{where}: corrupt {coder} stream ({exc}); re-compress the model") from exc
    return data


def layout_bytes(array: np.ndarray, order: str, shuffle: bool) -> bytes:
    """The section's uncoded bytes: `order` "row" or "column", then optional byte shuffle."""
    a = array if array.ndim == 1 or order == "row" else array.T
    a = np.ascontiguousarray(a)
    if shuffle and a.dtype.itemsize > 1:
        return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, a.dtype.itemsize).T).tobytes()
    return a.tobytes()


def unlayout_bytes(data: bytes, dtype: np.dtype, shape: list[int], order: str, shuffle: bool) -> np.ndarray:
    count = int(np.prod(shape)) if shape else 1
    if shuffle and dtype.itemsize > 1:
        data = np.frombuffer(data, np.uint8).reshape(dtype.itemsize, count).T.tobytes()
    a = np.frombuffer(data, dtype=dtype, count=count)
    if len(shape) == 2 and order == "column":
        return a.reshape(shape[1], shape[0]).T.copy()
    return a.reshape(shape).copy()


def _code_streams(data: bytes, jobs: int) -> list[bytes]:
    """data cut into XZ_STREAM_BYTES pieces, each its own xz stream, coded on `jobs` threads."""
    pieces = [data[i:i + XZ_STREAM_BYTES] for i in range(0, len(data), XZ_STREAM_BYTES)]
    with ThreadPoolExecutor(min(jobs, len(pieces))) as pool:
        return list(pool.map(lambda piece: _code(piece, "xz"), pieces))


def encode_section(section: Section, coder: str, offset: int, jobs: int = 1) -> tuple[bytes, dict]:
    """(coded bytes, manifest entry) for one section starting at byte `offset` of model.bin. jobs > 1: an xz
    section above XZ_STREAM_BYTES is coded as independent streams on that many threads (entry `streams`: their
    coded sizes)."""
    a = section.array
    dt = a.dtype.newbyteorder("<") if a.dtype.itemsize > 1 else a.dtype
    if dt.str not in DTYPES and dt.str.lstrip("|") not in DTYPES:
        raise ValueError(f"section {section.name}: unsupported dtype {a.dtype}")
    a = a.astype(dt, copy=False)
    small = a.nbytes < TRY_LAYOUTS_BELOW
    orders = ("row", "column") if a.ndim == 2 and a.shape[1] > 1 and small else ("row",)
    shuffles = (False, True) if a.dtype.itemsize > 1 and small else (a.dtype.itemsize > 1,)
    best = None
    for order in orders:
        for shuffle in shuffles:
            raw = layout_bytes(a, order, shuffle)
            streams = None
            if coder == "xz" and jobs > 1 and len(raw) > XZ_STREAM_BYTES:
                parts = _code_streams(raw, jobs)
                coded, streams = b"".join(parts), [len(p) for p in parts]
            else:
                coded = _code(raw, coder)
            if best is None or len(coded) < len(best[0]):
                best = (coded, order, shuffle, zlib.crc32(raw), streams)
    coded, order, shuffle, crc, streams = best
    entry = {"name": section.name, "dtype": dt.str.lstrip("|"), "shape": list(a.shape), "order": order,
             "shuffle": shuffle, "coder": coder, "offset": offset, "bytes": len(coded), "crc32": crc,
             **({"streams": streams} if streams else {}), "encoding": section.encoding}
    return coded, entry


def _decode_streams(data: bytes, streams, where: str) -> bytes:
    """The concatenated xz streams of one section decoded on threads (their coded sizes: `streams`)."""
    if not isinstance(streams, list) or not all(isinstance(n, int) and n > 0 for n in streams) \
            or sum(streams) != len(data):
        raise UserError(f"{where}: the stream sizes do not add up to the section's bytes (corrupt manifest); "
                        "re-compress the model")
    starts = [sum(streams[:i]) for i in range(len(streams))]
    pieces = [data[s:s + n] for s, n in zip(starts, streams)]
    with ThreadPoolExecutor(min(len(pieces), os.cpu_count() or 1)) as pool:
        return b"".join(pool.map(lambda piece: _decode(piece, "xz", where), pieces))


def decode_section(blob: bytes, entry: dict, path: str) -> np.ndarray:
    """The array of one manifest entry, read from the bytes of model.bin; UserError on any corruption."""
    where = f"{path} (section {entry.get('name')})"
    try:
        dtype = np.dtype(entry["dtype"])
        shape = [int(s) for s in entry["shape"]]
        start, size, coder = int(entry["offset"]), int(entry["bytes"]), entry["coder"]
        order, shuffle = entry["order"], bool(entry["shuffle"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{where}: incomplete section entry in the manifest ({exc}); re-compress the model") from exc
    if entry["dtype"] not in DTYPES or coder not in CODERS or order not in ("row", "column") \
            or len(shape) not in (1, 2) or min(shape, default=0) < 0:
        raise UserError(f"{where}: unsupported section entry (dtype {entry['dtype']}, coder {coder}, "
                        f"shape {shape}); re-compress the model with this ctgs")
    if start < 0 or start + size > len(blob):
        raise UserError(f"{where}: bytes {start}..{start + size} lie outside the {len(blob)}-byte file; "
                        "the file is truncated, re-compress the model")
    if "streams" in entry and coder == "xz":
        raw = _decode_streams(blob[start:start + size], entry["streams"], where)
    else:
        raw = _decode(blob[start:start + size], coder, where)
    if len(raw) != int(np.prod(shape)) * dtype.itemsize or zlib.crc32(raw) != entry.get("crc32"):
        raise UserError(f"{where}: decoded size or checksum mismatch (corrupt file); re-compress the model")
    return unlayout_bytes(raw, dtype, shape, order, shuffle)
