"""The records the benchmark tools write: benchmarks/results/<tool>/<name>_<commit>.{json,md}, the machine, the
command and the date inside. A library for the tools, not a tool: `stem` names a record, `write_record` writes one.

Name a record by what it measured (scene, resolution, variant: `herzjesu25_384_fast_2dgs_budget20_3seeds`); the
commit the code ran at is appended, so a rerun at another commit writes a new record beside the old one."""

from __future__ import annotations

import json
import os
import re
import subprocess
from typing import Callable

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def commit() -> str:
    """The checkout's short commit (7 hex digits), or "nogit" outside a git checkout."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short=7", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=10)
        return out.stdout.strip() or "nogit"
    except (OSError, subprocess.SubprocessError):
        return "nogit"


def stem(tool: str, name: str) -> str:
    """RESULTS/<tool>/<name>_<commit> (the folder made), without a suffix. A name that already ends with a commit
    keeps it."""
    folder = os.path.join(RESULTS, tool)
    os.makedirs(folder, exist_ok=True)
    if not re.search(r"_[0-9a-f]{7}$", name):
        name = f"{name}_{commit()}"
    return os.path.join(folder, name)


def portable(text: str) -> str:
    """Paths inside this checkout made relative to it, the home folder as ~: a record names no machine's paths."""
    return text.replace(ROOT + os.sep, "").replace(os.path.expanduser("~") + os.sep, "~" + os.sep)


def write_record(path_stem: str, result: dict, markdown: Callable[[dict], str]) -> str:
    """Write <path_stem>.json and .md (path_stem from `stem`) and print the table; returns path_stem."""
    os.makedirs(os.path.dirname(path_stem), exist_ok=True)
    with open(path_stem + ".json", "w") as f:
        f.write(portable(json.dumps(result, indent=2)))
    text = portable(markdown(result))
    with open(path_stem + ".md", "w") as f:
        f.write(text)
    print(text)
    return path_stem
