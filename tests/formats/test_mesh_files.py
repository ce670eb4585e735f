"""The mesh files `ctgs mesh` writes (.ply, .obj, .glb): read back by trimesh, the .glb through the Khronos glTF
validator, damaged files refused in one line, and the arrays the viewer uploads."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes
from test_export_cli import gltf_validator, validate  # noqa: F401  (gltf_validator: the fixture)

from ctgs.errors import UserError
from ctgs.formats.mesh import VIEWER_MESH_BIN, linear_to_srgb, read_mesh, viewer_mesh, write_mesh


def _sphere(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed sphere mesh from an n^3 grid, colours varying over it."""
    g = np.linspace(-1.2, 1.2, n)
    vol = np.linalg.norm(np.stack(np.meshgrid(g, g, g, indexing="ij"), -1), axis=-1) - 1.0
    v, f, _, _ = marching_cubes(vol.astype(np.float32), 0.0, spacing=(g[1] - g[0],) * 3)
    v = (v - 1.2).astype(np.float32)
    return v, f.astype(np.int64), np.clip((v + 1) / 2, 0, 1).astype(np.float32)


@pytest.fixture(scope="module", params=[24, 150], ids=["uint16_indices", "uint32_indices"])
def sphere(request):
    return _sphere(request.param)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_trimesh_reads_each_format_back(sphere, tmp_path, suffix):
    v, f, c = sphere
    path = str(tmp_path / f"mesh{suffix}")
    write_mesh(path, v, f, c)
    theirs = trimesh.load(path, process=False)
    if suffix == ".glb":  # a scene of one mesh; with a material, trimesh keeps COLOR_0 as stored (linear, uint16)
        (theirs,) = theirs.geometry.values()
        rgb = linear_to_srgb(theirs.visual.vertex_attributes["color"][:, :3] / 65535.0)
    else:
        rgb = theirs.visual.vertex_colors[:, :3] / 255.0
    assert len(theirs.vertices) == len(v) and np.array_equal(theirs.faces, f)
    assert np.allclose(theirs.vertices, v, atol=1e-5)
    assert np.abs(rgb - c).max() < 0.003
    assert theirs.is_watertight and theirs.volume > 0  # faces wound outwards
    v2, f2, c2 = read_mesh(path)
    assert np.allclose(v2, v, atol=1e-5) and np.array_equal(f2, f) and np.abs(c2 - c).max() < 0.003


def test_the_glb_passes_the_khronos_validator(sphere, tmp_path, gltf_validator):  # noqa: F811
    v, f, c = sphere
    path = str(tmp_path / "mesh.glb")
    write_mesh(path, v, f, c, origin=[120000.0, 0.0, -5.0])
    report = validate(gltf_validator, path)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    assert report["info"]["totalVertexCount"] == len(v) and report["info"]["totalTriangleCount"] == len(f)


def test_a_recentred_scene_says_where_its_origin_lies(tmp_path):
    v, f, c = _sphere(16)
    for suffix, marker in ((".ply", b"comment world_origin 120000.0 0.0 -5.0"),
                           (".obj", b"# world_origin 120000.0 0.0 -5.0")):
        path = str(tmp_path / f"m{suffix}")
        write_mesh(path, v, f, c, origin=[120000.0, 0.0, -5.0])
        assert marker in open(path, "rb").read(300)
    path = str(tmp_path / "m.glb")
    write_mesh(path, v, f, c, origin=[120000.0, 0.0, -5.0])
    scene = trimesh.load(path, process=False)
    transform, name = scene.graph.get(scene.graph.nodes_geometry[0])  # the mesh's node under the origin's
    placed = trimesh.transform_points(scene.geometry[name].vertices, transform)
    assert np.allclose(placed, v + [120000.0, 0.0, -5.0])


def test_damaged_files_are_refused_in_one_line(tmp_path):
    v, f, c = _sphere(16)
    path = str(tmp_path / "m.ply")
    write_mesh(path, v, f, c)
    data = open(path, "rb").read()
    open(path, "wb").write(data[:-7])
    with pytest.raises(UserError, match=r"m\.ply: not a mesh `ctgs mesh` writes \(ValueError: .*bytes of data"):
        read_mesh(path)
    with pytest.raises(UserError, match="a mesh file ends in"):
        read_mesh(str(tmp_path / "m.stl"))
    with pytest.raises(UserError, match="mesh file not found"):
        read_mesh(str(tmp_path / "none.glb"))
    bad = str(tmp_path / "bad.obj")
    open(bad, "w").write("v 0 0 0 1 1 1\nf 1 2 3\n")
    with pytest.raises(UserError, match="a face indexes past the 1 vertices"):
        read_mesh(bad)
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # no temporary left by the writes


def test_the_viewer_arrays_are_aligned_and_complete():
    v, f, c = _sphere(20)
    info, data = viewer_mesh(v, f, c)
    assert info["file"] == VIEWER_MESH_BIN and info["bytes"] == len(data)
    assert info["vertices"] == len(v) and info["triangles"] == len(f)
    arrays = info["arrays"]
    for name, (dtype, shape) in {"positions": ("float32", [len(v), 3]), "colors": ("uint8", [len(v), 4]),
                                 "indices": ("uint32", [len(f), 3])}.items():
        spec = arrays[name]
        assert spec["dtype"] == dtype and spec["shape"] == shape and spec["offset"] % 8 == 0
        back = np.frombuffer(data, dtype, count=shape[0] * shape[1], offset=spec["offset"]).reshape(shape)
        want = {"positions": v, "colors": None, "indices": f}[name]
        if want is not None:
            assert np.array_equal(back, want.astype(dtype))
        else:
            assert np.array_equal(back[:, :3], np.round(c * 255).astype(np.uint8)) and (back[:, 3] == 255).all()
