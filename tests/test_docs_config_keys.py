"""The config-keys page the docs build makes from configs/default.toml (docs/_hooks/config_keys.py) lists every key
with its default and its help."""

from __future__ import annotations

import importlib.util
import os
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _generator():
    spec = importlib.util.spec_from_file_location("config_keys", os.path.join(ROOT, "docs", "_hooks", "config_keys.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_config_key_is_on_the_page_with_its_help():
    gen = _generator()
    with open(gen.DEFAULT_TOML, "rb") as fh:
        keys = tomllib.load(fh)
    page = gen.render()
    rows = {line.split("`")[1]: line for line in page.splitlines() if line.startswith("| `")}
    assert set(rows) == set(keys), sorted(set(keys) ^ set(rows))
    assert all(not line.endswith("|  |") for line in rows.values()), [k for k, v in rows.items() if v.endswith("|  |")]


def test_the_page_is_in_the_site_nav():
    with open(os.path.join(ROOT, "mkdocs.yml"), encoding="utf-8") as fh:
        assert "reference/config.md" in fh.read()
