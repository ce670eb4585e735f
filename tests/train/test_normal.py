"""2DGS's depth-normal consistency and depth-distortion terms (ctgs.train.components.normal, config keys lambda_normal /
normal_from, lambda_dist / dist_from)."""

from __future__ import annotations

import math

import pytest
import torch

from ctgs.render import render
from ctgs.render.camera import Camera
from ctgs.render.geometry import rotmat_to_quat
from ctgs.render.types import SurfelInputs
from ctgs.train.components.normal import (consistency, depth_normals, distortion, distortion_map, facing_normals,
                                          geometry_terms, normal_inputs, normal_loss)

W, H, F = 32, 24, 30.0


def cam(dtype=torch.float32) -> Camera:
    return Camera(fx=F, fy=F * 1.1, cx=W / 2 + 0.3, cy=H / 2 - 0.2, width=W, height=H,
                  viewmat=torch.eye(4, dtype=dtype))


def rot(axis: str, deg: float, dtype=torch.float32) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    m = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]]}[axis]
    return torch.tensor(m, dtype=dtype)


def surfels(rots, means, scales, opacities, dtype=torch.float32) -> SurfelInputs:
    n = len(rots)
    quats = rotmat_to_quat(torch.stack(rots).to(dtype))
    return SurfelInputs(
        means=torch.tensor(means, dtype=dtype), quats=quats, scales=torch.tensor(scales, dtype=dtype),
        opacities=torch.tensor(opacities, dtype=dtype), sh=torch.zeros(n, 1, 3, dtype=dtype),
        texel_size=torch.ones(n, dtype=dtype), textures=torch.zeros(0, 3, dtype=dtype),
        tex_res=torch.zeros(n, 2, dtype=torch.int32), tex_offset=torch.zeros(n, dtype=torch.int64))


def test_depth_normals_of_a_tilted_plane_face_the_camera():
    c = cam(torch.float64)
    n = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
    n = n / n.norm()  # facing the camera (n . X < 0 for points in front)
    d = -4.0  # plane n . X = d
    u = (torch.arange(W, dtype=torch.float64) + 0.5 - c.cx) / c.fx
    v = (torch.arange(H, dtype=torch.float64) + 0.5 - c.cy) / c.fy
    ray = torch.stack([u[None, :].expand(H, W), v[:, None].expand(H, W), torch.ones(H, W, dtype=torch.float64)], -1)
    z = d / (ray @ n)  # depth along +z of the plane hit
    alpha = torch.full((H, W), 0.5, dtype=torch.float64)
    got = depth_normals(z * alpha, alpha, c)  # the renderer's depth is alpha-weighted
    assert torch.allclose(got[1:-1, 1:-1], n.expand(H - 2, W - 2, 3), atol=1e-9)
    assert got[0].abs().max() == 0 and got[:, -1].abs().max() == 0  # the border has no central difference
    alpha[5, 7] = 0.0
    assert depth_normals(z * alpha, alpha, c)[5, 7].abs().max() == 0  # nothing drawn there


def test_facing_normals_turn_towards_the_camera():
    s = surfels([torch.eye(3), rot("x", 180.0), rot("y", 40.0)], [[0, 0, 3.0], [0.2, 0, 3.0], [0, 0, 3.0]],
                [[0.1, 0.1]] * 3, [0.5] * 3)
    n = facing_normals(s.means, s.quats, cam())
    assert torch.allclose(n[0], torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)  # +z normal flipped
    assert torch.allclose(n[1], torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)  # already facing
    assert torch.allclose(n.norm(dim=-1), torch.ones(3), atol=1e-6)
    assert (n * s.means).sum(-1).max() < 0


def test_the_normal_render_is_the_alpha_weighted_normal_and_agrees_with_its_depth():
    """One tilted surfel covering the view: N_r / alpha is its facing normal at every drawn pixel, the expected depth
    describes the same plane, so the term is mean(1 - alpha^2) away from the border and the surfel's edge."""
    R = rot("y", 30.0) @ rot("x", -20.0)
    s = surfels([R], [[0.1, -0.1, 3.0]], [[2.0, 2.0]], [0.9])
    c = cam()
    out = render(normal_inputs(s, c), c, backend="cpu", sh_degree=0, background=torch.zeros(3))
    n = facing_normals(s.means, s.quats, c)[0]
    drawn = out.alpha > 0.2
    assert int(drawn.sum()) > 0.9 * W * H
    n_r = 2 * out.rgb - out.alpha[..., None]
    assert torch.allclose((n_r / out.alpha[..., None].clamp_min(1e-6))[drawn], n.expand(int(drawn.sum()), 3),
                          atol=1e-5)
    n_d = depth_normals(out.depth, out.alpha, c)
    inner = drawn.clone()
    inner[[0, -1]] = False
    inner[:, [0, -1]] = False
    assert torch.allclose(n_d[inner], n.expand(int(inner.sum()), 3), atol=2e-3)
    # colour render and normal render blend with the same weights
    base = render(s, c, backend="cpu", sh_degree=0, background=torch.zeros(3))
    assert torch.equal(base.alpha, out.alpha) and torch.equal(base.depth, out.depth)


