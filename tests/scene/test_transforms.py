"""transforms.json scenes (nerfstudio, instant-ngp, Blender synthetic): the demo scene written in each layout reads
back as its COLMAP scene; camera conventions (one render, both ways); distortion, masks, transparency, random
initial points, levels; and the errors that name the file and the key."""

from __future__ import annotations

import json
import math
import os
import shutil

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.io.images import read_image, write_image
from ctgs.render import render
from ctgs.scene import conventions, load_scene
from ctgs.scene.transforms import read_transforms
from ctgs.train.start.init import init_model

from scene_layouts import write_blender, write_instant_ngp, write_nerfstudio

TEST_NAMES = {"000.png", "008.png"}  # the tiny demo's every-8th views


@pytest.fixture(scope="module")
def layouts(tiny_demo_master, tmp_path_factory):
    root = tmp_path_factory.mktemp("layouts")
    ns = write_nerfstudio(tiny_demo_master, str(root / "ns"))
    return {"colmap": tiny_demo_master, "nerfstudio": ns, "instant-ngp": write_instant_ngp(ns, str(root / "ngp")),
            "blender": write_blender(ns, str(root / "blender"), TEST_NAMES)}


def _doc(scene: str) -> dict:
    with open(os.path.join(scene, "transforms.json")) as f:
        return json.load(f)


def _save(scene: str, doc: dict, name: str = "transforms.json") -> None:
    with open(os.path.join(scene, name), "w") as f:
        json.dump(doc, f)


def _copy(scene: str, tmp_path) -> str:
    return shutil.copytree(scene, str(tmp_path / os.path.basename(scene)), symlinks=False)


@pytest.mark.parametrize("layout", ["nerfstudio", "instant-ngp", "blender"])
def test_each_layout_reads_as_the_colmap_scene(layouts, layout):
    ref, got = load_scene(layouts["colmap"]), load_scene(layouts[layout])
    assert got.meta["layout"] == layout
    assert [v.name for v in ref.test] == [v.name.removeprefix("test_") for v in got.test] == sorted(TEST_NAMES)
    assert len(got.train) == len(ref.train)
    for a, b in zip(ref.train + ref.test, got.train + got.test):
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height)
        assert (b.camera.fx, b.camera.fy, b.camera.cx, b.camera.cy) == \
            pytest.approx((a.camera.fx, a.camera.fy, a.camera.cx, a.camera.cy), rel=1e-9)
        np.testing.assert_allclose(b.camera.viewmat.numpy(), a.camera.viewmat.numpy(), atol=2e-7)
        np.testing.assert_array_equal(b.image, a.image)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-6)
    np.testing.assert_array_equal(got.point_colors, ref.point_colors)
    assert got.extent == pytest.approx(ref.extent, rel=1e-6)


def test_one_model_renders_the_same_from_both_conventions(layouts):
    """A model placed on the demo's points, rendered from each view's camera as COLMAP gives it (OpenCV axes) and as
    nerfstudio's transforms.json gives it (OpenGL axes, z-up world): the same images."""
    ref, ns = load_scene(layouts["colmap"], load_images=False), load_scene(layouts["nerfstudio"], load_images=False)
    model = init_model(ref.points, ref.point_colors, max_points=300, opacity=0.8, max_sh_degree=0,
                       random_rotation=True, texture_mode="none", fixed_res=1, seed=0)
    inputs = model.render_inputs()
    for a, b in zip(ref.train + ref.test, ns.train + ns.test):
        ra = render(inputs, a.camera, backend="cpu", sh_degree=0)
        rb = render(inputs, b.camera, backend="cpu", sh_degree=0)
        assert float(ra.alpha.detach().mean()) > 0.2  # the model is in view: the comparison compares something
        torch.testing.assert_close(rb.rgb, ra.rgb, atol=1e-5, rtol=0)


