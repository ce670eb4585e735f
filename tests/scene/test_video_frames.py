"""`ctgs sfm VIDEO`: frames picked by sharpness and spacing, written with their source times; reruns reuse them."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from ctgs.cli import main
from ctgs.errors import UserError
from ctgs.io.images import list_images, read_image
from ctgs.scene import video

FPS = 10
SHARP_EVERY = 10  # one sharp frame in each 10, at index 7, 17, ...


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> str:
    """40 frames of a panning texture, every frame blurred but one in ten (MJPG: decodable everywhere)."""
    import cv2

    path = str(tmp_path_factory.mktemp("video") / "walk.avi")
    base = (np.random.default_rng(0).random((96, 128, 3)) * 255).astype(np.uint8)
    out = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), FPS, (128, 96))
    for i in range(40):
        frame = np.roll(base, 2 * i, axis=1)
        out.write(frame if i % SHARP_EVERY == 7 else cv2.GaussianBlur(frame, (9, 9), 3))
    out.release()
    return path


def test_pick_takes_the_sharpest_of_each_span():
    scores = [0, 5, 1, 2, 9, 0, 3, 3, 1, 7]
    assert video.pick(scores, 2) == [4, 9] and video.pick(scores, 5) == [1, 3, 4, 6, 9]
    assert video.pick(scores[:3], 5) == [0, 1, 2]


def test_frames_by_sharpness_and_spacing(clip, tmp_path):
    scene = str(tmp_path / "scene")
    frames_dir, record = video.extract_frames(clip, scene, 4)
    assert [f["index"] for f in record["frames"]] == [7, 17, 27, 37]
    assert [f["time_s"] for f in record["frames"]] == pytest.approx([0.7, 1.7, 2.7, 3.7], abs=1e-3)
    assert record["frames_in_video"] == 40 and record["fps"] == FPS and record["requested"] == 4
    assert list_images(frames_dir) == [f"frame_{i:05d}.jpg" for i in range(1, 5)]
    assert read_image(os.path.join(frames_dir, "frame_00001.jpg")).shape == (96, 128, 3)
    with open(os.path.join(scene, video.RECORD)) as f:
        assert json.load(f)["frames"] == record["frames"]
    # the same video and count again: the frames written before; another count: refused without --force
    assert video.extract_frames(clip, scene, 4)[1] == record
    with pytest.raises(UserError, match="another --frames"):
        video.extract_frames(clip, scene, 5)
    assert len(video.extract_frames(clip, scene, 5, force=True)[1]["frames"]) == 5


def test_sfm_command_takes_a_video(clip, tmp_path, monkeypatch):
    """`ctgs sfm VIDEO -o SCENE` runs SfM on SCENE/input with the sequential matcher (frames in time order)."""
    from ctgs.scene import sfm

    calls = []

    def fake_run_sfm(images_dir, scene_dir, opts, **kwargs):
        calls.append((images_dir, scene_dir, opts.matcher))
        raise UserError("stop here")

    monkeypatch.setattr(sfm, "run_sfm", fake_run_sfm)
    scene = str(tmp_path / "scene")
    result = CliRunner().invoke(main, ["sfm", clip, "-o", scene, "--frames", "3"])
    assert "stop here" in result.output and result.exit_code == UserError.exit_code
    assert calls == [(os.path.join(scene, "input"), scene, "sequential")]
    assert len(list_images(os.path.join(scene, "input"))) == 3


def test_bad_video_and_too_few_frames(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video at all" * 10)
    with pytest.raises(UserError, match="broken.mp4: cannot be decoded as a video"):
        video.extract_frames(str(bad), str(tmp_path / "s"), 10)
    with pytest.raises(UserError, match="--frames 2"):
        video.extract_frames(str(bad), str(tmp_path / "s"), 2)
    assert not os.path.exists(tmp_path / "s")
