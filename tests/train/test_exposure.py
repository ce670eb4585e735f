"""Per-training-image exposure compensation (ctgs.train.components.exposure, config keys
exposure_comp / lr_exposure)."""

from __future__ import annotations

import os

import pytest
import torch

from ctgs.train.components.exposure import Exposure


def test_gains_are_centred_and_only_scale_the_render():
    e = Exposure(4, "cpu", lr=0.1)
    with torch.no_grad():
        e.log_gain.copy_(torch.tensor([[0.1, 0.0, 0.3], [0.5, 0.2, 0.3], [0.3, 0.4, 0.3], [0.7, 0.2, 0.3]]))
    g = e.gains()
    assert torch.allclose(g.log().mean(0), torch.zeros(3), atol=1e-6)  # geometric mean 1 per channel
    assert torch.allclose(g[:, 2], torch.ones(4))  # a shared offset is no gain at all
    rgb = torch.rand(5, 6, 3)
    assert torch.allclose(e.apply(rgb, 1), rgb * g[1])


def test_one_gain_per_image_scales_all_three_channels_alike():
    """exposure_channels = 1: one gain per image (exposure, not white balance), centred the same way; fitted to an
    image whose channels brighten unequally it takes their common part and cannot tint the render."""
    e = Exposure(2, "cpu", lr=0.02, channels=1)
    assert e.gains().shape == (2, 1)
    render = torch.full((4, 4, 3), 0.5)
    targets = [torch.tensor([0.4, 0.4, 0.4]), torch.tensor([0.55, 0.6, 0.65])]
    for it in range(400):
        i = it % 2
        ((e.apply(render, i) - targets[i]) ** 2).mean().backward()
        e.step()
    g = e.gains().detach()
    assert torch.allclose(g.log().mean(0), torch.zeros(1), atol=1e-6)
    out = e.apply(render, 1)
    assert torch.allclose(out[..., 0], out[..., 2])  # no tint
    assert float(g[1, 0] / g[0, 0]) == pytest.approx(0.6 / 0.4, rel=0.05)


def test_the_gains_follow_a_brighter_image_and_round_trip():
    """Fitting gain x a grey render to images brighter and darker than it: the gains order as the images do, and
    their state restores exactly."""
    e = Exposure(3, "cpu", lr=0.02)
    render = torch.full((4, 4, 3), 0.5)
    targets = [0.45, 0.5, 0.6]
    for it in range(300):
        i = it % 3
        loss = (e.apply(render, i) - targets[i]).abs().mean()
        loss.backward()
        e.step()
    g = e.gains().detach()[:, 0]
    assert g[0] < g[1] < g[2]
    assert float(g[2] / g[0]) == pytest.approx(0.6 / 0.45, rel=0.05)
    f = Exposure(3, "cpu", lr=0.02)
    f.load_state_dict(e.state_dict())
    assert torch.equal(f.gains(), e.gains()) and f.t == e.t and torch.equal(f.v, e.v)


def test_exposure_comp_recovers_the_gains_a_capture_was_shot_with(tmp_path):
    """The demo scene with every other training photo darkened by 20%: a short run with exposure_comp learns gains
    that tell the darkened photos from the others, and ends with a checkpoint that holds them."""
    from ctgs.io.images import read_image, write_image
    from ctgs.runs import training_scene
    from ctgs.runs import checkpoint as ckpt
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import resolve_config
    from ctgs.train.loop.trainer import Trainer

    scene_dir = make_demo_scene(str(tmp_path / "demo"), num_views=9, width=64, height=48, points=300)
    folder = os.path.join(scene_dir, "images")
    names = sorted(os.listdir(folder))
    dark = set(names[1::2])
    for name in dark:
        path = os.path.join(folder, name)
        write_image(path, read_image(path) * 0.8)  # float [0, 1] in, 8-bit PNG out
    run = str(tmp_path / "run")
    cfg = resolve_config(scene_dir, run, None, 400, ["threads=1", "seed=1", "exposure_comp=true", "lr_exposure=0.01"],
                         None, False, None, None, preset="fast")
    t = Trainer(cfg, training_scene(cfg), run)
    for _ in t.run():
        pass
    g = t.exposure.gains().detach().mean(1)  # [V] mean over channels
    is_dark = torch.tensor([v.name in dark for v in t.train_views])
    assert is_dark.any() and (~is_dark).any()
    assert float(g[is_dark].max()) < float(g[~is_dark].min())  # every darkened photo below every other
    assert float(g[~is_dark].mean() / g[is_dark].mean()) == pytest.approx(1 / 0.8, rel=0.08)
    state = ckpt.load_checkpoint(run)
    assert torch.equal(state["exposure"]["log_gain"], t.exposure.log_gain.detach().cpu())


