"""npm packages the I/O tests check our files with (the Khronos glTF validator, Niantic's spz reader), installed
once into the per-user cache (<CTGS_CACHE_DIR or ~/.cache/ctgs>/node/<spec>/); a test skips only where node or
npm is missing."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile

import pytest

from ctgs.resources import cache_dir


def npm_package(spec: str, name: str, why: str, ignore_scripts: bool = False) -> tuple[str, str]:
    """(node, path of package `name` installed from `spec`, e.g. "gltf-validator@2.0.0-dev.3.10"). ignore_scripts:
    install without running the packages' install scripts (what the tests use needs none)."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if not node or not npm:
        pytest.skip(f"node or npm not found: {why} (npm package {spec}) cannot run")
    prefix = cache_dir() / "node" / spec.replace("@", "-").replace("/", "-")
    package = prefix / "node_modules" / name
    if not (package / "package.json").is_file():
        prefix.parent.mkdir(parents=True, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=".install-", dir=prefix.parent)  # complete installs only, then renamed
        subprocess.run([npm, "install", "--no-audit", "--no-fund", *(["--ignore-scripts"] if ignore_scripts else []),
                        "--prefix", tmp, spec], check=True, capture_output=True, timeout=600)
        if (package / "package.json").is_file():  # another process finished first
            shutil.rmtree(tmp)
        else:
            shutil.rmtree(prefix, ignore_errors=True)
            os.replace(tmp, prefix)
    return node, str(package)
