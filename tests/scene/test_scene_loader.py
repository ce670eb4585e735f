"""load_scene on the demo scene: split rule, cameras, intrinsics rescale, text models, errors."""

from __future__ import annotations

import json
import os

import numpy as np
import pycolmap
import pytest
import torch

from ctgs.errors import UserError
from ctgs.io.images import read_image, resize_image, write_image
from ctgs.scene import load_scene
from ctgs.scene.loader import is_test_index, scene_extent

from scene_fixtures import TINY


def _meta(scene_dir) -> dict:
    with open(os.path.join(scene_dir, "demo_meta.json")) as f:
        return json.load(f)


def test_split_rule_is_every_8th_of_sorted_names():
    assert [i for i in range(20) if is_test_index(i, 8)] == [0, 8, 16]
    assert not any(is_test_index(i, 0) for i in range(20))
    assert not any(is_test_index(i, None) for i in range(20))
    assert [i for i in range(7) if is_test_index(i, 3)] == [0, 3, 6]


def test_demo_scene_loads_with_true_cameras(tiny_demo_master):
    scene = load_scene(tiny_demo_master)
    meta = _meta(tiny_demo_master)
    n = TINY["num_views"]
    assert [v.name for v in scene.test] == ["000.png", "008.png"]
    assert len(scene.train) == n - 2
    names = sorted(v.name for v in scene.train + scene.test)
    assert names == [f"{i:03d}.png" for i in range(n)]
    assert [v.name for v in scene.train] == sorted(v.name for v in scene.train)

    intr = meta["intrinsics"]
    true_centers = {c["name"]: np.array(c["center"]) for c in meta["cameras"]}
    for view in scene.train + scene.test:
        cam = view.camera
        assert (cam.width, cam.height) == (TINY["width"], TINY["height"])
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((intr["fx"], intr["fy"], intr["cx"], intr["cy"]))
        assert cam.viewmat.dtype == torch.float32 and cam.viewmat.shape == (4, 4)
        np.testing.assert_allclose(cam.center.numpy(), true_centers[view.name], atol=1e-5)
        assert view.image.dtype == np.float32 and view.image.shape == (TINY["height"], TINY["width"], 3)
        assert 0.0 <= view.image.min() and view.image.max() <= 1.0 and view.image.std() > 0.05
    centers = np.stack(list(true_centers.values()))
    assert scene.extent == pytest.approx(1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max(), rel=1e-6)
    assert scene.extent == pytest.approx(scene_extent(centers))
    assert scene.points.shape == (TINY["points"], 3) and scene.points.dtype == np.float32
    assert scene.point_colors.shape == (TINY["points"], 3)
    assert 0.0 <= scene.point_colors.min() and scene.point_colors.max() <= 1.0


def _flat_surface_points(scene, meta):
    """Points on the demo's flat-coloured surfaces (a grid from the metadata: the SfM-like demo points
    avoid textureless surfaces), with that surface's colour."""
    pts, cols = [], []
    for s in meta["surfaces"]:
        if s["kind"] != "flat" or s["id"].startswith("box_"):  # box faces: mostly hidden by the box itself
            continue
        g = np.linspace(-0.95, 0.95, max(2, round(6 * np.sqrt(s["area"]))))  # ~36 points per unit area
        a, b = np.meshgrid(g * s["half_extents"][0], g * s["half_extents"][1])
        p = np.array(s["center"]) + a.reshape(-1, 1) * np.array(s["u"]) + b.reshape(-1, 1) * np.array(s["v"])
        pts.append(p)
        cols.append(np.broadcast_to(np.array(s["color"]), (len(p), 3)))
    return np.concatenate(pts), np.concatenate(cols)


