"""Triangle meshes with vertex colours (`ctgs mesh`): binary PLY, OBJ and glTF binary, written atomically, read back.

- PLY: `binary_little_endian 1.0`, vertex x y z (float) red green blue (uchar), face vertex_indices (uchar count, int
  indices): what MeshLab, Open3D, trimesh and Blender read.
- OBJ: `v x y z r g b` (colours in [0, 1], the extension MeshLab, trimesh and Blender read) and `f a b c` (1-based).
- GLB: one mesh, POSITION (float32), COLOR_0 (unsigned short normalised RGBA, linear as glTF requires: the sRGB
  colours are decoded), indices (uint16 or uint32), an unlit material (KHR_materials_unlit: the colours come from
  renders and already hold the lighting). glTF viewers make flat normals themselves.

Positions are the model's frame. A recentred scene's origin in the COLMAP frame is a PLY comment and an OBJ comment
`world_origin X Y Z`, and a glTF root node's translation (as `ctgs export` writes it: float32 far from the origin
would lose detail).
"""

from __future__ import annotations

import errno
import os

import numpy as np

from ctgs.errors import UserError
from ctgs.formats.gltf import FLOAT, UINT16, UINT32, UNLIT, ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, _Blob, finish
from ctgs.io import atomic

MESH_SUFFIXES = (".ply", ".obj", ".glb")
GENERATOR = "ctgs mesh"
PLY_FACE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def mesh_suffix(path: str) -> str:
    """The output's suffix (.ply, .obj or .glb); UserError naming the path otherwise."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in MESH_SUFFIXES:
        raise UserError(f"{path}: a mesh file ends in {', '.join(MESH_SUFFIXES)}; pass -o NAME.ply, NAME.obj or NAME.glb")
    return suffix


def write_mesh(path: str, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, origin=None) -> int:
    """Write the mesh (vertices [V, 3], faces [F, 3], colors [V, 3] sRGB in [0, 1]) in the format its suffix names,
    atomically. origin: [3] where the model's frame has its origin in the COLMAP frame (a recentred scene). Returns
    the file's bytes."""
    suffix = mesh_suffix(path)
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.int64)
    c = np.clip(np.asarray(colors, np.float64), 0.0, 1.0)
    origin = [float(x) for x in origin] if origin is not None and any(origin) else None
    if suffix == ".glb":
        _write_glb(path, v, f, c, origin)
    else:
        with atomic.atomic_path(path) as tmp, open(tmp, "wb") as fh:
            if suffix == ".ply":
                _write_ply(fh, v, f, c, origin)
            else:
                _write_obj(fh, v, f, c, origin)
    return os.path.getsize(path)


