"""Initial points where the training views see no SfM point (ctgs.train.start.fill, config key init_fill)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from ctgs.render.camera import Camera
from ctgs.train.components.shell import OCCUPANCY_CELL_PX
from ctgs.train.start.fill import FILL_CELL_PX, fill_points


def _view(image, x=0.0):
    h, w = image.shape[:2]
    vm = torch.eye(4, dtype=torch.float64)
    vm[0, 3] = -x  # camera centre at (x, 0, 0), looking down +z
    cam = Camera(fx=60.0, fy=60.0, cx=w / 2, cy=h / 2, width=w, height=h, viewmat=vm)
    return SimpleNamespace(camera=cam, image=image.astype(np.float32))


def _plane_with_a_hole(rng, n=8000, depth=4.0):
    """SfM points on the plane z = depth beyond the image's edges, none where x > 0.4 (the right part of the image)."""
    pts = np.stack([rng.uniform(-6.0, 0.4, n), rng.uniform(-4.0, 4.0, n), np.full(n, depth)], 1)
    return pts


def _image(w=160, h=96):
    img = np.zeros((h, w, 3), np.float32)
    img[..., 0] = np.linspace(0, 1, w)[None, :]  # red grows to the right
    img[..., 2] = 0.5
    return img


def test_fill_points_lie_in_the_hole_at_the_depth_of_the_points_around_it_and_take_the_cells_colour():
    rng = np.random.default_rng(0)
    pts = _plane_with_a_hole(rng)
    view = _view(_image())
    xyz, rgb = fill_points(pts, [view])
    cam = view.camera
    assert len(xyz) > 0
    u = cam.fx * xyz[:, 0] / xyz[:, 2] + cam.cx
    v = cam.fy * xyz[:, 1] / xyz[:, 2] + cam.cy
    sfm_u = cam.fx * pts[:, 0] / pts[:, 2] + cam.cx
    # Only where no SfM point comes within a dilated occupancy cell, on cell centres.
    assert (u > sfm_u.max() + OCCUPANCY_CELL_PX).all()
    assert np.allclose((u - FILL_CELL_PX / 2 - 0.5) % FILL_CELL_PX, 0, atol=1e-6)
    assert np.allclose((v - FILL_CELL_PX / 2 - 0.5) % FILL_CELL_PX, 0, atol=1e-6)
    # Every open cell centre of the right part gets one.
    right_cols = np.arange(FILL_CELL_PX // 2, cam.width, FILL_CELL_PX)
    right_cols = right_cols[right_cols > sfm_u.max() + 2 * OCCUPANCY_CELL_PX]
    assert len(xyz) >= len(right_cols) * (cam.height // FILL_CELL_PX)
    # The plane's depth (the median of the nearest SfM points'), and the cell's mean colour.
    assert np.allclose(xyz[:, 2], 4.0, atol=1e-9)
    assert np.allclose(rgb[:, 0], (np.round(u - 0.5)) / (cam.width - 1), atol=0.01)
    assert np.allclose(rgb[:, 2], 0.5)


def test_a_region_two_views_see_is_filled_once():
    rng = np.random.default_rng(1)
    pts = _plane_with_a_hole(rng)
    one = fill_points(pts, [_view(_image())])[0]
    two = fill_points(pts, [_view(_image()), _view(_image(), x=0.05)])[0]
    # The second view, a little to the right, sees the first view's fill points where it sees the hole: it adds only
    # along the strip the first did not see.
    assert len(one) <= len(two) < 1.3 * len(one)


def test_no_fill_where_the_points_cover_the_view_or_a_view_has_too_few_points():
    rng = np.random.default_rng(2)
    full = np.stack([rng.uniform(-6.0, 6.0, 12000), rng.uniform(-4.0, 4.0, 12000), np.full(12000, 4.0)], 1)
    xyz, rgb = fill_points(full, [_view(_image())])
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    xyz, _ = fill_points(full[:5], [_view(_image())])  # no depth to borrow
    assert xyz.shape == (0, 3)


def test_init_fill_adds_primitives_at_initialisation(tmp_path):
    from ctgs.runs import training_scene
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=6, width=96, height=72, points=60)
    counts = {}
    for fill in ("false", "true"):
        run = str(tmp_path / f"run_{fill}")
        cfg = resolve_config(scene_dir, run, None, 1, [f"init_fill={fill}", "threads=1"], None, False, None, None,
                             preset="fast")
        scene = training_scene(cfg)
        counts[fill] = Trainer(cfg, scene, run).model.num_primitives
    expected = len(fill_points(scene.points, scene.train)[0])
    assert expected > 0 and counts["true"] == counts["false"] + expected
