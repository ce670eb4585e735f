"""Shared fixtures of the scene tests: one tiny demo scene per session (fast: ~1 s)."""

from __future__ import annotations

import shutil

import pytest

from ctgs.scene.demo import make_demo_scene

from scene_fixtures import TINY


@pytest.fixture(scope="session")
def tiny_demo_master(tmp_path_factory) -> str:
    return make_demo_scene(str(tmp_path_factory.mktemp("demo") / "scene"), **TINY)


@pytest.fixture
def tiny_demo(tiny_demo_master, tmp_path) -> str:
    """A private copy tests may modify."""
    return shutil.copytree(tiny_demo_master, tmp_path / "scene")
