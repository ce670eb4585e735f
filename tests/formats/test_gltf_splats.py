"""KHR_gaussian_splatting .glb (ctgs.formats.gltf_splats): the attributes read by hand, the round trip, the frame, and the
file against the one PlayCanvas's `splat-transform` writes from our 3DGS PLY (the same attributes, the same frame)
and against the Khronos validator (which does not know the extension yet: only its attribute names are flagged)."""

from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import pygltflib
import pytest
import torch
from factory_io import random_model
from npm_cache import npm_package
from test_export_cli import VALIDATE_JS, VALIDATOR

from ctgs.errors import UserError
from ctgs.formats.gltf_splats import EXTENSION, read_glb_splats, write_glb_splats
from ctgs.formats.plain_ply import SH_C0, read_plain_ply, texture_means, write_plain_ply


def _unit(q: torch.Tensor) -> torch.Tensor:
    q = torch.nn.functional.normalize(q.double(), dim=1)
    return q * torch.where(q[:, :1] < 0, -1.0, 1.0)


def _attributes(path) -> tuple[dict[str, np.ndarray], dict]:
    """Every attribute of the first primitive as float64 arrays (decoded here from the accessors), and its
    extensions."""
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    out = {}
    for name, index in prim.attributes.__dict__.items():
        if index is None:
            continue
        a = gltf.accessors[index]
        view = gltf.bufferViews[a.bufferView]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a.type]
        dtype = {5126: "<f4", 5121: "u1"}[a.componentType]
        out[name] = np.frombuffer(blob, dtype, a.count * width, (view.byteOffset or 0) + (a.byteOffset or 0)) \
            .reshape(a.count, width).astype(np.float64)
    return out, prim.extensions


def test_attributes_by_hand(tmp_path):
    m = random_model(n=80, sh_degree=3, seed=6)
    info = write_glb_splats(m, str(tmp_path / "m.glb"))
    assert info == {"bytes": os.path.getsize(tmp_path / "m.glb"), "splats": 80, "sh_degree": 2}
    attrs, ext = _attributes(tmp_path / "m.glb")
    assert ext == {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                               "sortingMethod": "cameraDistance", "projection": "perspective"}}
    assert sorted(attrs) == sorted(["POSITION", "COLOR_0"] + [f"{EXTENSION}:{k}" for k in (
        "ROTATION", "SCALE", "OPACITY", "SH_DEGREE_0_COEF_0", *[f"SH_DEGREE_1_COEF_{c}" for c in range(3)],
        *[f"SH_DEGREE_2_COEF_{c}" for c in range(5)])])
    means = m.means.double().numpy()
    np.testing.assert_allclose(attrs["POSITION"], means * [-1, -1, 1], rtol=1e-6)  # half a turn about z
    scale = attrs[f"{EXTENSION}:SCALE"]
    np.testing.assert_allclose(np.log(scale[:, :2]), m.log_scales.double().numpy(), atol=1e-6)
    np.testing.assert_allclose(scale[:, 2], 1e-3 * scale[:, :2].min(1), rtol=1e-5)
    np.testing.assert_allclose(attrs[f"{EXTENSION}:OPACITY"][:, 0], m.opacities.double().numpy(), atol=1e-7)
    dc = m.sh[:, 0].double().numpy() + texture_means(m).numpy() / SH_C0
    np.testing.assert_allclose(attrs[f"{EXTENSION}:SH_DEGREE_0_COEF_0"], dc, atol=1e-6)
    np.testing.assert_allclose(attrs["COLOR_0"][:, 3], np.round(m.opacities.double().numpy() * 255), atol=0)
    # the rotation turned with the frame: R' = T R with T = diag(-1, -1, 1)
    from ctgs.render.geometry import quat_to_rotmat

    xyzw = torch.from_numpy(attrs[f"{EXTENSION}:ROTATION"])
    r_file = quat_to_rotmat(torch.cat([xyzw[:, 3:], xyzw[:, :3]], 1))
    r_model = quat_to_rotmat(torch.nn.functional.normalize(m.quats.double(), dim=1))
    torch.testing.assert_close(r_file, torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64)) @ r_model,
                               atol=1e-6, rtol=0)


def test_round_trip_in_the_colmap_frame(tmp_path):
    m = random_model(n=60, sh_degree=3, seed=7)
    write_glb_splats(m, str(tmp_path / "m.glb"))
    back = read_glb_splats(str(tmp_path / "m.glb"))
    ref = read_plain_ply_of(m, tmp_path)
    torch.testing.assert_close(back.means, ref.means, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.log_scales, ref.log_scales, atol=1e-5, rtol=0)
    torch.testing.assert_close(_unit(back.quats), _unit(ref.quats), atol=1e-6, rtol=0)
    torch.testing.assert_close(back.opacities, ref.opacities, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.sh, ref.sh[:, :9], atol=1e-6, rtol=0)  # SH bands un-turned


