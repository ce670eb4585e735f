"""`ctgs sfm` on the demo scene's images: registration, reprojection error, camera centres vs truth."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.scene import load_scene
from ctgs.scene.colmap import read_colmap_model
from ctgs.scene.demo import make_demo_scene
from ctgs.scene import sfm
from ctgs.scene.sfm import markers, pipeline, steps, supervise
from measures.align import umeyama

VIEWS, WIDTH, HEIGHT = 24, 256, 192
FRAMES = 12  # the sequential matcher's video: the first half of the arc
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
        patch.setattr(steps, "undistort", interrupted)
        with pytest.raises(KeyboardInterrupt):
            sfm.run_sfm(os.path.join(demo, "images"), str(scene_dir), sfm.SfmOptions(threads=2))
    assert not scene_dir.exists() and (tmp_path / ".recon.sfm-work" / "mapping.done").is_file()

    # The re-run resumes: extraction, matching and mapping are not redone.
    calls = []
    for step in ("extract_features", "match_pairs", "map_photos"):
        monkeypatch.setattr(steps, step, lambda *a, _s=step, **k: calls.append(_s))
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
    """Video-style input (names in capture order): neighbours-only matching still registers the arc (its first
    half: FRAMES consecutive views, as many matches per frame as the whole arc gives)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in sorted(os.listdir(os.path.join(demo24, "images")))[:FRAMES]:
        os.symlink(os.path.join(demo24, "images", name), frames / name)
    scene_dir = tmp_path / "seq"
    result = CliRunner().invoke(main, ["sfm", str(frames), "-o", str(scene_dir), "--matcher", "sequential",
                                       "--threads", "2"])
    assert result.exit_code == 0, result.output
    with open(scene_dir / "sfm_report.json") as f:
        report = json.load(f)
    assert report["matcher"] == "sequential"
    assert report["registered"] >= 0.9 * FRAMES and report["mean_reprojection_error_px"] < 1.0


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
        monkeypatch.setattr(steps, "extract_features", extract)
        with pytest.raises(KeyboardInterrupt):
            sfm.run_sfm(os.path.join(demo, "images"), str(tmp_path / "recon"), sfm.SfmOptions(threads=1))
        assert seen == [signal.SIG_DFL]
        assert signal.getsignal(signal.SIGTERM) is handler
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.mark.slow
def test_retrieval_pairs_and_global_mapper_reconstruct_the_demo_scene(tmp_path, monkeypatch, demo24):
    """The large-capture path on a small one: retrieval pairing (the capture's own vocabulary) and the global
    mapper register the arc, with the same report and layout; progress reaches every step's total. The repair after
    the global mapper (a photo it keeps with too few 3D points is registered again by the incremental mapper, the
    rest held fixed) is forced on the demo photos with the fewest points."""
    monkeypatch.setattr(steps, "MIN_POINTS_PER_IMAGE", 450)
    seen: dict[str, list] = {}
    report, ran = sfm.run_sfm(os.path.join(demo24, "images"), str(tmp_path / "big"),
                              sfm.SfmOptions(matcher="retrieval", mapper="global", threads=2),
                              progress=lambda step, done, total, note: seen.setdefault(step, []).append((done, total)))
    assert ran and report.matcher == "retrieval" and report.mapper == "global"
    assert report.reregistered, "no photo below the threshold: the repair did not run"
    n = VIEWS
    assert 0 < report.pairs < n * (n - 1) // 2  # fewer pairs than exhaustive
    assert report.registered >= 0.9 * n and report.mean_reprojection_error_px < 1.0
    assert {"images", "images_2", "images_4", "images_8", "sparse", "sfm_report.json"} <= set(os.listdir(tmp_path / "big"))
    assert seen["features"][-1] == (n, n) and seen["matches"][-1] == (report.pairs, report.pairs)
    assert seen["mapping"][-1] == (report.registered, n) and seen["pyramid"][-1] == (n, n)
    for step, calls in seen.items():
        done = [d for d, _ in calls]
        assert done == sorted(done), (step, done)
    truth = _centers(read_colmap_model(os.path.join(demo24, "sparse", "0")))
    estimate = _centers(read_colmap_model(str(tmp_path / "big" / "sparse" / "0")))
    names = sorted(set(truth) & set(estimate))
    src, dst = np.stack([estimate[n] for n in names]), np.stack([truth[n] for n in names])
    s, R, t = umeyama(src, dst)
    spread = np.linalg.norm(dst - dst.mean(0), axis=1).max()
    assert np.linalg.norm(s * src @ R.T + t - dst, axis=1).max() < MAX_ALIGNED_ERROR * spread


