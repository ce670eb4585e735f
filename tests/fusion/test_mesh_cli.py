"""`ctgs mesh` end to end on a model that is the demo scene's surfaces: the mesh against the exact geometry, read back
by a third-party library (trimesh), and bad input refused in one line. The file formats themselves:
tests/formats/test_mesh_files.py."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from surface_model import demo_scene, surface_model, write_run

from ctgs.cli import main
from ctgs.formats.mesh import read_mesh
from ctgs.scene.loader import load_scene
from measures.demo_surfaces import load_demo_meta
from measures.mesh_accuracy import mesh_accuracy

RESOLUTION = "192"  # voxels across the scene extent (5.6 world units): 2.9 cm voxels on a 5 m room


def _mesh(*args: str):
    return CliRunner().invoke(main, ["mesh", *args])


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> dict:
    root = str(tmp_path_factory.mktemp("mesh_demo"))
    scene = demo_scene(root)
    run = write_run(os.path.join(root, "run"), surface_model(), scene)
    out = os.path.join(root, "mesh.ply")
    res = _mesh(run, "-o", out, "--resolution", RESOLUTION)
    assert res.exit_code == 0, res.output
    return {"root": root, "scene": scene, "run": run, "ply": out, "output": res.output}


def _accuracy(vertices, faces, scene: str) -> dict:
    cams = [v.camera for v in load_scene(scene, load_images=False).train]
    return mesh_accuracy(vertices, faces, load_demo_meta(scene), cams, samples=100_000)


def test_the_mesh_lies_on_the_true_surfaces(demo):
    v, f, c = read_mesh(demo["ply"])
    acc = _accuracy(v, f, demo["scene"])
    voxel = 5.6 / int(RESOLUTION)
    assert acc["accuracy_median"] < voxel and acc["completeness_median"] < voxel, acc
    assert acc["chamfer"] < 0.035 and acc["normal_consistency"] > 0.8 and acc["fscore"]["0.05"]["f"] > 0.85, acc
    # the same check fails a mesh 6 cm off every wall and the floor
    shifted = _accuracy(v + np.float32([0.06, 0.06, 0.06]), f, demo["scene"])
    assert shifted["chamfer"] > 0.05 and shifted["fscore"]["0.02"]["f"] < 0.3, (acc, shifted)
    # colours: the surfaces' colours (the floor's gravel photo is tinted sand; the left wall flat blue-grey)
    left = (v[:, 0] < -2.4) & (v[:, 2] > 0.1)  # the wall, not the floor's strip beside it
    assert np.abs(c[left].mean(0) - [0.50, 0.60, 0.75]).max() < 0.05, c[left].mean(0)


def test_trimesh_reads_the_mesh_back(demo):
    v, f, c = read_mesh(demo["ply"])
    theirs = trimesh.load(demo["ply"], process=False)
    assert len(theirs.vertices) == len(v) and len(theirs.faces) == len(f) > 10000
    assert np.array_equal(theirs.faces, f) and np.allclose(theirs.vertices, v)
    assert np.array_equal(theirs.visual.vertex_colors[:, :3], np.round(c * 255).astype(np.uint8))


def test_the_command_says_what_it_made(demo):
    assert "volume: " in demo["output"] and " triangles (" in demo["output"]
    assert not [n for n in os.listdir(demo["root"]) if n.startswith(".") or n.endswith(".tmp")]


def test_contracted_space_meshes_the_room_too(demo, tmp_path):
    out = str(tmp_path / "contracted.ply")
    res = _mesh(demo["run"], "-o", out, "--bound", "contract", "--resolution", "96")
    assert res.exit_code == 0, res.output
    v, f, _ = read_mesh(out)
    acc = _accuracy(v, f, demo["scene"])
    assert acc["accuracy_median"] < 0.06 and acc["fscore"]["0.05"]["f"] > 0.6, acc


@pytest.mark.parametrize("args, says", [
    (["-o", "{root}/mesh.stl"], "a mesh file ends in .ply, .obj, .glb"),
    (["-o", "{root}/x.ply", "--max-memory", "0.05", "--resolution", RESOLUTION],
     "but --max-memory allows 0.05 GB; pass --voxel-size"),
])
def test_bad_input_is_one_line_and_writes_nothing(demo, tmp_path, args, says):
    root = str(tmp_path)
    res = _mesh(demo["run"], *[a.format(root=root) for a in args])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert lines[-1].startswith("error: ") and says in lines[-1], res.output
    assert os.listdir(root) == []


def test_a_folder_is_no_mesh_file(demo, tmp_path):
    res = _mesh(demo["run"], "-o", str(tmp_path))
    assert res.exit_code == 2 and "is a directory" in res.output and os.listdir(tmp_path) == []


def test_a_missing_run_says_how_to_make_one(tmp_path):
    res = _mesh(str(tmp_path / "nope"), "-o", str(tmp_path / "m.ply"))
    assert res.exit_code == 2 and "run folder not found" in res.output and not os.path.exists(tmp_path / "m.ply")


def test_the_default_voxel_coarsens_to_fit_the_memory_allowed(demo, tmp_path):
    """Without --resolution or --voxel-size, a volume too big for --max-memory is meshed at a voxel that fits (and
    says so) instead of stopping."""
    out = str(tmp_path / "fit.ply")
    res = _mesh(demo["run"], "-o", out, "--max-memory", "0.002")
    assert res.exit_code == 0, res.output
    assert "would not fit in 0.002 GB" in res.output and os.path.isfile(out)
    plan_line = next(ln for ln in res.output.splitlines() if ln.startswith("volume: "))
    assert float(plan_line.split(" voxels of ")[1].split()[0]) > float(plan_line.split("(voxels of ")[1].split()[0])


def test_default_vertices_follow_the_pixels_of_the_photos(demo):
    """The default voxel is two pixels at the cameras' distance: the same surfaces seen through cameras of twice the
    resolution give about four times the vertices (and the 2-pixel voxel the rule names)."""
    from ctgs.fusion.pipeline import MeshOptions, extract, fuse, pixel_voxel, plan_volume
    from ctgs.fusion.domain import camera_sphere
    from ctgs.fusion.pipeline import _camera_arrays

    model = surface_model()
    cams = [v.camera for v in load_scene(demo["scene"], load_images=False).train]
    counts = {}
    for factor in (1, 2):
        scaled = [c.scaled(factor) for c in cams]
        plan = plan_volume(model, scaled, None, MeshOptions())
        radius = camera_sphere(*_camera_arrays(scaled))[1]
        assert plan.domain.voxel == pytest.approx(2 * radius / scaled[0].fx, rel=0.01)
        assert plan.domain.voxel == pytest.approx(pixel_voxel(scaled, radius))
        counts[factor] = extract(fuse(model, scaled, plan, "cpu"), 50)[0].num_vertices
    assert 3.0 < counts[2] / counts[1] < 5.0, counts


def test_the_median_depth_stays_on_the_surface_where_the_mean_is_pulled_off(demo):
    """Half-transparent surfaces with a second layer 0.5 world units behind each: the median depth is the front
    layer's (as without the second layer), the mean lies between them."""
    import torch

    from ctgs.fusion.pipeline import view_maps
    from ctgs.model.surfels import SurfelModel
    from ctgs.render.geometry import quat_to_rotmat

    front = surface_model()
    front.opacity_logits.fill_(-0.5)  # opacity 0.38: overlapping, they still take T below 0.5 at most pixels
    normals = quat_to_rotmat(front.quats)[:, :, 2]
    state = front.state_dict()
    both = {k: torch.cat([v, v]) if torch.is_tensor(v) and v.ndim and len(v) == front.num_primitives else v
            for k, v in state.items()}
    both["means"] = torch.cat([front.means, front.means - 0.5 * normals])  # behind: the normals face the room
    layered = SurfelModel.from_state_dict(both)
    cam = load_scene(demo["scene"], load_images=False).train[0].camera
    maps = {}
    for name, model in (("front", front), ("layered", layered)):
        with torch.no_grad():
            inputs = model.render_inputs()
            maps[name] = {k: view_maps(inputs, cam, "cpu", 0, 100.0, k)[0] for k in ("median", "mean")}
    seen = (maps["front"]["median"] > 0) & (maps["layered"]["median"] > 0)
    assert seen.float().mean() > 0.8
    on = (maps["layered"]["median"][seen] - maps["front"]["median"][seen]).abs() < 1e-3
    assert on.float().mean() > 0.95  # (observed 0.988)
    pulled = maps["layered"]["mean"][seen] - maps["front"]["median"][seen]
    assert float(pulled.median()) > 0.04  # (observed 0.072)
