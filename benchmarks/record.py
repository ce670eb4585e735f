"""Writing a benchmark's record: benchmarks/results/<stem>.json (the figures) and .md (the table), and the table
printed."""

from __future__ import annotations

import json
import os
from typing import Callable

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def write_record(stem: str, result: dict, markdown: Callable[[dict], str]) -> str:
    """Write RESULTS/<stem>.json and .md; returns the path without suffix."""
    out = os.path.join(RESULTS, stem)
    with open(out + ".json", "w") as f:
        json.dump(result, f, indent=2)
    text = markdown(result)
    with open(out + ".md", "w") as f:
        f.write(text)
    print(text)
    return out
