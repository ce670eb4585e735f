"""Minimal binary little-endian PLY (one element, scalar properties) with numpy; no plyfile needed.

Only what ctgs writes is supported: `format binary_little_endian 1.0`, a single `vertex` element,
scalar properties. Readers check the header and that the file holds exactly count * stride bytes of
data, so a truncated or foreign file raises `UserError` instead of returning garbage.
"""

from __future__ import annotations

import numpy as np

from ctgs.errors import UserError
from ctgs.io import atomic

# PLY scalar type name <-> little-endian numpy dtype (the PLY 1.0 names; int8.. aliases accepted on read).
PLY_TO_NUMPY = {
    "char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
    "float": "<f4", "double": "<f8",
    "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
    "float32": "<f4", "float64": "<f8",
}
NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                "f4": "float", "f8": "double"}
# A header longer than this is not one of ours (guards against reading a huge foreign file as text).
MAX_HEADER_BYTES = 1 << 20


def write_ply(path: str, columns: dict[str, np.ndarray], comments: list[str] | None = None) -> None:
    """Write `columns` (name -> [N] array, any supported dtype) as a binary PLY `vertex` element.

    Written atomically (ctgs.io.atomic): `path` never holds a half-written file.
    """
    if not columns:
        raise ValueError("write_ply needs at least one column")
    n = len(next(iter(columns.values())))
    fields = []
    for name, col in columns.items():
        col = np.asarray(col)
        if col.ndim != 1 or len(col) != n:
            raise ValueError(f"PLY column {name} must have shape [{n}], got {list(col.shape)}")
        code = col.dtype.newbyteorder("<").str[1:]
        if code not in NUMPY_TO_PLY:
            raise ValueError(f"PLY column {name}: unsupported dtype {col.dtype}")
        fields.append((name, "<" + code if code[1] != "1" else code))
    data = np.empty(n, dtype=np.dtype(fields))
    for name, col in columns.items():
        data[name] = col
    write_ply_records(path, data, comments)


def write_ply_records(path: str, data: np.ndarray, comments: list[str] | None = None) -> None:
    """Write a structured [N] array (scalar little-endian fields) as a binary PLY `vertex` element, atomically,
    straight from the array's memory (no copy of it: large baked models)."""
    if data.ndim != 1 or data.dtype.names is None:
        raise ValueError("write_ply_records needs a 1-D structured array")
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in (comments or [])]
    header.append(f"element vertex {len(data)}")
    for name in data.dtype.names:
        code = data.dtype.fields[name][0].str[1:]
        if code not in NUMPY_TO_PLY or data.dtype.fields[name][0].str[0] == ">":
            raise ValueError(f"PLY field {name}: unsupported dtype {data.dtype.fields[name][0]}")
        header.append(f"property {NUMPY_TO_PLY[code]} {name}")
    header.append("end_header")
    data = np.ascontiguousarray(data)
    with atomic.atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(memoryview(data).cast("B"))


def read_ply(path: str) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read a PLY written by `write_ply` (or any binary little-endian single-element PLY).

    Returns (columns name -> [N] array, comments). Raises UserError naming the file on anything else.
    """
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise UserError(f"{path}: cannot open PLY ({exc.strerror}); check the path") from exc
    with f:
        if f.read(4) != b"ply\n":
            raise UserError(f"{path}: not a PLY file (bad magic); pass a PLY written by `ctgs export`")
        lines, size = [], 4
        while True:
            line = f.readline(MAX_HEADER_BYTES)
            size += len(line)
            if not line.endswith(b"\n") or size > MAX_HEADER_BYTES:
                raise UserError(f"{path}: truncated or corrupt PLY header; re-export the model")
            text = line.decode("ascii", errors="replace").strip()
            if text == "end_header":
                break
            lines.append(text)
        payload = f.read()
    fmt, count, props, comments = None, None, [], []
    for text in lines:
        parts = text.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1:]
        elif parts[0] == "comment":
            comments.append(text[len("comment "):])
        elif parts[0] == "element":
            if count is not None or len(parts) != 3:
                raise UserError(f"{path}: PLY with more than one element is not a ctgs model file")
            count = int(parts[2])
        elif parts[0] == "property":
            if len(parts) != 3 or parts[1] not in PLY_TO_NUMPY:
                raise UserError(f"{path}: unsupported PLY property line {text!r} (only scalar properties)")
            props.append((parts[2], PLY_TO_NUMPY[parts[1]]))
    if fmt != ["binary_little_endian", "1.0"]:
        raise UserError(f"{path}: PLY format {fmt} unsupported; ctgs reads binary_little_endian 1.0")
    if count is None or not props:
        raise UserError(f"{path}: PLY header has no vertex element/properties")
    dtype = np.dtype(props)
    expected = count * dtype.itemsize
    if len(payload) != expected:
        raise UserError(f"{path}: PLY data is {len(payload)} bytes, header says {expected} "
                        f"({count} x {dtype.itemsize}); the file is truncated or corrupt, re-export it")
    data = np.frombuffer(payload, dtype=dtype, count=count)
    return {name: data[name].copy() for name, _ in props}, comments