def read_plain_ply_of(m, tmp_path):
    write_plain_ply(m, str(tmp_path / "ref.ply"))
    return read_plain_ply(str(tmp_path / "ref.ply"))


def test_a_recentred_scene_gets_a_root_translation(tmp_path):
    m = random_model(n=10, sh_degree=1, seed=1)
    write_glb_splats(m, str(tmp_path / "m.glb"), origin=[1000.0, 2.0, -3.0])
    gltf = pygltflib.GLTF2().load(str(tmp_path / "m.glb"))
    root = gltf.nodes[gltf.scenes[0].nodes[0]]
    assert root.translation == [-1000.0, -2.0, -3.0] and root.children == [0]


def test_bad_files_are_refused(tmp_path):
    from ctgs.formats.gltf import write_glb

    write_glb(random_model(n=5, sh_degree=1, seed=1), str(tmp_path / "quads.glb"))
    with pytest.raises(UserError, match=r"quads.glb: no KHR_gaussian_splatting primitive"):
        read_glb_splats(str(tmp_path / "quads.glb"))
    (tmp_path / "x.glb").write_bytes(b"glTF nonsense")
    with pytest.raises(UserError, match=r"x.glb: not a readable glTF binary"), \
            pytest.warns(UserWarning, match="pygltflib does not support version"):  # pygltflib's own word on it
        read_glb_splats(str(tmp_path / "x.glb"))


@pytest.fixture(scope="session")
def splat_transform() -> tuple[str, str]:
    # its one install script (webgpu's) only clears a macOS quarantine flag: not needed to read and write files
    node, package = npm_package("@playcanvas/splat-transform@3.7.0", "@playcanvas/splat-transform",
                                "PlayCanvas's reader and writer", ignore_scripts=True)
    return node, f"{package}/bin/cli.mjs"


def test_the_same_file_as_playcanvas_writes(tmp_path, splat_transform):
    """splat-transform turns our 3DGS PLY into a KHR_gaussian_splatting .glb; ours holds the same attributes to
    float32 (its SH padded to degree 3 as in the PLY: ours stops at the model's degree 2), in the same frame."""
    m = random_model(n=200, sh_degree=3, seed=9)
    m.quats.data = torch.nn.functional.normalize(m.quats.data, dim=1)  # splat-transform copies quaternions as read
    write_glb_splats(m, str(tmp_path / "ours.glb"))
    write_plain_ply(m, str(tmp_path / "m.ply"))
    node, cli = splat_transform
    p = subprocess.run([node, cli, "-q", "-w", str(tmp_path / "m.ply"), str(tmp_path / "theirs.glb")],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    ours, ours_ext = _attributes(tmp_path / "ours.glb")
    theirs, theirs_ext = _attributes(tmp_path / "theirs.glb")
    assert ours_ext == theirs_ext
    assert set(ours) <= set(theirs) and all(k.startswith(f"{EXTENSION}:SH_DEGREE_3") for k in set(theirs) - set(ours))
    for name, value in ours.items():
        atol = 1e-6 * max(1.0, float(np.abs(value).max()))
        if name.endswith("ROTATION"):
            np.testing.assert_allclose(np.abs((value * theirs[name]).sum(1)), 1.0, atol=1e-6)
        else:
            np.testing.assert_allclose(value, theirs[name], atol=atol, rtol=1e-6, err_msg=name)


@pytest.fixture(scope="session")
def gltf_validator() -> tuple[str, str]:
    return npm_package(VALIDATOR, "gltf-validator", "the Khronos glTF validator")


def test_the_khronos_validator_flags_only_the_extensions_attribute_names(tmp_path, gltf_validator):
    """The validator (2.0.0-dev.3.10, the newest on npm) does not know KHR_gaussian_splatting: it reports the
    extension as unsupported and each of its attribute names as invalid (it does the same to splat-transform's
    files). Nothing else: accessors, buffer views, bounds and the GLB container pass."""
    write_glb_splats(random_model(n=40, sh_degree=3, seed=2), str(tmp_path / "m.glb"))
    node, package = gltf_validator
    p = subprocess.run([node, "-e", VALIDATE_JS, package, str(tmp_path / "m.glb")], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    report = json.loads(p.stdout)
    messages = report["issues"]["messages"]
    other = [x for x in messages if not (x["code"] == "UNSUPPORTED_EXTENSION" or (
        x["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" and f"/attributes/{EXTENSION}:" in x["pointer"]))]
    assert other == [], other
    assert sum(x["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" for x in messages) == 4 + 3 + 5
    assert report["info"]["totalVertexCount"] == 40