def _write_ply(fh, v: np.ndarray, f: np.ndarray, c: np.ndarray, origin) -> None:
    header = ["ply", "format binary_little_endian 1.0", f"comment {GENERATOR}"]
    if origin:
        header.append("comment world_origin " + " ".join(repr(x) for x in origin))
    header += [f"element vertex {len(v)}", "property float x", "property float y", "property float z",
               "property uchar red", "property uchar green", "property uchar blue",
               f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    fh.write(("\n".join(header) + "\n").encode("ascii"))
    rec = np.empty(len(v), np.dtype([("p", "<f4", (3,)), ("c", "u1", (3,))]))
    rec["p"] = v
    rec["c"] = np.round(c * 255)
    fh.write(rec.tobytes())
    tri = np.empty(len(f), PLY_FACE)
    tri["n"] = 3
    tri["i"] = f
    fh.write(tri.tobytes())


def _write_obj(fh, v: np.ndarray, f: np.ndarray, c: np.ndarray, origin) -> None:
    fh.write(f"# {GENERATOR}: {len(v)} vertices, {len(f)} triangles; v x y z r g b\n".encode())
    if origin:
        fh.write(("# world_origin " + " ".join(repr(x) for x in origin) + "\n").encode())
    rows = 1 << 18  # lines formatted at a time
    for s in range(0, len(v), rows):
        block = np.concatenate([v[s:s + rows].astype(np.float64), c[s:s + rows]], 1)
        fh.write("".join("v %.7g %.7g %.7g %.4f %.4f %.4f\n" % tuple(r) for r in block).encode())
    for s in range(0, len(f), rows):
        fh.write("".join("f %d %d %d\n" % tuple(r) for r in f[s:s + rows] + 1).encode())


def _write_glb(path: str, v: np.ndarray, f: np.ndarray, c: np.ndarray, origin) -> None:
    # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
    import pygltflib as g

    gltf = g.GLTF2(asset=g.Asset(generator=GENERATOR, version="2.0"), scene=0, extensionsUsed=[UNLIT])
    blob = _Blob(gltf)
    rgba = np.ones((len(c), 4))
    rgba[:, :3] = srgb_to_linear(c)
    index_type, np_index = (UINT16, np.uint16) if len(v) <= 65535 else (UINT32, np.uint32)
    pos = blob.accessor(v, FLOAT, "VEC3", ARRAY_BUFFER, minmax=True)
    col = blob.accessor(np.round(rgba * 65535).astype(np.uint16), UINT16, "VEC4", ARRAY_BUFFER)
    gltf.accessors[col].normalized = True  # COLOR_0 as unsigned shorts: normalised to [0, 1]
    idx = blob.accessor(f.reshape(-1).astype(np_index), index_type, "SCALAR", ELEMENT_ARRAY_BUFFER)
    gltf.materials.append(g.Material(name="mesh", doubleSided=True, extensions={UNLIT: {}},
                                     pbrMetallicRoughness=g.PbrMetallicRoughness(metallicFactor=0.0,
                                                                                 roughnessFactor=1.0)))
    gltf.meshes.append(g.Mesh(name="mesh", primitives=[g.Primitive(
        attributes=g.Attributes(POSITION=pos, COLOR_0=col), indices=idx, material=0)]))
    gltf.nodes.append(g.Node(mesh=0, name="mesh"))
    finish(gltf, blob, [0], origin)
    with atomic.atomic_path(path) as tmp:
        # pygltflib reports a failed write by returning False, not by raising
        if not gltf.save_binary(tmp) or os.path.getsize(tmp) == 0:
            raise OSError(errno.EIO, "pygltflib could not write the file", path)


# ---- reading (what `ctgs view --mesh` shows) ------------------------------------------------------------------------
def read_mesh(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices [V, 3] float32, faces [F, 3] int64, colors [V, 3] float32 sRGB in [0, 1]) of a mesh `ctgs mesh` wrote;
    UserError naming the file otherwise."""
    suffix = mesh_suffix(path)
    if not os.path.isfile(path):
        raise UserError(f"{path}: mesh file not found; write one with `ctgs mesh RUN_DIR -o {os.path.basename(path)}`")
    reader = {".ply": _read_ply, ".obj": _read_obj, ".glb": _read_glb}[suffix]
    try:
        v, f, c = reader(path)
    except (ValueError, IndexError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a mesh `ctgs mesh` writes ({type(exc).__name__}: {exc}); write it again with "
                        "`ctgs mesh`") from None
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise UserError(f"{path}: a face indexes past the {len(v)} vertices; the file is damaged, write it again")
    return v, f, c


def _read_ply(path: str):
    with open(path, "rb") as fh:
        data = fh.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("no PLY header")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    counts = {p[1]: int(p[2]) for p in (line.split() for line in header) if len(p) == 3 and p[0] == "element"}
    if "binary_little_endian 1.0" not in " ".join(header) or set(counts) != {"vertex", "face"}:
        raise ValueError("not a binary PLY of vertices and faces")
    body = data[end + len(b"end_header\n"):]
    vdt = np.dtype([("p", "<f4", (3,)), ("c", "u1", (3,))])
    nv, nf = counts["vertex"], counts["face"]
    if len(body) != nv * vdt.itemsize + nf * PLY_FACE.itemsize:
        raise ValueError(f"{len(body)} bytes of data where the header asks for {nv} vertices and {nf} triangles")
    verts = np.frombuffer(body, vdt, count=nv)
    tris = np.frombuffer(body, PLY_FACE, count=nf, offset=nv * vdt.itemsize)
    if nf and (tris["n"] != 3).any():
        raise ValueError("faces other than triangles")
    return verts["p"].copy(), tris["i"].astype(np.int64), verts["c"].astype(np.float32) / 255


def _read_obj(path: str):
    verts, faces = [], []
    with open(path, encoding="ascii") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:7]])
            elif line.startswith("f "):
                faces.append([int(x.split("/")[0]) - 1 for x in line.split()[1:4]])
    v = np.asarray(verts, np.float64).reshape(-1, 6)
    return v[:, :3].astype(np.float32), np.asarray(faces, np.int64).reshape(-1, 3), v[:, 3:].astype(np.float32)


def _read_glb(path: str):
    # pygltflib only where a glTF file is written or read (ctgs.formats loads every format)
    import pygltflib as g

    gltf = g.GLTF2().load(path)
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    types = {FLOAT: np.float32, UINT16: np.uint16, UINT32: np.uint32}
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def accessor(i: int) -> np.ndarray:
        a = gltf.accessors[i]
        view = gltf.bufferViews[a.bufferView]
        start = (view.byteOffset or 0) + (a.byteOffset or 0)
        return np.frombuffer(blob, types[a.componentType], count=a.count * widths[a.type], offset=start).reshape(a.count, -1)

    v = accessor(prim.attributes.POSITION).astype(np.float32)
    c = linear_to_srgb(accessor(prim.attributes.COLOR_0)[:, :3] / 65535.0).astype(np.float32)
    return v, accessor(prim.indices).reshape(-1, 3).astype(np.int64), c


# ---- what the viewer draws ------------------------------------------------------------------------------------------
VIEWER_MESH_BIN = "mesh.bin"


def viewer_mesh(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> tuple[dict, bytes]:
    """(the `mesh` entry of the viewer's bundle.json, the bytes of its mesh.bin) for a mesh: little-endian arrays a
    browser uploads to WebGL2 buffers as they are, each at an 8-byte aligned offset: positions float32 [V, 3], colors
    uint8 [V, 4] (sRGB, alpha 255), indices uint32 [F, 3]."""
    rgba = np.full((len(vertices), 4), 255, np.uint8)
    rgba[:, :3] = np.round(np.clip(colors, 0, 1) * 255)
    parts, arrays, offset = [], {}, 0
    for name, arr in (("positions", np.asarray(vertices, "<f4")), ("colors", rgba),
                      ("indices", np.asarray(faces, "<u4"))):
        pad = (-offset) % 8
        parts.append(b"\0" * pad)
        offset += pad
        data = np.ascontiguousarray(arr).tobytes()
        arrays[name] = {"offset": offset, "dtype": {"f": "float32", "u": f"uint{arr.itemsize * 8}"}[arr.dtype.kind],
                        "shape": list(arr.shape)}
        parts.append(data)
        offset += len(data)
    info = {"file": VIEWER_MESH_BIN, "vertices": int(len(vertices)), "triangles": int(len(faces)), "bytes": offset,
            "arrays": arrays}
    return info, b"".join(parts)
