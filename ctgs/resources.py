"""Where ctgs finds the files it ships (kernel sources, configs, dataset manifests) and where it caches.

The repository keeps them at its top level (kernels/, configs/, data_manifests/); a wheel carries the
same folders inside the package as ctgs/_kernels, ctgs/_configs, ctgs/_manifests (pyproject.toml maps
them with setuptools' package-dir). Every caller asks this module, so both layouts (an installed wheel,
an editable install or a plain checkout) resolve to the same files; nothing else hard-codes a path.

The per-user cache (compiled extensions, converted LPIPS weights) is $CTGS_CACHE_DIR, else ~/.cache/ctgs
(`cache_dir`, the one place that says so; the Makefile follows the same rule): never inside the package, whose
folder may be read-only (site-packages of a system Python) or shared between users.
"""

from __future__ import annotations

import os
from pathlib import Path

from ctgs.errors import UserError

PACKAGE_DIR = Path(__file__).resolve().parent
# (folder inside an installed package, folder in a source checkout next to the package)
_SHIPPED = {"kernels": ("_kernels", "kernels"), "configs": ("_configs", "configs"),
            "manifests": ("_manifests", "data_manifests")}
CACHE_ENV = "CTGS_CACHE_DIR"
CONFIG_SUFFIX = ".toml"


def _shipped(kind: str) -> Path:
    """The shipped folder `kind`: inside the package (wheel) if there, else the checkout's top level."""
    inside, top = _SHIPPED[kind]
    for candidate in (PACKAGE_DIR / inside, PACKAGE_DIR.parent / top):
        if candidate.is_dir():
            return candidate
    raise UserError(f"{PACKAGE_DIR}: the package's {top}/ files are missing (looked in {PACKAGE_DIR / inside} "
                    f"and {PACKAGE_DIR.parent / top}); reinstall ctgs (pip install ctgs, or pip install -e . "
                    "in a checkout)")


def kernels_dir() -> Path:
    """Kernel sources: bindings*.cpp, cpu/, cuda/, include/ctgs/."""
    return _shipped("kernels")


def configs_dir() -> Path:
    """Training configs: default.toml and the named experiments/baselines."""
    return _shipped("configs")


def manifests_dir() -> Path:
    """Dataset manifests (<dataset>.toml) that `ctgs fetch` and the Makefile read."""
    return _shipped("manifests")


def config_names() -> list[str]:
    """Names of the shipped configs (file stems), sorted."""
    return sorted(p.stem for p in configs_dir().glob("*" + CONFIG_SUFFIX))


def resolve_config(name_or_path: str) -> str:
    """A config argument -> a file path. An existing file stays as given; a bare name (`default`, `2dgs`,
    `demo`) is the shipped configs/<name>.toml; anything else is a UserError listing the shipped names."""
    if os.path.isfile(name_or_path):
        return name_or_path
    is_name = os.sep not in name_or_path and "/" not in name_or_path
    stem = name_or_path[: -len(CONFIG_SUFFIX)] if name_or_path.endswith(CONFIG_SUFFIX) else name_or_path
    if is_name and (configs_dir() / (stem + CONFIG_SUFFIX)).is_file():
        return str(configs_dir() / (stem + CONFIG_SUFFIX))
    what = "no such config name" if is_name else "config file not found"
    raise UserError(f"{name_or_path}: {what}; pass an existing TOML file or one of the shipped configs: "
                    f"{', '.join(config_names())}")


def cache_dir() -> Path:
    """The per-user cache folder (not created here)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    return Path(os.path.expanduser("~")) / ".cache" / "ctgs"
