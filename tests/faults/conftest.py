"""The fault suite's starting point: one tiny finished pipeline per session (scene, run, model, compressed model),
a few seconds to make. Cases that damage a file restore it (fault_helpers.damaged) or work on copies."""

from __future__ import annotations

import os

import pytest

from fault_helpers import SCENE_OPTS, TRAIN_OPTS, cli


def _ok(args: list[str]) -> None:
    result = cli(args)
    assert result.exit_code == 0, (args, result.output, result.stderr)


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory) -> dict:
    root = str(tmp_path_factory.mktemp("pipeline"))
    p = {"root": root, "scene": f"{root}/scene", "run": f"{root}/run", "model": f"{root}/run/model",
         "small": f"{root}/run/small", "web": f"{root}/run/webmodel/web"}
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _ok(["demo-scene", p["scene"], *SCENE_OPTS])
    _ok(["train", p["scene"], "-o", p["run"], *TRAIN_OPTS])
    _ok(["export", p["run"], "-o", p["model"]])
    _ok(["compress", p["model"], "-o", p["small"]])
    _ok(["export", p["run"], "--format", "web", "-o", f"{root}/run/webmodel"])
    return p