def test_points_project_onto_their_colour(tiny_demo_master):
    """Cameras, image orientation and the pixel-centre convention agree: flat-surface points land on
    pixels of their surface's colour (occluded points and edge pixels excepted)."""
    scene = load_scene(tiny_demo_master, holdout=0)
    pts, cols = _flat_surface_points(scene, _meta(tiny_demo_master))
    assert len(pts) > 50
    hits, total = 0, 0
    for view in scene.train:
        cam = view.camera
        pc = pts @ cam.R.numpy().T + cam.t.numpy()  # [P, 3] camera space
        front = pc[:, 2] > 0.1
        x = cam.fx * pc[:, 0] / pc[:, 2] + cam.cx  # continuous image coords, pixel centres at +0.5
        y = cam.fy * pc[:, 1] / pc[:, 2] + cam.cy
        inside = front & (x >= 1) & (y >= 1) & (x < cam.width - 1) & (y < cam.height - 1)
        px, py = np.floor(x[inside]).astype(int), np.floor(y[inside]).astype(int)
        diff = np.abs(view.image[py, px] - cols[inside]).max(axis=1)
        hits += int((diff < 0.02).sum())
        total += int(inside.sum())
    assert total > 100
    assert hits / total > 0.6, f"only {hits}/{total} flat-surface points land on their colour"


def test_intrinsics_rescaled_per_axis(tiny_demo):
    """A folder of images at a size that is not an exact fraction (T&T-like): fx/cx scale by W ratio,
    fy/cy by the H ratio."""
    w, h = 33, 24  # from 64x48: x ratio 0.515625, y ratio 0.5
    src = os.path.join(tiny_demo, "images")
    for name in os.listdir(src):
        write_image(os.path.join(tiny_demo, "images_2", name), resize_image(read_image(os.path.join(src, name)), w, h))
    full = load_scene(tiny_demo, holdout=0, load_images=False)
    half = load_scene(tiny_demo, images="images_2", holdout=0)
    for a, b in zip(full.train, half.train):
        assert a.image is None and b.image.shape == (h, w, 3)
        assert (b.camera.width, b.camera.height) == (w, h)
        assert b.camera.fx == pytest.approx(a.camera.fx * w / 64)
        assert b.camera.cx == pytest.approx(a.camera.cx * w / 64)
        assert b.camera.fy == pytest.approx(a.camera.fy * h / 48)
        assert b.camera.cy == pytest.approx(a.camera.cy * h / 48)
        assert torch.equal(a.camera.viewmat, b.camera.viewmat)


def test_text_model_loads_the_same(tiny_demo):
    sparse = os.path.join(tiny_demo, "sparse", "0")
    rec = pycolmap.Reconstruction(sparse)
    for name in os.listdir(sparse):
        os.remove(os.path.join(sparse, name))
    rec.write_text(sparse)
    assert any(n.endswith(".txt") for n in os.listdir(sparse))
    scene = load_scene(tiny_demo, load_images=False)
    meta = _meta(tiny_demo)
    assert len(scene.train) + len(scene.test) == TINY["num_views"]
    assert scene.train[0].camera.fx == pytest.approx(meta["intrinsics"]["fx"], rel=1e-6)
    assert scene.points.shape == (TINY["points"], 3)


def _rewrite_camera(scene_dir, model: str, params) -> None:
    sparse = os.path.join(scene_dir, "sparse", "0")
    rec = pycolmap.Reconstruction(sparse)
    cam = rec.cameras[1]
    cam.model = model
    cam.params = params
    rec.write_binary(sparse)


def test_simple_radial_is_rejected_with_sfm_hint(tiny_demo):
    _rewrite_camera(tiny_demo, "SIMPLE_RADIAL", [50.0, 32.0, 24.0, 0.01])
    with pytest.raises(UserError) as err:
        load_scene(tiny_demo)
    message = str(err.value)
    assert "SIMPLE_RADIAL" in message and "ctgs sfm" in message and "cameras.bin" in message
    assert "\n" not in message


def test_simple_pinhole_is_accepted(tiny_demo):
    _rewrite_camera(tiny_demo, "SIMPLE_PINHOLE", [50.0, 30.0, 20.0])
    cam = load_scene(tiny_demo, load_images=False).train[0].camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (50.0, 50.0, 30.0, 20.0)


def test_validation_split_holds_out_every_kth_from_the_middle():
    from ctgs.scene.loader import validation_split

    views = list(range(10))
    assert validation_split(views, 4) == ([0, 1, 3, 4, 5, 7, 8, 9], [2, 6])
    assert validation_split(views, 0) == (views, [])
    train, val = validation_split(views, 8)
    assert val == [4] and len(train) == 9
