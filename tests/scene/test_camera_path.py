"""Camera paths for videos: fitted to rings of cameras around a point and to forward captures, a spline through
views, and camera path files in nerfstudio's layout (written, read back, refused in one line when broken)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ctgs.errors import UserError
from ctgs.scene.camera_path import (OBJECT_CENTRIC_MAX, Rig, camera_path_json, fit_path, look_at, path_cameras,
                                    read_camera_path, spline_poses)

UP = np.array([0.0, 0.0, 1.0])
FOCUS = np.array([0.3, -0.2, 0.5])


def ring(n: int = 24, radius=(2.0, 1.2), height: float = 0.6, arc: float = 2 * math.pi) -> list[np.ndarray]:
    """n cameras on an ellipse about FOCUS (axes x, y; z up), looking at FOCUS."""
    out = []
    for k in range(n):
        t = arc * k / n
        eye = FOCUS + np.array([radius[0] * math.cos(t), radius[1] * math.sin(t), height])
        out.append(look_at(eye, FOCUS, UP))
    return out


def forward_rig(n: int = 20, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """A forward capture: cameras jittered over a 1 x 0.4 x 0.6 box about the origin, looking along +y at points 3
    to 8 units away."""
    g = np.random.default_rng(seed)
    mats = []
    for _ in range(n):
        eye = np.array([g.uniform(-0.5, 0.5), g.uniform(-0.2, 0.2), g.uniform(-0.3, 0.3)])
        mats.append(look_at(eye, eye + np.array([0.02 * g.normal(), 1.0, 0.02 * g.normal()]), UP))
    points = np.stack([g.uniform(-3, 3, 500), g.uniform(3, 8, 500), g.uniform(-2, 2, 500)], 1)
    return mats, points


def centers_and_axes(viewmats):
    rig = Rig.of(viewmats)
    return rig.centers, rig.forward, rig.up


def test_the_rig_reads_centres_and_axes_of_world_to_camera_matrices():
    v = look_at([1.0, 2.0, 3.0], [1.0, 5.0, 3.0], UP)
    c, f, u = centers_and_axes([v])
    assert np.allclose(c[0], [1, 2, 3]) and np.allclose(f[0], [0, 1, 0]) and np.allclose(u[0], UP)
    assert np.isclose(np.linalg.det(v[:3, :3]), 1.0)


def test_orbit_around_a_360_capture_circles_its_focus_on_the_cameras_ellipse():
    cams = ring()
    rig = Rig.of(cams)
    assert rig.object_centric() and np.allclose(rig.focus(), FOCUS, atol=1e-6)
    assert np.allclose(rig.scene_up(), UP, atol=0.5)  # (the cameras look down at the focus: their up leans in)
    path = fit_path("orbit", cams, 72)
    c, f, u = centers_and_axes(path)
    # every frame looks at the focus, from the ellipse the cameras lie on, at their height
    to_focus = FOCUS - c
    assert np.allclose(f, to_focus / np.linalg.norm(to_focus, axis=1, keepdims=True), atol=1e-9)
    d = c - FOCUS
    assert np.allclose((d[:, 0] / 2.0) ** 2 + (d[:, 1] / 1.2) ** 2, 1.0, atol=1e-6)
    assert np.allclose(d[:, 2], 0.6, atol=1e-9)
    # a closed loop, evenly stepped: the step from the last frame back to the first is like any other
    steps = np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1)
    assert steps.max() < 1.01 * steps.min() and steps.max() < 0.2
    # it starts at the first training camera and goes all the way round
    assert np.allclose(c[0], Rig.of(cams).centers[0], atol=1e-6)
    assert np.ptp(np.unwrap(np.arctan2(d[:, 1], d[:, 0]))) > 2 * math.pi * 0.95
    # the image's up stays the scene's: the camera's x axis is horizontal
    x = np.stack([m[0, :3] for m in path])
    assert np.abs(x @ UP).max() < 1e-9


def test_spiral_around_a_360_capture_rises_and_falls_within_the_cameras_heights():
    cams = []
    for k, v in enumerate(ring(height=0.0)):  # heights going three times up and down: -0.4 .. 0.4
        c = Rig.of([v]).centers[0] + np.array([0, 0, 0.4 * math.sin(3 * 2 * math.pi * k / 24)])
        cams.append(look_at(c, FOCUS, UP))
    up = Rig.of(cams).scene_up()  # (tilted a little: the cameras above and below the focus lean their up vectors)
    heights = (Rig.of(cams).centers - FOCUS) @ up
    lo, hi = np.percentile(heights, [10, 90])
    c, _, _ = centers_and_axes(fit_path("spiral", cams, 60))
    h = (c - FOCUS) @ up
    assert h.min() >= lo - 1e-9 and h.max() <= hi + 1e-9 and np.ptp(h) > 0.99 * (hi - lo)
    flat, _, _ = centers_and_axes(fit_path("orbit", cams, 60))
    assert np.ptp((flat - FOCUS) @ up) < 1e-9  # the orbit keeps their mean height


def test_a_half_circle_is_still_a_capture_around_its_focus_and_a_forward_capture_is_not():
    assert Rig.of(ring(arc=math.pi)).object_centric()  # |mean direction| 2/pi < OBJECT_CENTRIC_MAX
    mats, _ = forward_rig()
    assert not Rig.of(mats).object_centric()
    assert np.linalg.norm(Rig.of(mats).forward.mean(0)) > OBJECT_CENTRIC_MAX


@pytest.mark.parametrize("kind", ["orbit", "spiral"])
def test_a_forward_capture_circles_in_front_looking_at_a_point_inside_the_scene(kind):
    mats, points = forward_rig()
    path = fit_path(kind, mats, 40, points)
    c, f, _ = centers_and_axes(path)
    train = Rig.of(mats).centers
    # within the patch the cameras cover (90th percentile of their offsets), never behind or ahead of them
    for axis in (0, 1, 2):
        assert np.abs(c[:, axis] - train[:, axis].mean()).max() <= np.percentile(
            np.abs(train[:, axis] - train[:, axis].mean()), 90) * 1.05 + 1e-6
    fwd = Rig.of(mats).forward.mean(0)
    along = np.ptp(c @ (fwd / np.linalg.norm(fwd)))
    assert along > 0.05 if kind == "spiral" else along < 1e-6  # the spiral moves along the view, the orbit not
    # every frame looks at one focus point, ahead of the nearest points and inside the scene
    focus = Rig.of(path).focus()
    miss = np.linalg.norm(np.cross(focus - c, f), axis=1)
    assert miss.max() < 1e-6
    depth = focus[1] - train[:, 1].mean()
    assert np.percentile(points[:, 1], 10) < depth < 5 * points[:, 1].max()


def test_interpolate_runs_from_the_first_to_the_last_view_smoothly_through_views_in_name_order():
    cams = ring(n=30, arc=math.pi)
    path = fit_path("interpolate", cams, 90)
    c, f, _ = centers_and_axes(path)
    train = Rig.of(cams)
    assert np.allclose(c[0], train.centers[0], atol=1e-9) and np.allclose(c[-1], train.centers[-1], atol=1e-9)
    assert np.allclose(f[0], train.forward[0], atol=1e-9) and np.allclose(f[-1], train.forward[-1], atol=1e-9)
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert steps.max() < 1.5 * np.median(steps)  # evenly spaced, no jump
    turn = np.degrees(np.arccos(np.clip((f[1:] * f[:-1]).sum(1), -1, 1)))
    assert turn.max() < 5.0


def test_spline_passes_through_every_keyframe_and_turns_on_the_spot_without_nan():
    keys = [look_at([0, 0, 0], [1, 0, 0], UP), look_at([1, 1, 0], [2, 1, 0], UP), look_at([2, 0, 0], [2, 1, 0], UP)]
    rig = Rig.of(keys)
    # keyframe positions split the path's length at frames 0, 50 and 100 when the segments are equal
    path = spline_poses(rig.centers, rig.forward, rig.up, 101)
    c, _, _ = centers_and_axes(path)
    assert np.allclose(c[[0, 50, 100]], rig.centers, atol=1e-9)
    still = Rig.of([look_at([0, 0, 0], [1, 0, 0], UP), look_at([0, 0, 0], [0, 1, 0], UP)])
    turned = spline_poses(still.centers, still.forward, still.up, 10)
    assert all(np.isfinite(v).all() for v in turned)
    assert np.allclose(Rig.of(turned[-1:]).forward[0], [0, 1, 0], atol=1e-9)


def test_path_cameras_have_the_size_and_vertical_field_of_view_asked_for():
    cams = path_cameras(ring(n=4), math.radians(50.0), 320, 180, 0.01)
    assert len(cams) == 4 and (cams[0].width, cams[0].height) == (320, 180)
    assert math.isclose(2 * math.degrees(math.atan(90 / cams[0].fy)), 50.0, rel_tol=1e-9)
    assert cams[0].fx == cams[0].fy and (cams[0].cx, cams[0].cy) == (160.0, 90.0)


def test_a_camera_path_file_reads_back_as_written(tmp_path):
    frames = fit_path("orbit", ring(), 12)
    data = camera_path_json(frames, math.radians(40.0), 200, 134, 24.0, keyframes=frames[:3])
    # nerfstudio's layout: these keys, camera_to_world as 16 numbers, OpenGL camera axes (z backward)
    for key in ("camera_type", "render_width", "render_height", "fps", "seconds", "keyframes", "camera_path"):
        assert key in data
    first = np.array(data["camera_path"][0]["camera_to_world"]).reshape(4, 4)
    assert np.allclose(-first[:3, 2], Rig.of(frames[:1]).forward[0])  # looks down -z
    assert data["seconds"] == 12 / 24.0 and len(data["keyframes"]) == 3
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps(data))
    read = read_camera_path(str(path))
    assert (read.width, read.height, read.fps) == (200, 134, 24.0)
    assert all(np.allclose(a, b, atol=1e-12) for a, b in zip(read.viewmats, frames))
    assert np.allclose(read.fov_y, math.radians(40.0))


BAD = [
    ("{", "not a JSON camera path"),
    ('{"camera_path": []}', "no camera_path entries"),
    ('{"camera_type": "fisheye", "camera_path": [{}]}', "only perspective"),
    ('{"render_width": 0, "render_height": 10, "fps": 30, "camera_path": [{}]}', "render_width is 0"),
    ('{"render_width": 10, "render_height": 10, "fps": 0, "camera_path": [{}]}', "fps is 0"),
    ('{"render_width": 10, "render_height": 10, "fps": 30, "camera_path": [{"fov": 0, "camera_to_world": []}]}',
     "camera_path[0].fov is 0"),
    ('{"render_width": 10, "render_height": 10, "fps": 30, "camera_path": [{"fov": 50, "camera_to_world": [1, 2]}]}',
     "camera_path[0].camera_to_world has 2 numbers"),
    ('{"render_width": 10, "render_height": 10, "fps": 30, "camera_path": [{"fov": 50, "camera_to_world": '
     '[2,0,0,0, 0,2,0,0, 0,0,2,0, 0,0,0,1]}]}', "camera_path[0].camera_to_world is not a rigid transform"),
    ('{"render_width": 10, "render_height": 10, "fps": 30, "camera_path": [{"fov": 50, "camera_to_world": "x"}]}',
     "camera_path[0].camera_to_world"),
]


@pytest.mark.parametrize("text, says", BAD)
def test_a_broken_camera_path_file_is_one_error_naming_the_file_the_entry_and_the_fix(tmp_path, text, says):
    path = tmp_path / "path.json"
    path.write_text(text)
    with pytest.raises(UserError) as err:
        read_camera_path(str(path))
    msg = str(err.value)
    assert msg.startswith(str(path)) and says in msg and "ctgs view" in msg and "\n" not in msg


def test_a_missing_camera_path_file_says_so(tmp_path):
    with pytest.raises(UserError, match="camera path file not found"):
        read_camera_path(str(tmp_path / "none.json"))
