"""docs/reference/config.md from configs/default.toml: every key, its default and the comment above it.

    python docs/_hooks/config_keys.py          # rewrite the page
    python docs/_hooks/config_keys.py --check  # exit 1 if the page differs from what the TOML gives

mkdocs.yml runs it as a hook: the site build fails when the committed page has drifted from the TOML
(tests/test_docs_config_keys.py checks the same without building the site).
"""

from __future__ import annotations

import os
import sys
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEFAULT_TOML = os.path.join(ROOT, "configs", "default.toml")
PAGE = os.path.join(ROOT, "docs", "reference", "config.md")

HEADER = """# Config keys

Every key `ctgs train` reads, with its default (the paper's recipe, `configs/default.toml`) and what it does.
A preset (`--preset fast`) or an overlay (`--config 2dgs`) is a TOML file listing only what it changes;
`--set key=value` overrides one key; an unknown key is an error that names it. `ctgs train --list-keys` prints
the same list. Values in pixels, texels and iterations are at the paper's scale and are resolved per run
([Training](../guide/training.md#scene-relative-settings)).

This page is generated from `configs/default.toml` by `docs/_hooks/config_keys.py`; the docs build fails if it
is out of date.

| key | default | what it does |
| --- | --- | --- |
"""


def _cell(text: str) -> str:
    return text.replace("|", "\\|").strip()


def render(toml_path: str = DEFAULT_TOML) -> str:
    """The page's markdown: one table row per top-level key, its help the comment lines right above it."""
    with open(toml_path, "rb") as fh:
        values = tomllib.load(fh)
    rows, comment = [], []
    with open(toml_path, encoding="utf-8") as fh:
        for line in fh:
            stripped = line.strip()
            if stripped.startswith("#"):
                comment.append(stripped.lstrip("#").strip())
            elif "=" in stripped and not stripped.startswith("["):
                key = stripped.split("=", 1)[0].strip()
                if key in values:
                    default = stripped.split("=", 1)[1].strip()
                    rows.append(f"| `{key}` | `{_cell(default)}` | {_cell(' '.join(comment))} |")
                comment = []
            elif not stripped:
                comment = []
    return HEADER + "\n".join(rows) + "\n"


def main(argv: list[str]) -> int:
    text = render()
    if "--check" in argv:
        with open(PAGE, encoding="utf-8") as fh:
            current = fh.read()
        if current != text:
            print(f"{PAGE} is out of date with {DEFAULT_TOML}: run python docs/_hooks/config_keys.py")
            return 1
        return 0
    with open(PAGE, "w", encoding="utf-8") as fh:
        fh.write(text)
    print(f"wrote {PAGE}")
    return 0


def on_pre_build(config, **kwargs):  # mkdocs hook
    if main(["--check"]):
        raise SystemExit(1)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