def test_two_crossing_surfels_disagree_and_the_gradient_matches_the_reference_renderer():
    """Two overlapping surfels at different tilts: the term is above its one-plane value, and its gradient from the
    compiled CPU backend matches the reference renderer's autograd one (float64 gradcheck on the reference)."""
    def inputs(dtype):
        s = surfels([rot("y", 35.0, dtype), rot("x", -25.0, dtype)], [[0.0, 0.0, 3.0], [0.2, 0.1, 3.2]],
                    [[0.6, 0.5], [0.5, 0.7]], [0.7, 0.6], dtype)
        for t in (s.means, s.quats, s.scales, s.opacities):
            t.requires_grad_(True)
        return s

    s = inputs(torch.float32)
    loss = normal_loss(s, cam(), "cpu")
    loss.backward()
    ref = inputs(torch.float32)
    normal_loss(ref, cam(), "reference").backward()
    for a, b in ((s.means, ref.means), (s.quats, ref.quats), (s.scales, ref.scales), (s.opacities, ref.opacities)):
        assert a.grad.abs().max() > 0
        assert torch.allclose(a.grad, b.grad, rtol=2e-3, atol=2e-5), (a.grad, b.grad)

    # float64 gradcheck through the reference renderer, the alpha weight held at its value (it is detached in the
    # term: a constant of the step)
    s64 = inputs(torch.float64)
    cam64 = cam(torch.float64)
    zero = torch.zeros(3, dtype=torch.float64)

    def f(means, quats):
        si = SurfelInputs(means=means, quats=quats, scales=s64.scales, opacities=s64.opacities, sh=s64.sh,
                          texel_size=s64.texel_size, textures=s64.textures, tex_res=s64.tex_res,
                          tex_offset=s64.tex_offset)
        return consistency(render(normal_inputs(si, cam64), cam64, backend="reference", sh_degree=0, background=zero),
                           cam64, weight)

    with torch.no_grad():
        weight = render(s64, cam64, backend="reference", sh_degree=0, background=zero).alpha
    assert torch.autograd.gradcheck(f, (s64.means, s64.quats), eps=1e-6, atol=1e-5)
    # above its floor: N_r . N_d = alpha wherever N_d is defined would mean one plane (normals and depth agree)
    with torch.no_grad():
        out = render(normal_inputs(s, cam()), cam(), backend="cpu", sh_degree=0, background=torch.zeros(3))
        defined = depth_normals(out.depth, out.alpha, cam()).norm(dim=-1) > 0
        floor = float((1 - out.alpha ** 2 * defined).mean())
    assert float(loss.detach()) > floor + 0.005, (float(loss.detach()), floor)


def _train(scene_dir: str, run: str, sets: list[str]):
    """80 `fast` iterations of the small demo scene, seed 3, one thread: the finished Trainer."""
    from ctgs.runs import training_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    cfg = resolve_config(scene_dir, run, None, 80, sets + ["threads=1", "seed=3"], None, False, None, None,
                         preset="fast")
    t = Trainer(cfg, training_scene(cfg), run)
    for _ in t.run():
        pass
    return t


@pytest.fixture(scope="module")
def demo_and_plain_run(tmp_path_factory):
    """(the demo scene, the run without either term): the baseline both short-run tests compare against, trained once."""
    from ctgs.scene.demo import make_demo_scene

    root = tmp_path_factory.mktemp("geometry_terms")
    scene_dir = make_demo_scene(str(root / "demo"), num_views=8, width=64, height=48, points=300)
    return scene_dir, _train(scene_dir, str(root / "off"), [])


