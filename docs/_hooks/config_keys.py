"""The config-keys page (reference/config.md) from configs/default.toml: every key, its default and the comment above
it. The docs build makes the page from the TOML every time (an mkdocs hook), so it cannot drift from it.

    python docs/_hooks/config_keys.py [OUT.md]   # print the page (or write it to OUT.md) to read it outside the site
"""

from __future__ import annotations

import os
import sys
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEFAULT_TOML = os.path.join(ROOT, "configs", "default.toml")
PAGE = "reference/config.md"  # where the page sits in the site

HEADER = """# Config keys

Every key `ctgs train` reads, with its default (the paper's recipe, `configs/default.toml`) and what it does.
A preset (`--preset fast`) or an overlay (`--config 2dgs`) is a TOML file listing only what it changes;
`--set key=value` overrides one key; an unknown key is an error that names it. `ctgs train --list-keys` prints
the same list. Values in pixels, texels and iterations are at the paper's scale and are resolved per run
([Training](../guide/training.md#scene-relative-settings)).

The docs build makes this page from `configs/default.toml` (`docs/_hooks/config_keys.py`).

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


def on_files(files, config, **kwargs):  # mkdocs hook: the page joins the site as a generated file
    from mkdocs.structure.files import File

    files.append(File.generated(config, PAGE, content=render()))
    return files


if __name__ == "__main__":
    text = render()
    if len(sys.argv) > 1:
        with open(sys.argv[1], "w", encoding="utf-8") as fh:
            fh.write(text)
    else:
        sys.stdout.write(text)
