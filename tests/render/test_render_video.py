"""`ctgs render RUN --path ...`: a video along a fitted camera path or a camera path file, at the size asked for;
frames that match `ctgs render`'s images of the same cameras; bad input is one line and writes nothing; a failure
part-way leaves no file."""

from __future__ import annotations

import json
import math
import os
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.io.images import read_rgb
from ctgs.runs import load_run, run_scene
from ctgs.scene.camera_path import camera_path_json, vertical_fov

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "eval"))
from fixture_run import make_run  # noqa: E402

cv2 = pytest.importorskip("cv2")

# A frame of the video against `ctgs render`'s PNG of the same camera: what the codecs keep of a 40x32 image at
# OpenCV's default bit rate (observed 31.8 dB mpeg4, 32.6 dB vp9), well above two different views (under 18.1 dB).
MIN_FRAME_PSNR = 28.0


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return make_run(str(tmp_path_factory.mktemp("video")))


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _frames(path) -> tuple[list[np.ndarray], float]:
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS)
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[:, :, ::-1].astype(np.float32) / 255.0)
    cap.release()
    return frames, fps


def _psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 99.0 if mse == 0 else -10 * math.log10(mse)


@pytest.mark.parametrize("maps", ["rgb", "texels"])
def test_a_fitted_path_is_a_video_of_the_frames_size_and_rate_asked_for(run_dir, tmp_path, maps):
    out = tmp_path / "orbit.mp4"
    res = _invoke("render", run_dir, "--path", "orbit", "--frames", 12, "--fps", 12, "--size", "48x32", "--maps", maps,
                  "-o", out, "--backend", "cpu")
    assert res.exit_code == 0, res.output
    frames, fps = _frames(out)
    assert len(frames) == 12 and frames[0].shape == (32, 48, 3) and fps == 12
    steps = [float(np.abs(a - b).mean()) for a, b in zip(frames, frames[1:])]
    assert min(steps) > 1e-3  # the camera moves every frame
    assert os.listdir(tmp_path) == ["orbit.mp4"]  # no temporary left beside it


def test_interpolate_starts_on_the_first_training_view(run_dir, tmp_path):
    scene = run_scene(load_run(run_dir), load_images=False)
    first = scene.train[0]
    w, h = first.camera.width, first.camera.height
    assert _invoke("render", run_dir, "--views", "train", "-o", tmp_path / "views", "--backend", "cpu").exit_code == 0
    res = _invoke("render", run_dir, "--path", "interpolate", "--frames", 6, "-o", tmp_path / "i.mp4",
                  "--size", f"{w}x{h}", "--backend", "cpu")
    assert res.exit_code == 0, res.output
    frames, _ = _frames(tmp_path / "i.mp4")
    ref = read_rgb(str(tmp_path / "views" / (os.path.splitext(first.name)[0] + ".png")))
    assert _psnr(frames[0], ref) >= MIN_FRAME_PSNR
    assert _psnr(frames[-1], ref) < MIN_FRAME_PSNR - 5  # and moves on to the last one


def test_a_camera_path_file_renders_the_cameras_it_names(run_dir, tmp_path):
    scene = run_scene(load_run(run_dir), load_images=False)
    view = scene.test[0]
    cam = view.camera
    path = tmp_path / "camera_path.json"
    other = scene.train[3].camera.viewmat.numpy()
    path.write_text(json.dumps(camera_path_json([cam.viewmat.numpy(), other], vertical_fov(cam), cam.width,
                                                cam.height, 10.0)))
    assert _invoke("render", run_dir, "-o", tmp_path / "views", "--backend", "cpu").exit_code == 0
    res = _invoke("render", run_dir, "--path", path, "-o", tmp_path / "p.mp4", "--backend", "cpu", "--codec", "mpeg4")
    assert res.exit_code == 0, res.output
    frames, fps = _frames(tmp_path / "p.mp4")
    assert len(frames) == 2 and fps == 10 and frames[0].shape == (cam.height, cam.width, 3)
    ref = read_rgb(str(tmp_path / "views" / (os.path.splitext(view.name)[0] + ".png")))
    assert _psnr(frames[0], ref) >= MIN_FRAME_PSNR
    assert _psnr(frames[1], ref) < MIN_FRAME_PSNR - 5
    # --size scales the file's cameras
    res = _invoke("render", run_dir, "--path", path, "-o", tmp_path / "big.mp4", "--size", "80x64", "--backend", "cpu")
    assert res.exit_code == 0 and _frames(tmp_path / "big.mp4")[0][0].shape == (64, 80, 3)


BAD = [
    (["--path", "orbit", "-o", "{tmp}/v.avi"], "v.avi: a video is written as an .mp4 file"),
    (["--path", "orbit", "-o", "{tmp}/v.mp4", "--size", "41x32"], "its sides must be even"),
    (["--path", "orbit", "-o", "{tmp}/v.mp4", "--size", "big"], "pass WIDTHxHEIGHT"),
    (["--path", "orbit", "-o", "{tmp}/v.mp4", "--views", "all"], "a video follows --path"),
    (["--path", "orbit", "-o", "{tmp}/v.mp4", "--maps", "rgb,texels"], "a video shows one of"),
    (["--path", "{tmp}/none.json", "-o", "{tmp}/v.mp4"], "camera path file not found"),
    (["--path", "{tmp}/bad.json", "-o", "{tmp}/v.mp4"], "bad.json: not a JSON camera path"),
    (["--path", "{tmp}/bad.json", "-o", "{tmp}/v.mp4", "--frames", "3"], "holds its own frames"),
    (["-o", "{tmp}/views", "--frames", "3"], "applies to a video: pass --path too"),
]


@pytest.mark.parametrize("args, says", BAD)
def test_bad_input_is_one_line_and_writes_nothing(run_dir, tmp_path, args, says):
    (tmp_path / "bad.json").write_text("{not json")
    res = _invoke("render", run_dir, *[a.format(tmp=tmp_path) for a in args])
    assert res.exit_code == 2, res.output
    assert says in res.output, res.output
    assert sorted(os.listdir(tmp_path)) == ["bad.json"]


def test_a_failure_part_way_leaves_no_video(run_dir, tmp_path, monkeypatch):
    import ctgs.io.video

    real, written = ctgs.io.video.VideoWriter.write, []

    def flaky(self, rgb):
        written.append(1)
        if len(written) > 3:
            raise OSError("disk full (injected)")
        real(self, rgb)

    monkeypatch.setattr(ctgs.io.video.VideoWriter, "write", flaky)
    res = _invoke("render", run_dir, "--path", "spiral", "--frames", 8, "-o", tmp_path / "v.mp4", "--backend", "cpu")
    assert res.exit_code != 0 and len(written) == 4
    assert os.listdir(tmp_path) == []


def test_views_render_at_any_size_with_their_maps(run_dir, tmp_path):
    res = _invoke("render", run_dir, "-o", tmp_path / "v", "--size", "80x64", "--maps", "rgb,texels",
                  "--backend", "cpu")
    assert res.exit_code == 0, res.output
    names = sorted(os.listdir(tmp_path / "v"))
    pngs = [n for n in names if n.endswith(".png")]
    assert len(pngs) == 3 * 2 and any(n.endswith(".texels.png") for n in pngs)  # 2 test views, 3 pictures each
    for name in pngs:
        assert read_rgb(str(tmp_path / "v" / name)).shape == (64, 80, 3), name