def test_lambda_normal_trains_and_brings_normals_to_the_depth(tmp_path, demo_and_plain_run):
    """A short run with the term trains (finite, logged) and ends with rendered normals closer to the depth's than
    the same run without it."""
    import numpy as np

    scene_dir, off = demo_and_plain_run
    on = _train(scene_dir, str(tmp_path / "on"), ["lambda_normal=0.5", "normal_from=0"])

    def term(t) -> float:
        with torch.no_grad():
            inp = t.model.render_inputs()
            return float(np.mean([float(normal_loss(inp, v.camera, "cpu")) for v in t.train_views]))

    assert math.isfinite(term(on)) and term(on) < term(off)


def test_distortion_is_the_weights_spread_along_the_ray():
    """Two fronto-parallel surfels on the optical axis at depths 2 and 3: on the axis the map is
    w1 w2 (z1 - z2)^2 / zbar^2 with w1 = o1, w2 = o2 (1 - o1); one surfel alone gives 0."""
    c = Camera(fx=20.0, fy=20.0, cx=7.5, cy=7.5, width=16, height=16, viewmat=torch.eye(4, dtype=torch.float64))
    two = surfels([torch.eye(3), torch.eye(3)], [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], [[1.0, 1.0], [1.0, 1.0]],
                  [0.6, 0.5], torch.float64)
    out = render(two, c, backend="cpu")
    w1, w2 = 0.6, 0.5 * 0.4
    zbar = (2 * w1 + 3 * w2) / (w1 + w2)
    assert float(distortion_map(out)[7, 7]) == pytest.approx(w1 * w2 / zbar**2, rel=1e-9)
    one = surfels([torch.eye(3)], [[0.0, 0.0, 2.0]], [[1.0, 1.0]], [0.6], torch.float64)
    assert float(distortion_map(render(one, c, backend="cpu")).abs().max()) < 1e-12


def test_distortion_gradient_matches_the_reference_renderer():
    """The term through the compiled CPU backend's depth2 and through the reference renderer's autograd agree, and a
    float64 gradcheck passes on the reference."""
    def inputs(dtype):
        s = surfels([rot("y", 35.0, dtype), rot("x", -25.0, dtype)], [[0.0, 0.0, 3.0], [0.2, 0.1, 3.6]],
                    [[0.6, 0.5], [0.5, 0.7]], [0.7, 0.6], dtype)
        for t in (s.means, s.quats, s.scales, s.opacities):
            t.requires_grad_(True)
        return s

    grads = {}
    for backend in ("cpu", "reference"):
        s = inputs(torch.float64)
        geometry_terms(s, cam(torch.float64), backend, normal=False)["dist"].backward()
        grads[backend] = [t.grad for t in (s.means, s.quats, s.scales, s.opacities)]
    for a, b in zip(grads["cpu"], grads["reference"]):
        assert b.abs().max() > 0
        assert torch.allclose(a, b, rtol=1e-8, atol=1e-10), (a, b)
    s64 = inputs(torch.float64)
    cam64 = cam(torch.float64)

    def f(means, opacities):
        si = SurfelInputs(means=means, quats=s64.quats, scales=s64.scales, opacities=opacities, sh=s64.sh,
                          texel_size=s64.texel_size, textures=s64.textures, tex_res=s64.tex_res,
                          tex_offset=s64.tex_offset)
        out = render(si, cam64, backend="reference")
        return (out.alpha * out.depth2 - out.depth**2).sum()  # the term without its (constant) 1 / zbar^2

    assert torch.autograd.gradcheck(f, (s64.means, s64.opacities), eps=1e-6, atol=1e-5)


def test_lambda_dist_trains_and_gathers_the_weights_on_the_ray(tmp_path, demo_and_plain_run):
    """A short run with the distortion term (logged) ends with less of it over the training views than the same run
    without."""
    import json

    import numpy as np

    scene_dir, off = demo_and_plain_run
    on = _train(scene_dir, str(tmp_path / "on"), ["lambda_dist=1.0", "dist_from=0"])

    def term(t) -> float:
        with torch.no_grad():
            inp = t.model.render_inputs()
            return float(np.mean([float(distortion(render(inp, v.camera, backend="cpu"))) for v in t.train_views]))

    assert math.isfinite(term(on)) and term(on) < 0.8 * term(off), (term(on), term(off))
    with open(tmp_path / "on" / "log.jsonl") as f:
        steps = [json.loads(line) for line in f if '"step"' in line]
    assert any("dist" in r for r in steps) and not any("normal" in r for r in steps)


def test_lambda_normal_rejects_negative_values():
    from ctgs.errors import UserError
    from ctgs.train.config import load_config

    for key in ("lambda_normal", "normal_from", "lambda_dist", "dist_from"):
        with pytest.raises(UserError, match=key):
            load_config(None, {key: -1})
