"""The texture blob (`textures.bin`): a 64-byte little-endian header + raw or codebook texel payload.

Layout (all little-endian; the full spec is docs/reference/model_format.md):

| offset | type | field |
| --- | --- | --- |
| 0 | 8 bytes | magic `CTGSTEX\\0` |
| 8 | uint32 | version (1) |
| 12 | uint32 | header size in bytes (64) |
| 16 | uint32 | encoding: 0 = raw texels, 1 = codebook + indices |
| 20 | uint32 | value dtype: 1 = float16, 2 = float32, 3 = float64 |
| 24 | uint64 | T, number of texels |
| 32 | uint32 | channels (3) |
| 36 | uint32 | K, codebook size (0 when raw) |
| 40 | uint32 | index dtype: 0 = none, 1 = uint8, 2 = uint16, 3 = uint32 |
| 44 | uint32 | CRC-32 (zlib) of the payload |
| 48 | uint64 | payload size in bytes |
| 56 | 8 bytes | reserved, zero |

Payload: raw: T*3 values (texel-major). Codebook: K*3 values, then T indices. Values are *raw*
(pre-activation) texel parameters: offset = 2*sigmoid(value) - 1.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from ctgs.errors import UserError

MAGIC = b"CTGSTEX\x00"
BLOB_VERSION = 1
HEADER = struct.Struct("<8sIIIIQIIIIQ8x")  # 64 bytes, see the table above
ENCODINGS = {0: "raw", 1: "codebook"}
VALUE_DTYPES = {1: np.dtype("<f2"), 2: np.dtype("<f4"), 3: np.dtype("<f8")}
INDEX_DTYPES = {0: None, 1: np.dtype("u1"), 2: np.dtype("<u2"), 3: np.dtype("<u4")}


@dataclass
class TextureBlob:
    """Texel payload. raw: `values` [T, 3]. codebook: `values` [K, 3] and `indices` [T]."""

    values: np.ndarray
    indices: np.ndarray | None = None

    @property
    def encoding(self) -> str:
        return "raw" if self.indices is None else "codebook"

    @property
    def num_texels(self) -> int:
        return len(self.values) if self.indices is None else len(self.indices)

    def decode(self) -> np.ndarray:
        """[T, 3] raw texel values (codebook entries gathered by index)."""
        return self.values if self.indices is None else self.values[self.indices.astype(np.int64)]


def index_dtype_for(k: int) -> np.dtype:
    """Smallest unsigned index type that addresses a codebook of `k` entries."""
    return np.dtype("u1") if k <= 1 << 8 else np.dtype("<u2") if k <= 1 << 16 else np.dtype("<u4")


def _code(table: dict, dtype) -> int:
    for code, dt in table.items():
        if dt is not None and dtype is not None and np.dtype(dt) == np.dtype(dtype).newbyteorder("<"):
            return code
    raise ValueError(f"unsupported dtype {dtype}")


def encode_blob(blob: TextureBlob) -> bytes:
    values = np.ascontiguousarray(blob.values)
    if values.ndim != 2 or values.shape[1] != 3:
        raise ValueError(f"texture values must have shape [*, 3], got {list(values.shape)}")
    vcode = _code(VALUE_DTYPES, values.dtype)
    payload = values.astype(VALUE_DTYPES[vcode], copy=False).tobytes()
    k, icode = 0, 0
    if blob.indices is not None:
        k = len(values)
        icode = _code(INDEX_DTYPES, blob.indices.dtype)
        payload += np.ascontiguousarray(blob.indices).astype(INDEX_DTYPES[icode], copy=False).tobytes()
    header = HEADER.pack(MAGIC, BLOB_VERSION, HEADER.size, 0 if blob.indices is None else 1, vcode,
                         blob.num_texels, 3, k, icode, zlib.crc32(payload), len(payload))
    return header + payload


def decode_blob(data: bytes, path: str = "textures.bin") -> TextureBlob:
    """Parse a blob; every inconsistency raises UserError naming `path`."""
    if len(data) < HEADER.size:
        raise UserError(f"{path}: {len(data)} bytes, shorter than the 64-byte header; re-export the model")
    magic, version, hsize, enc, vcode, t, ch, k, icode, crc, nbytes = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise UserError(f"{path}: not a ctgs texture blob (bad magic); pass a folder written by `ctgs export`")
    if version != BLOB_VERSION:
        raise UserError(f"{path}: texture blob version {version}, this ctgs reads version {BLOB_VERSION}; "
                        "re-export the model with this version")
    if hsize != HEADER.size or ch != 3 or enc not in ENCODINGS or vcode not in VALUE_DTYPES \
            or icode not in INDEX_DTYPES or (enc == 1) != (icode != 0):
        raise UserError(f"{path}: corrupt texture blob header; re-export the model")
    payload = data[HEADER.size:]
    vdt = VALUE_DTYPES[vcode]
    rows = t if enc == 0 else k
    expected = rows * 3 * vdt.itemsize + (t * INDEX_DTYPES[icode].itemsize if enc == 1 else 0)
    if len(payload) != nbytes or nbytes != expected:
        raise UserError(f"{path}: payload is {len(payload)} bytes, expected {expected}; "
                        "the file is truncated or corrupt, re-export the model")
    if zlib.crc32(payload) != crc:
        raise UserError(f"{path}: checksum mismatch (corrupt file); re-export the model")
    values = np.frombuffer(payload, dtype=vdt, count=rows * 3).reshape(rows, 3).copy()
    if enc == 0:
        return TextureBlob(values)
    idt = INDEX_DTYPES[icode]
    indices = np.frombuffer(payload, dtype=idt, count=t, offset=rows * 3 * vdt.itemsize).copy()
    if t and int(indices.max()) >= k:
        raise UserError(f"{path}: codebook index out of range (corrupt file); re-compress the model")
    return TextureBlob(values, indices)
