"""docs/reference/config.md is what docs/_hooks/config_keys.py makes from configs/default.toml (it cannot drift)."""

from __future__ import annotations

import importlib.util
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _generator():
    spec = importlib.util.spec_from_file_location("config_keys", os.path.join(ROOT, "docs", "_hooks", "config_keys.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_config_keys_page_matches_default_toml():
    gen = _generator()
    with open(gen.PAGE, encoding="utf-8") as fh:
        page = fh.read()
    assert page == gen.render(), "docs/reference/config.md is stale: run python docs/_hooks/config_keys.py"


def test_every_config_key_is_on_the_page():
    import tomllib

    gen = _generator()
    with open(gen.DEFAULT_TOML, "rb") as fh:
        keys = tomllib.load(fh)
    page = gen.render()
    assert all(f"| `{k}` |" in page for k in keys), sorted(k for k in keys if f"| `{k}` |" not in page)