def test_E_with_the_views_gains_holds_what_the_model_does_not_explain():
    """compute_E with gains (exposure_in_E): a photo that is the render x 1.25 leaves E at about 0 once its gain is
    applied, and a large E without it; a view without a gain in the dict is scored as before."""
    from types import SimpleNamespace

    from ctgs.render import render
    from ctgs.train.routines.error import compute_E
    from train_helpers import BACKEND, camera, image, model

    m = model(means=[[-0.25, 0.0, 3.0], [0.3, 0.1, 3.5]], scales=[[0.2, 0.15], [0.15, 0.2]], opacities=[0.9, 0.8],
              tex_res=[[4, 4], [4, 4]])
    with torch.no_grad():
        m.sh[:, 0] = -0.8  # dark enough that x 1.25 stays below 1
    cam = camera()
    photo = (image(m, cam) * 1.25).detach()
    view = SimpleNamespace(name="a.jpg", camera=cam, image_t=photo)

    def render_fn(inputs, c, error_image=None):
        return render(inputs, c, backend=BACKEND, sh_degree=0, error_image=error_image)

    plain = compute_E(m, [view], render_fn)
    matched = compute_E(m, [view], render_fn, gains={"a.jpg": torch.full((3,), 1.25)})
    other = compute_E(m, [view], render_fn, gains={"b.jpg": torch.full((3,), 1.25)})
    assert float(plain.max()) > 1e-4
    assert float(matched.max()) < 1e-3 * float(plain.max())
    assert torch.equal(other, plain)


def test_the_check_freezes_gains_of_one_exposure_and_keeps_real_ones():
    """exposure_check: gains all within exposure_min_gain of 1 are frozen at 1 (and stay there through steps and a
    checkpoint); a capture whose photos differ keeps its gains."""
    same = Exposure(3, "cpu", lr=0.02)
    with torch.no_grad():
        same.log_gain.copy_(torch.tensor([[0.01, 0.0, -0.01], [0.0, 0.02, 0.0], [-0.01, -0.02, 0.01]]))
    seen = same.check(0.03)
    assert seen["frozen"] and 0 < seen["max_gain_deviation"] < 0.03
    assert torch.equal(same.gains(), torch.ones(3, 3))
    (same.apply(torch.full((2, 2, 3), 0.5), 0) - 0.9).abs().mean().backward()
    same.step()
    assert torch.equal(same.gains(), torch.ones(3, 3))
    again = Exposure(3, "cpu", lr=0.02)
    again.load_state_dict(same.state_dict())
    assert again.frozen and again.checked
    differ = Exposure(3, "cpu", lr=0.02)
    with torch.no_grad():
        differ.log_gain.copy_(torch.tensor([[0.15, 0.15, 0.15], [0.0, 0.0, 0.0], [-0.1, -0.1, -0.1]]))
    before = differ.gains().clone()
    seen = differ.check(0.03)
    assert not seen["frozen"] and seen["max_gain_deviation"] > 0.1 and torch.equal(differ.gains(), before)
