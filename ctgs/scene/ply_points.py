"""Point clouds as capture tools write them: the `vertex` element of a PLY file (ASCII or binary), x y z and an
optional colour (red green blue, 8-bit or float), such as nerfstudio's `sparse_pc.ply` or 3DGS's `points3D.ply`.

COLMAP's own PLY reader (pycolmap) takes float and uchar properties only, and nerfstudio writes `uint8`: the header is
read here and the data with numpy.
"""

from __future__ import annotations

import os

import numpy as np

from ctgs.errors import UserError
from ctgs.io import atomic

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_LINES = 1000


def _header(path: str, f) -> tuple[str, int, list[tuple[str, str]]]:
    """(format, vertex count, [(property, numpy type)]) of the vertex element, which must come first."""
    def bad(why: str) -> UserError:
        return UserError(f"{path}: not a point cloud PLY ({why}); point ply_file_path at the capture's points file "
                         f"or remove the key to start from random points")

    if f.readline().strip() != b"ply":
        raise bad("no 'ply' first line")
    fmt, count, props, element = None, None, [], None
    for _ in range(MAX_HEADER_LINES):
        line = f.readline()
        if not line:
            raise bad("the header has no end_header")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            element = words[1]
            if element == "vertex":
                count = int(words[2]) if words[2].isdigit() else None
            elif count is None:
                raise bad(f"its first element is '{element}', not 'vertex'")
        elif words[0] == "property" and element == "vertex":
            if len(words) != 3 or words[1] not in _TYPES:
                raise bad(f"vertex property '{' '.join(words[1:])}' is not a number")
            props.append((words[2], _TYPES[words[1]]))
    else:
        raise bad("the header has no end_header")
    if fmt not in _FORMATS:
        raise bad(f"format {fmt!r}")
    if count is None:
        raise bad("no vertex element")
    names = [p for p, _ in props]
    if not all(k in names for k in "xyz"):
        raise bad("its vertices have no x, y, z")
    return fmt, count, props


def read_points_ply(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(points [P, 3] float64, colours [P, 3] uint8) of a PLY's vertices; mid grey where it has no colour.
    UserError naming the file when it is missing, cut short or not a point cloud."""
    if not os.path.isfile(path):
        raise UserError(f"{path}: point cloud file not found; restore it, or remove ply_file_path to start from "
                        f"random points")
    with open(path, "rb") as f:
        fmt, count, props = _header(path, f)
        order = _FORMATS[fmt]
        if count == 0:
            columns = {name: np.zeros(0) for name, _ in props}
        elif order is None:
            try:
                table = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2)
            except ValueError as exc:
                raise UserError(f"{path}: corrupt point cloud PLY ({' '.join(str(exc).split())[:120]}); restore it "
                                "or remove ply_file_path") from None
            if table.shape != (count, len(props)):
                raise UserError(f"{path}: point cloud PLY cut short ({len(table)} of {count} vertices); restore it "
                                "or remove ply_file_path")
            columns = {name: table[:, i] for i, (name, _) in enumerate(props)}
        else:
            dtype = np.dtype([(name, order + t) for name, t in props])
            data = f.read(count * dtype.itemsize)
            if len(data) < count * dtype.itemsize:
                raise UserError(f"{path}: point cloud PLY cut short ({len(data)} of {count * dtype.itemsize} bytes "
                                "of vertices); restore it or remove ply_file_path")
            records = np.frombuffer(data, dtype=dtype, count=count)
            columns = {name: records[name].astype(np.float64) for name, _ in props}
    points = np.stack([columns[k] for k in "xyz"], axis=1)
    if not np.isfinite(points).all():
        raise UserError(f"{path}: {int((~np.isfinite(points).all(1)).sum())} points with non-finite coordinates; fix "
                        "the file or remove ply_file_path")
    types = dict(props)
    if all(k in columns for k in ("red", "green", "blue")):
        rgb = np.stack([columns[k] for k in ("red", "green", "blue")], axis=1)
        if types["red"].startswith("f"):
            rgb = rgb * 255.0  # float colours are in [0, 1]
        colors = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    else:
        colors = np.full((count, 3), 128, dtype=np.uint8)
    return points, colors


def write_points_ply(path: str, points: np.ndarray, colors: np.ndarray) -> None:
    """points [P, 3] and colours [P, 3] uint8 as an ASCII PLY, as nerfstudio writes its sparse_pc.ply; atomic."""
    lines = ["ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x", "property float y",
             "property float z", "property uint8 red", "property uint8 green", "property uint8 blue", "end_header"]
    body = [f"{x!r} {y!r} {z!r} {r} {g} {b}" for (x, y, z), (r, g, b)
            in zip(np.asarray(points, np.float64).tolist(), np.asarray(colors, np.uint8).tolist())]
    atomic.write_text(path, "\n".join(lines + body) + "\n")