@pytest.mark.slow
def test_the_repair_registers_a_photo_again_only_with_enough_inliers(tmp_path, monkeypatch, demo24):
    """The repair's bar for a photo taken out (REPAIR_MIN_INLIERS 2D-3D inliers) reaches the mapper: set above
    what any photo has, the photos taken out stay out and are reported unregistered."""
    monkeypatch.setattr(steps, "MIN_POINTS_PER_IMAGE", 450)
    monkeypatch.setattr(steps, "REPAIR_MIN_INLIERS", 100_000)
    report, _ = sfm.run_sfm(os.path.join(demo24, "images"), str(tmp_path / "big"),
                            sfm.SfmOptions(matcher="retrieval", mapper="global", threads=2))
    assert report.reregistered and set(report.reregistered) <= set(report.unregistered)
    assert report.registered == VIEWS - len(report.unregistered)


def test_auto_modes_follow_the_number_of_photos():
    small, large = sfm.EXHAUSTIVE_MAX_IMAGES, sfm.EXHAUSTIVE_MAX_IMAGES + 1
    assert sfm.resolve_modes(sfm.SfmOptions(), small)[::2] == ("exhaustive", sfm.DEFAULT_MAX_FEATURES)
    assert sfm.resolve_modes(sfm.SfmOptions(), large)[::2] == ("retrieval", sfm.LARGE_CAPTURE_MAX_FEATURES)
    assert sfm.resolve_modes(sfm.SfmOptions(max_features=2048), large)[2] == 2048
    assert sfm.resolve_modes(sfm.SfmOptions(), sfm.GLOBAL_MIN_IMAGES - 1)[1] == "incremental"
    assert sfm.resolve_modes(sfm.SfmOptions(), sfm.GLOBAL_MIN_IMAGES)[1] == "global"
    assert sfm.resolve_modes(sfm.SfmOptions(matcher="sequential", mapper="incremental"), 10**4)[:2] == \
        ("sequential", "incremental")


def test_pairings():
    from ctgs.scene.sfm import pairs as sfm_pairs

    assert sfm_pairs.name_order_pairs(4, 2, quadratic=False) == {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)}
    # Quadratic overlap: also 2^k ahead (k < overlap), as COLMAP's sequential pairing.
    assert (0, 8) in sfm_pairs.name_order_pairs(20, 4, quadratic=True)
    # Similarity: photos 0 and 5 look alike (a loop), the rest in name order.
    n = 6
    sim = np.full((n, n), 0.1)
    for i in range(n - 1):
        sim[i, i + 1] = sim[i + 1, i] = 0.5
    sim[0, 5] = sim[5, 0] = 0.9
    np.fill_diagonal(sim, -np.inf)
    assert sfm_pairs.retrieval_pairs(sim, 1) == {(0, 5), (0, 1), (1, 2), (2, 3), (3, 4)}
    loops = sfm_pairs.loop_pairs(sim, 1, window=2)
    assert (0, 5) in loops and all(j - i > 2 for i, j in loops)  # the loop, and nothing inside the window
    assert {i for pair in loops for i in pair} == set(range(n))  # every photo gets a loop candidate


def _finished_scene(tmp_path, photos: int, digest: str = "") -> str:
    scene = tmp_path / "scene"
    scene.mkdir()
    report = sfm.SfmReport(images_dir="/elsewhere/photos", scene_dir=str(scene), given=photos, registered=photos,
                           points=100, mean_reprojection_error_px=0.5, mean_track_length=3.0, camera_model="PINHOLE",
                           width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0, matcher="exhaustive",
                           inputs_digest=digest)
    (scene / "sfm_report.json").write_text(json.dumps(vars(report)))
    return str(scene)


@pytest.mark.parametrize("recorded", ["digest", "count only"])
def test_a_finished_scene_made_from_other_photos_is_refused(tmp_path, tiny_demo_master, recorded):
    images = os.path.join(tiny_demo_master, "images")
    photos = len(os.listdir(images))
    scene = _finished_scene(tmp_path, photos + 1 if recorded == "count only" else photos,
                            digest="0" * 64 if recorded == "digest" else "")
    before = open(os.path.join(scene, "sfm_report.json")).read()
    result = CliRunner().invoke(main, ["sfm", images, "-o", scene])
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert scene in lines[0] and "other photos" in lines[0] and "--force" in lines[0]
    assert open(os.path.join(scene, "sfm_report.json")).read() == before


def test_a_finished_scene_of_the_same_photos_is_reused(tmp_path, tiny_demo_master):
    images = os.path.join(tiny_demo_master, "images")
    names = sorted(os.listdir(images))
    copy = shutil.copytree(images, tmp_path / "copied")  # another folder, new dates: the same photos
    scene = _finished_scene(tmp_path, len(names), digest=markers.inputs_digest(images, names))
    result = CliRunner().invoke(main, ["sfm", str(copy), "-o", scene])
    assert result.exit_code == 0 and "already reconstructed" in " ".join(result.output.split())


