"""ctgs.resources: the shipped kernels, configs and manifests are found in a checkout and in a wheel's
layout, config names resolve, and every shipped file matches a package-data glob (so it is in the wheel)."""

from __future__ import annotations

import fnmatch
import os
import runpy
import tomllib
from pathlib import Path

import pytest

import ctgs.resources as resources
from ctgs.errors import UserError

ROOT = Path(__file__).resolve().parents[2]


def test_checkout_layout_finds_the_top_level_folders():
    assert (resources.kernels_dir() / "bindings.cpp").is_file()
    assert (resources.kernels_dir() / "include" / "ctgs" / "constants.h").is_file()
    assert (resources.configs_dir() / "default.toml").is_file()
    assert sorted(p.name for p in resources.manifests_dir().glob("*.toml"))


def test_installed_layout_is_preferred(monkeypatch, tmp_path):
    """In a wheel the folders sit inside the package as _kernels, _configs, _manifests."""
    pkg = tmp_path / "site-packages" / "ctgs"
    for inside in ("_kernels", "_configs", "_manifests"):
        (pkg / inside).mkdir(parents=True)
    (pkg / "_configs" / "only_here.toml").write_text("iterations = 5\n")
    monkeypatch.setattr(resources, "PACKAGE_DIR", pkg)
    assert resources.kernels_dir() == pkg / "_kernels"
    assert resources.manifests_dir() == pkg / "_manifests"
    assert resources.config_names() == ["only_here"]
    assert resources.resolve_config("only_here") == str(pkg / "_configs" / "only_here.toml")


def test_missing_folders_name_both_places(monkeypatch, tmp_path):
    monkeypatch.setattr(resources, "PACKAGE_DIR", tmp_path / "ctgs")
    with pytest.raises(UserError, match="_kernels.*kernels.*reinstall"):
        resources.kernels_dir()


def test_resolve_config_names_and_paths(tmp_path, monkeypatch):
    assert resources.resolve_config("default") == str(resources.configs_dir() / "default.toml")
    assert resources.resolve_config("2dgs.toml") == str(resources.configs_dir() / "2dgs.toml")
    mine = tmp_path / "default"  # an existing file wins over the shipped name
    mine.write_text("iterations = 1\n")
    monkeypatch.chdir(tmp_path)
    assert resources.resolve_config("default") == "default"
    assert resources.resolve_config(str(mine)) == str(mine)
    with pytest.raises(UserError, match=r"no-such-config: no such config name; .*default, fast"):
        resources.resolve_config("no-such-config")
    with pytest.raises(UserError, match=r"configs/nope.toml: config file not found; .*2dgs, .*balanced, default"):
        resources.resolve_config("configs/nope.toml")


def test_train_accepts_a_config_name(tmp_path):
    from ctgs.stages.train import resolve_config

    cfg = resolve_config(str(tmp_path), str(tmp_path / "run"), "higher_tau_ds", None, (), None, False, None, None,
                         preset="preview")
    assert cfg.tau_ds == 0.04 and cfg.iterations == 1000  # configs/higher_tau_ds.toml over preview (fast as base)
    with pytest.raises(UserError, match="no such config name"):
        resolve_config(str(tmp_path), str(tmp_path / "run"), "higher_tau_dss", None, (), None, False, None, None)


def test_cache_dir_rule(monkeypatch, tmp_path):
    monkeypatch.setenv("CTGS_CACHE_DIR", str(tmp_path / "c"))
    assert resources.cache_dir() == tmp_path / "c"
    monkeypatch.delenv("CTGS_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert resources.cache_dir() == tmp_path / ".cache" / "ctgs"


def _package_data_globs() -> list[str]:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["setuptools"]["package-data"]["*"]


@pytest.mark.parametrize("folder", ["kernels", "configs", "data_manifests"])
def test_every_shipped_file_matches_a_package_data_glob(folder):
    """A file type nobody listed (say a new `.inl` header) would silently be missing from the wheel."""
    globs = _package_data_globs() + ["*.py"]  # modules ship as code
    skipped = ("__pycache__",)
    left_out = []
    for dirpath, dirnames, filenames in os.walk(ROOT / folder):
        dirnames[:] = [d for d in dirnames if d not in skipped]
        for name in filenames:
            if name.endswith((".pyc", ".so", ".o")):
                continue  # build products, never shipped
            if not any(fnmatch.fnmatch(name, g) for g in globs):
                left_out.append(os.path.join(dirpath, name))
    assert not left_out, f"not matched by [tool.setuptools.package-data] in pyproject.toml: {left_out}"


def test_setup_py_maps_every_folder_and_package(monkeypatch):
    """setup.py's discovery: every ctgs subpackage and every folder below the shipped ones is a package."""
    from setuptools import find_namespace_packages

    monkeypatch.chdir(ROOT)  # setuptools runs setup.py from the project root
    setup_py = runpy.run_path(str(ROOT / "setup.py"), run_name="setup_py_under_test")
    packages = set(setup_py["packages"]())
    for sub in find_namespace_packages(where=str(ROOT), include=["ctgs.*"], exclude=["*__pycache__"]):
        assert sub in packages, sub
    for dirpath, dirnames, _ in os.walk(ROOT / "kernels"):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        rel = Path(dirpath).relative_to(ROOT / "kernels")
        assert ".".join(("ctgs._kernels",) + rel.parts) in packages, rel
    assert setup_py["SHIPPED"] == {"ctgs._kernels": "kernels", "ctgs._configs": "configs",
                                   "ctgs._manifests": "data_manifests"}
