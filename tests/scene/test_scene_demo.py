"""The demo scene generator: exact ray caster, metadata, determinism, idempotence, CLI."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.io.images import read_image
from ctgs.scene.demo import make_demo_scene
from ctgs.scene.raycast import Rect, render

from scene_fixtures import TINY


def test_raycaster_reproduces_a_texture_seen_at_one_texel_per_pixel():
    """A fronto-parallel photo rectangle sized so one texel covers one pixel renders as the texture
    itself (pins the pixel-centre convention, the texture orientation and bilinear weights)."""
    w, h, f, depth = 12, 8, 20.0, 5.0
    tex = np.random.default_rng(0).random((h, w, 3))
    px = depth / f  # world units per pixel at that depth
    rect = Rect("t", "photo", np.array([0.0, 0.0, depth]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]),
                (w / 2 * px, h / 2 * px), np.zeros(3), texture=tex)
    image = render([rect], np.eye(4), f, f, w / 2, h / 2, w, h, ss=1)
    np.testing.assert_allclose(image, tex, atol=1e-5)


def test_raycaster_keeps_the_nearest_surface_and_antialiases_edges():
    near = Rect("near", "flat", np.array([0.0, 0, 2]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (0.5, 5.0),
                np.array([1.0, 0, 0]))
    far = Rect("far", "flat", np.array([0.0, 0, 4]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (5.0, 5.0),
               np.array([0, 0, 1.0]))
    # near strip covers x in [-0.5, 0.5] at depth 2 -> pixels [cx - f/4, cx + f/4) = [7.5, 12.5): edge pixels mixed
    image = render([far, near], np.eye(4), 10.0, 10.0, 10.0, 5.0, 20, 10, ss=4)
    assert np.allclose(image[:, 9:12], [1, 0, 0])  # fully covered by the near (red) strip
    assert np.allclose(image[:, :7], [0, 0, 1]) and np.allclose(image[:, 13:], [0, 0, 1])
    assert np.allclose(image[:, 7], [0.5, 0, 0.5])  # half-covered edge pixel: exact coverage with 4x4 samples


def test_metadata_describes_surfaces_and_points_lie_on_them(tiny_demo_master):
    with open(os.path.join(tiny_demo_master, "demo_meta.json")) as f:
        meta = json.load(f)
    kinds = [s["kind"] for s in meta["surfaces"]]
    assert set(kinds) == {"photo", "flat", "smooth"} and kinds.count("photo") >= 3
    for s in meta["surfaces"]:
        u, v, n = (np.array(s[k]) for k in ("u", "v", "normal"))
        np.testing.assert_allclose(np.cross(u, v), n, atol=1e-12)
        assert abs(u @ v) < 1e-12 and abs(np.linalg.norm(n) - 1) < 1e-12
        assert s["area"] == pytest.approx(4 * s["half_extents"][0] * s["half_extents"][1])
        assert s["kind"] != "photo" or len(s["texture_resolution"]) == 2
    from ctgs.scene.colmap import read_colmap_model

    model = read_colmap_model(os.path.join(tiny_demo_master, "sparse", "0"))
    assert len(model.points) == TINY["points"]
    dist = np.full(len(model.points), np.inf)
    for s in meta["surfaces"]:
        rel = model.points - np.array(s["center"])
        lx, ly = rel @ np.array(s["u"]), rel @ np.array(s["v"])
        inside = (np.abs(lx) <= s["half_extents"][0] + 1e-9) & (np.abs(ly) <= s["half_extents"][1] + 1e-9)
        dist = np.where(inside, np.minimum(dist, np.abs(rel @ np.array(s["normal"]))), dist)
    assert dist.max() < 1e-9  # every point lies on some surface


def test_surface_of_classifies_points_by_surface(tiny_demo_master):
    from ctgs.scene.colmap import read_colmap_model
    from measures.demo_surfaces import load_demo_meta, surface_of

    meta = load_demo_meta(tiny_demo_master)
    points = read_colmap_model(os.path.join(tiny_demo_master, "sparse", "0")).points
    ids = surface_of(points, meta)
    assert (ids >= 0).all()  # every sampled point lies on a surface
    floor = [s["id"] for s in meta["surfaces"]].index("floor")
    assert surface_of(np.array([[0.3, -2.0, 0.001], [0.3, -2.0, 0.5], [9.0, 9.0, 0.0]]), meta).tolist() == \
        [floor, -1, -1]
    # SfM-like points: textured (photo) surfaces get far more points per unit area than flat ones
    kinds = np.array([meta["surfaces"][i]["kind"] for i in ids])
    area = {k: sum(s["area"] for s in meta["surfaces"] if s["kind"] == k) for k in ("photo", "flat")}
    density = {k: (kinds == k).sum() / area[k] for k in area}
    assert density["photo"] > 5 * density["flat"], density


def test_deterministic_for_a_seed_and_idempotent(tmp_path, tiny_demo_master):
    params = dict(TINY, num_views=3)
    a = make_demo_scene(str(tmp_path / "a"), **params)
    b = make_demo_scene(str(tmp_path / "b"), **params)
    c = make_demo_scene(str(tmp_path / "c"), **dict(params, seed=params["seed"] + 1))
    for name in ("000.png", "002.png"):
        assert (tmp_path / "a" / "images" / name).read_bytes() == (tmp_path / "b" / "images" / name).read_bytes()
    assert (tmp_path / "a" / "sparse/0/points3D.bin").read_bytes() == (tmp_path / "b" / "sparse/0/points3D.bin").read_bytes()
    assert (tmp_path / "a" / "sparse/0/points3D.bin").read_bytes() != (tmp_path / "c" / "sparse/0/points3D.bin").read_bytes()
    mtime = os.path.getmtime(os.path.join(a, "images", "000.png"))
    assert make_demo_scene(a, **params) == a and os.path.getmtime(os.path.join(a, "images", "000.png")) == mtime
    with pytest.raises(UserError, match="--force"):
        make_demo_scene(a, **dict(params, num_views=4))
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # no temporary folders left
    assert read_image(os.path.join(b, "images", "000.png")).shape == (TINY["height"], TINY["width"], 3)


def test_cli_writes_a_colmap_scene(tmp_path):
    out = tmp_path / "cli_scene"
    result = CliRunner().invoke(main, ["demo-scene", str(out), "--views", "3", "--width", "32", "--height", "24",
                                       "--points", "50", "--supersample", "1"])
    assert result.exit_code == 0, result.output
    assert sorted(os.listdir(out / "images")) == ["000.png", "001.png", "002.png"]
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= set(os.listdir(out / "sparse" / "0"))
    assert (out / "demo_meta.json").is_file()
