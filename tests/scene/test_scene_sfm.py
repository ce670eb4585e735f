"""`ctgs sfm` on the demo scene's images: registration, reprojection error, camera centres vs truth."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.scene import load_scene
from ctgs.scene.colmap import read_colmap_model
from ctgs.scene.demo import make_demo_scene
from ctgs.scene import sfm
from ctgs.scene.sfm import umeyama

VIEWS, WIDTH, HEIGHT = 24, 256, 192
# Aligned centre error bound, as a fraction of the camera spread. Observed: ~0.1% (2 mm over 2.5 m).
MAX_ALIGNED_ERROR = 0.01


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R_est, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])


def _centers(model) -> dict[str, np.ndarray]:
    return {im.name: -im.viewmat[:3, :3].T @ im.viewmat[:3, 3] for im in model.images}


@pytest.fixture(scope="module")
def demo24(tmp_path_factory) -> str:
    return make_demo_scene(str(tmp_path_factory.mktemp("sfm") / "demo"), num_views=VIEWS, width=WIDTH, height=HEIGHT,
                           seed=0)


@pytest.mark.slow
def test_sfm_reconstructs_the_demo_scene(tmp_path, monkeypatch, demo24):
    demo = demo24
    scene_dir = tmp_path / "recon"

    # First run interrupted during undistortion: SCENE_DIR must not exist, the work folder must.
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(sfm, "_undistort", interrupted)
        with pytest.raises(KeyboardInterrupt):
            sfm.run_sfm(os.path.join(demo, "images"), str(scene_dir), sfm.SfmOptions(threads=2))
    assert not scene_dir.exists() and (tmp_path / ".recon.sfm-work" / "mapping.done").is_file()

    # The re-run resumes: extraction, matching and mapping are not redone.
    calls = []
    for step in ("_extract", "_match", "_map"):
        monkeypatch.setattr(sfm, step, lambda *a, _s=step, **k: calls.append(_s))
    result = CliRunner().invoke(main, ["sfm", os.path.join(demo, "images"), "-o", str(scene_dir), "--threads", "2"])
    assert result.exit_code == 0, result.output
    assert calls == []
    monkeypatch.undo()
    with open(scene_dir / "sfm_report.json") as f:
        report = json.load(f)
    assert report["given"] == VIEWS
    assert report["registered"] >= 0.9 * VIEWS
    assert report["mean_reprojection_error_px"] < 1.0
    assert report["camera_model"] == "PINHOLE" and report["points"] > 100

    # Layout: images/, sparse/0/, images_2/4/8 at 1/2, 1/4, 1/8 size; no work folder left behind.
    assert {"images", "images_2", "images_4", "images_8", "sparse", "sfm_report.json"} <= set(os.listdir(scene_dir))
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]
    scene = load_scene(str(scene_dir), images="images_4", load_images=False)
    cam = scene.train[0].camera
    assert cam.width == round(report["width"] / 4) and cam.height == round(report["height"] / 4)

    truth, estimate = _centers(read_colmap_model(os.path.join(demo, "sparse", "0"))), \
        _centers(read_colmap_model(str(scene_dir / "sparse" / "0")))
    names = sorted(set(truth) & set(estimate))
    src, dst = np.stack([estimate[n] for n in names]), np.stack([truth[n] for n in names])
    s, R, t = umeyama(src, dst)
    aligned_error = np.linalg.norm(s * src @ R.T + t - dst, axis=1)  # [C] world units
    spread = np.linalg.norm(dst - dst.mean(0), axis=1).max()
    print(f"\nsfm on demo: registered {report['registered']}/{VIEWS}, points {report['points']}, "
          f"reprojection {report['mean_reprojection_error_px']:.3f} px, aligned centre error mean "
          f"{aligned_error.mean():.4f} max {aligned_error.max():.4f} (spread {spread:.2f}), "
          f"times {report['seconds']}")
    assert aligned_error.max() < MAX_ALIGNED_ERROR * spread

    # Re-running skips everything (no --force) and says so.
    again = CliRunner().invoke(main, ["sfm", os.path.join(demo, "images"), "-o", str(scene_dir)])
    assert again.exit_code == 0 and "already reconstructed" in " ".join(again.output.split())


@pytest.mark.slow
def test_sequential_matcher_on_ordered_frames(tmp_path, demo24):
    """Video-style input (names in capture order): neighbours-only matching still registers the arc."""
    scene_dir = tmp_path / "seq"
    result = CliRunner().invoke(main, ["sfm", os.path.join(demo24, "images"), "-o", str(scene_dir),
                                       "--matcher", "sequential", "--threads", "2"])
    assert result.exit_code == 0, result.output
    with open(scene_dir / "sfm_report.json") as f:
        report = json.load(f)
    assert report["matcher"] == "sequential"
    assert report["registered"] >= 0.9 * VIEWS and report["mean_reprojection_error_px"] < 1.0


def test_sigterm_ends_sfm_at_once_during_its_steps_and_is_restored_after(tmp_path, monkeypatch):
    """Inside the pycolmap steps SIGTERM is the default action (a Python handler would wait for a long pycolmap call
    to return; the work folder makes a killed run resumable); the caller's handler is back afterwards."""
    import signal

    demo = make_demo_scene(str(tmp_path / "demo"), num_views=4, width=48, height=36, seed=0)
    seen = []

    def handler(signum, frame):  # the caller's (the CLI installs one like it)
        raise KeyboardInterrupt

    def extract(*args, **kwargs):
        seen.append(signal.getsignal(signal.SIGTERM))
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        monkeypatch.setattr(sfm, "_extract", extract)
        with pytest.raises(KeyboardInterrupt):
            sfm.run_sfm(os.path.join(demo, "images"), str(tmp_path / "recon"), sfm.SfmOptions(threads=1))
        assert seen == [signal.SIG_DFL]
        assert signal.getsignal(signal.SIGTERM) is handler
    finally:
        signal.signal(signal.SIGTERM, previous)