def test_opengl_and_opencv_axes():
    """A camera at (1, 2, 3) looking down world -y with world z up: OpenGL's c2w has its z column (backward) along
    +y and its y column (up) along +z; ctgs's viewmat looks down +z_camera = world -y, with y_camera down."""
    c2w = np.array([[-1, 0, 0, 1], [0, 0, 1, 2], [0, 1, 0, 3], [0, 0, 0, 1]], dtype=float)
    v = conventions.viewmat_from_opengl_c2w(c2w)
    np.testing.assert_allclose(v[2, :3], [0, -1, 0], atol=1e-12)  # forward
    np.testing.assert_allclose(v[1, :3], [0, 0, -1], atol=1e-12)  # image down = world down
    np.testing.assert_allclose(v[0, :3], [-1, 0, 0], atol=1e-12)  # image right
    np.testing.assert_allclose(-v[:3, :3].T @ v[:3, 3], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(conventions.opengl_c2w_from_viewmat(v), c2w, atol=1e-12)


def test_nerfstudio_world_is_read_back_in_colmap_world(layouts):
    """nerfstudio's file holds the z-up world (its applied_transform): its matrices differ from the COLMAP poses."""
    doc = _doc(layouts["nerfstudio"])
    assert doc["applied_transform"] == conventions.NERFSTUDIO_APPLIED_TRANSFORM.tolist()
    ref = load_scene(layouts["colmap"], load_images=False)
    first = np.array(doc["frames"][0]["transform_matrix"])
    centre = ref.test[0].camera.center.double().numpy()  # 000.png
    np.testing.assert_allclose(first[:3, 3], [centre[0], centre[2], -centre[1]], atol=1e-6)


def test_random_points_without_a_point_file(layouts, tmp_path):
    scene = _copy(layouts["instant-ngp"], tmp_path)
    doc = _doc(scene)
    del doc["ply_file_path"], doc["aabb_scale"]
    _save(scene, doc)
    s = load_scene(scene, load_images=False)
    assert s.meta["points"] == "random" and "ply_file_path" in s.meta["points_note"]
    assert "the cube the cameras look at" in s.meta["points_note"]
    lo, hi = s.points.min(0), s.points.max(0)
    assert np.all(lo < [0.0, 0.6, 0.6]) and np.all(hi > [0.0, 0.6, 0.6])  # the demo's cameras look at this point
    # instant-ngp's aabb: its unit cube (scale 0.33, offset 0.5) grown aabb_scale times, in the file's world
    doc["aabb_scale"], doc["scale"], doc["offset"] = 2, 0.5, [0.5, 0.5, 0.25]
    _save(scene, doc)
    s = load_scene(scene, load_images=False)
    assert "aabb_scale 2" in s.meta["points_note"]
    np.testing.assert_allclose(s.points.min(0), [0.5 - 2, -2, -2], atol=0.01)  # centre (x, y, z) = (0.5, 0, 0)
    np.testing.assert_allclose(s.points.max(0), [0.5 + 2, 2, 2], atol=0.01)


def test_distorted_photos_are_undistorted(layouts, tmp_path):
    """Photos distorted with OpenCV's k1 k2 p1 p2 through the file's camera read back as the pinhole photos, seen
    through the undistorted camera."""
    import cv2

    scene = _copy(layouts["nerfstudio"], tmp_path)
    doc = _doc(scene)
    coeffs = {"k1": -0.12, "k2": 0.03, "p1": 0.002, "p2": -0.001}
    k = np.array([[doc["fl_x"], 0, doc["cx"]], [0, doc["fl_y"], doc["cy"]], [0, 0, 1]])
    d = np.array([coeffs["k1"], coeffs["k2"], coeffs["p1"], coeffs["p2"], 0.0])
    w, h = doc["w"], doc["h"]
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    ideal = cv2.undistortPoints(grid, k, d, P=k).reshape(h, w, 2).astype(np.float32)  # where each pixel looks
    name = "003.png"
    clean = read_image(os.path.join(scene, "images", name))
    distorted = cv2.remap(clean, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    write_image(os.path.join(scene, "images", name), distorted)
    doc.update(coeffs, camera_model="OPENCV")
    _save(scene, doc)
    view = next(v for v in load_scene(scene).train if v.name == name)
    assert view.distortion is not None and view.camera.fx != pytest.approx(doc["fl_x"])
    # the pinhole photo resampled into the undistorted camera: pixel q sees ray K_new^-1 q, at K K_new^-1 q in it
    c = view.camera
    a = k @ np.linalg.inv(np.array([[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]]))
    expected = cv2.warpAffine(clean, a[:2], (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    inner = (slice(6, h - 6), slice(6, w - 6))
    err = np.abs(view.image[inner] - expected[inner][..., :3]).mean()
    assert err < 0.012, err
    assert np.abs(distorted[inner][..., :3] - expected[inner][..., :3]).mean() > 2 * err  # (distortion was visible)


def test_masks_from_a_folder_and_from_mask_path(layouts, tmp_path):
    scene = _copy(layouts["nerfstudio"], tmp_path)
    mask = np.ones((48, 64))
    mask[:, :20] = 0.0
    write_image(os.path.join(scene, "masks", "001.png"), mask)  # masks/ beside images/, same name
    doc = _doc(scene)
    write_image(os.path.join(scene, "own", "m2.png"), 1.0 - mask)
    doc["frames"][2]["mask_path"] = "own/m2.png"
    _save(scene, doc)
    views = {v.name: v for v in load_scene(scene).train}
    assert views["001.png"].mask.shape == (48, 64) and not views["001.png"].mask[:, :20].any()
    assert views["001.png"].mask[:, 20:].all()
    assert views["002.png"].mask[:, :20].all() and not views["002.png"].mask[:, 20:].any()
    assert views["003.png"].mask is None
    # a level (images_2, made from images/) reads the full-size masks shrunk to it
    small = {v.name: v for v in load_scene(scene, images="images_2").train}
    assert small["001.png"].mask.shape == (24, 32) and not small["001.png"].mask[:, :10].any()
    assert small["001.png"].camera.fx == pytest.approx(views["001.png"].camera.fx / 2)
    write_image(os.path.join(scene, "masks", "001.png"), np.zeros((48, 64)))
    with pytest.raises(UserError, match=r"masks/001.png: the mask leaves no pixel"):
        load_scene(scene)


def test_transparent_photos_over_the_background(layouts, tmp_path):
    alpha = np.ones((48, 64))
    alpha[10:20, 10:30] = 0.0
    scene = write_blender(layouts["nerfstudio"], str(tmp_path / "rgba"), TEST_NAMES, points=False,
                          alpha={"001.png": alpha})
    black = {v.name: v for v in load_scene(scene).train}
    white = {v.name: v for v in load_scene(scene, background=(1.0, 1.0, 1.0)).train}
    v = white["train_001.png"]
    assert v.alpha is not None and v.alpha.shape == (48, 64, 1)
    assert black["train_002.png"].alpha is None  # opaque photos keep no alpha
    np.testing.assert_allclose(v.image[10:20, 10:30], 1.0)
    np.testing.assert_allclose(black["train_001.png"].image[10:20, 10:30], 0.0)
    np.testing.assert_allclose(v.image[30:], black["train_001.png"].image[30:])


def test_blender_scene_reads_a_smaller_level_in_memory(layouts):
    full = load_scene(layouts["blender"], load_images=False)
    half = load_scene(layouts["blender"], images="images_2")
    assert [v.name for v in half.test] == ["test_000.png", "test_008.png"]
    v, f = half.train[0], full.train[0]
    assert v.image.shape == (24, 32, 3) and (v.camera.width, v.camera.height) == (32, 24)
    assert v.camera.fx == pytest.approx(f.camera.fx / 2)
    assert not os.path.exists(os.path.join(layouts["blender"], "images_2"))


def test_nerfstudio_split_lists(layouts, tmp_path):
    scene = _copy(layouts["nerfstudio"], tmp_path)
    doc = _doc(scene)
    doc["test_filenames"] = ["images/003.png", "images/004.png", "images/005.png"]
    _save(scene, doc)
    s = load_scene(scene, load_images=False)
    assert [v.name for v in s.test] == ["003.png", "004.png", "005.png"] and len(s.train) == 7
    assert "own" in s.meta["split"]


def _error(scene: str, *fragments: str) -> str:
    """`ctgs convert` on a bad scene: one error line naming each fragment, a user error exit code, nothing written."""
    out = os.path.join(os.path.dirname(scene), "converted")
    result = CliRunner().invoke(main, ["convert", scene, "--to", "colmap", "-o", out])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == UserError.exit_code and len(lines) == 1 and lines[0].startswith("error: "), result.output
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert not os.path.exists(out)
    return lines[0]


def _broken(layouts, tmp_path, change, layout="nerfstudio") -> str:
    scene = _copy(layouts[layout], tmp_path)
    name = "transforms_train.json" if layout == "blender" else "transforms.json"
    with open(os.path.join(scene, name)) as f:
        doc = json.load(f)
    change(doc, scene)
    _save(scene, doc, name)
    return os.path.join(scene, name)


def test_error_missing_frames(layouts, tmp_path):
    path = _broken(layouts, tmp_path, lambda d, s: d.pop("frames"))
    _error(os.path.dirname(path), path, "'frames'")


def test_error_image_missing(layouts, tmp_path):
    path = _broken(layouts, tmp_path, lambda d, s: os.remove(os.path.join(s, "images", "004.png")))
    _error(os.path.dirname(path), f"{path}: frames[4]", "'file_path'", "004.png")


@pytest.mark.parametrize("bad, words", [(float("nan"), "non-finite"), (0.0, "not invertible"),
                                        (2.0, "scaled or sheared")])
def test_error_bad_matrix(layouts, tmp_path, bad, words):
    def change(doc, scene):
        m = np.array(doc["frames"][3]["transform_matrix"])
        m[:3, :3] = m[:3, :3] * bad if bad == bad else bad
        doc["frames"][3]["transform_matrix"] = m.tolist()

    path = _broken(layouts, tmp_path, change)
    line = _error(os.path.dirname(path), f"{path}: frames[3]", "'transform_matrix'")
    assert words in line


def test_error_mixed_sizes_without_per_frame_intrinsics(layouts, tmp_path):
    def change(doc, scene):
        del doc["w"], doc["h"]
        write_image(os.path.join(scene, "images", "006.png"), np.zeros((24, 32, 3)))

    path = _broken(layouts, tmp_path, change)
    _error(os.path.dirname(path), path, "006.png", "32x24", "'w'", "'h'", "'fl_x'")


def test_error_blender_missing_frames_and_other_keys(layouts, tmp_path):
    path = _broken(layouts, tmp_path, lambda d, s: d.pop("frames"), layout="blender")
    _error(os.path.dirname(path), path, "'frames'")
    path = _broken(layouts, tmp_path / "b", lambda d, s: d.pop("camera_angle_x"), layout="blender")
    _error(os.path.dirname(path), f"{path}: frames[0]", "'fl_x'", "'camera_angle_x'")
    path = _broken(layouts, tmp_path / "c", lambda d, s: d.update(camera_model="OPENCV_FISHEYE"))
    _error(os.path.dirname(path), path, "'camera_model'", "OPENCV_FISHEYE")
    path = _broken(layouts, tmp_path / "d", lambda d, s: d.update(ply_file_path="gone.ply"))
    _error(os.path.dirname(path), path, "'ply_file_path'", "gone.ply")


def test_error_not_json(layouts, tmp_path):
    scene = _copy(layouts["nerfstudio"], tmp_path)
    with open(os.path.join(scene, "transforms.json"), "w") as f:
        f.write('{"frames": [')
    _error(scene, os.path.join(scene, "transforms.json"), "not valid JSON")


def test_frames_without_extension_and_sorted_names(layouts):
    fs = read_transforms(layouts["instant-ngp"])
    assert fs.layout == "instant-ngp" and [f.name for f in fs.frames] == sorted(f.name for f in fs.frames)
    assert all(f.path.endswith(".png") for f in fs.frames)
    assert math.isclose(fs.frames[0].intrinsics.pinhole(64, 48, (64, 48))[0],
                        load_scene(layouts["colmap"], load_images=False).test[0].camera.fx, rel_tol=1e-9)