def _sfm_lines(images, scene) -> tuple[int, list[str]]:
    result = CliRunner().invoke(main, ["sfm", images, "-o", scene, "--threads", "1"])
    return result.exit_code, [line for line in result.stderr.splitlines() if line.strip()]


def test_too_little_free_space_is_said_before_starting(tmp_path, monkeypatch, tiny_demo_master):
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**9, 10**9 - 10**5, 10**5))
    code, lines = _sfm_lines(os.path.join(tiny_demo_master, "images"), str(tmp_path / "out"))
    assert code == 2 and len(lines) == 1 and "GB free" in lines[0] and str(tmp_path) in lines[0], lines
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("fault", ["disk full", "failed check"])
def test_a_colmap_abort_is_one_line_and_the_work_is_kept(tmp_path, monkeypatch, tiny_demo_master, fault):
    """COLMAP ends its process (SIGABRT, a native stack dump) when SQLite says the disk is full or a check fails: the
    worker dies, `ctgs sfm` prints one line, exits 2, installs nothing and keeps the work folder to resume."""
    message = "SQLite error: database or disk is full" if fault == "disk full" else "Check failed: num_images > 0"
    script = (f"import os, sys; sys.stderr.write('F20261127 database.cc:42] {message}\\n*** Check failure stack "
              f"trace: ***\\n    @ 0x7f colmap::Database::Open\\n'); sys.stderr.flush(); os.abort()")
    monkeypatch.setattr(supervise, "worker_command", lambda job: [sys.executable, "-c", script])
    code, lines = _sfm_lines(os.path.join(tiny_demo_master, "images"), str(tmp_path / "out"))
    assert code == 2 and len(lines) == 1, lines
    if fault == "disk full":
        assert "disk is full" in lines[0] and "run the same command again" in lines[0]
    else:
        assert "Check failed: num_images > 0" in lines[0] and "signal 6" in lines[0] and "extract.log" in lines[0]
    assert not (tmp_path / "out").exists() and (tmp_path / ".out.sfm-work").is_dir()


def test_a_really_full_disk_is_one_line(tmp_path, monkeypatch, tiny_demo_master):
    """A 200 KiB tmpfs (root only): SQLite reports "database or disk is full" while the features database is written, which
    stops the worker; `ctgs sfm` says so in one line (the free-space check is bypassed to get there)."""
    small = tmp_path / "small"
    small.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(small)],
                                           capture_output=True).returncode != 0:
        pytest.skip("mounting a small tmpfs needs root")
    try:
        monkeypatch.setattr(pipeline, "check_free_space", lambda *args, **kwargs: None)
        code, lines = _sfm_lines(os.path.join(tiny_demo_master, "images"), str(small / "out"))
        assert code == 2 and len(lines) == 1, lines
        assert "the disk is full" in lines[0] and "SIFT extraction" in lines[0] and str(small) in lines[0]
        assert not (small / "out").exists()
    finally:
        subprocess.run(["umount", str(small)], check=True)



def test_a_damaged_record_of_the_inputs_redoes_every_step(tmp_path, capsys):
    """inputs.json cut by a crash (or overwritten): the steps it vouched for are redone, with one line saying so."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "database.db").write_bytes(b"features of other photos")
    (work / "inputs.json").write_bytes(b'{"images_dir": "/ph')
    fingerprint = {"images_dir": str(tmp_path), "files": [["a.jpg", 1, 2]], "max_image_size": 0, "max_features": 0,
                   "matcher": "exhaustive", "mapper": "incremental"}
    markers.prepare_work(str(work), fingerprint, force=False)
    assert os.listdir(work) == ["inputs.json"]
    assert json.loads((work / "inputs.json").read_text()) == fingerprint
    assert "inputs.json: unreadable (damaged)" in capsys.readouterr().err


def test_opencv_sift_through_the_pipeline_registers_the_demo_scene(tmp_path, monkeypatch, demo24):
    """The CPU extractor of captures above 50 photos (OpenCV's SIFT written into COLMAP's database), chosen here for
    the 24 demo photos: every later step reads its features and the scene registers as with COLMAP's."""
    monkeypatch.setattr(pipeline, "feature_extractor", lambda device, has_cuda, n: "opencv")
    scene_dir = tmp_path / "recon_opencv"
    sfm.run_sfm(os.path.join(demo24, "images"), str(scene_dir), sfm.SfmOptions(threads=2))
    with open(scene_dir / "sfm_report.json") as f:
        report = json.load(f)
    assert report["extractor"] == "opencv"
    assert report["registered"] >= 0.9 * VIEWS and report["points"] > 100, report
