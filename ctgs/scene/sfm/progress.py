"""Progress while a worker runs: read from what it writes (the COLMAP database, its progress file, its log), never
from the worker itself."""

from __future__ import annotations

import json
import os
import sqlite3
from collections.abc import Callable

ProgressFn = Callable[[str, int, "int | None", str], None]  # (step, done, total or None, note)


def no_progress(step: str, done: int, total: int | None, note: str) -> None:
    pass


def count_rows(database: str, table: str, where: str = "") -> int | None:
    """Rows of a table of the (WAL-mode) database a worker is writing (those meeting `where`, SQL), or None while it
    cannot be read."""
    value = _query(database, f"SELECT COUNT(*) FROM {table}" + (f" WHERE {where}" if where else ""))
    return None if value is None else int(value)


def mean_rows(database: str, table: str) -> float:
    """The mean of a COLMAP blob table's `rows` column (keypoints: features per photo); 0 when unknown."""
    return float(_query(database, f"SELECT AVG(rows) FROM {table}") or 0.0)


def _query(database: str, sql: str):
    try:
        con = sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=0.05)
        try:
            return con.execute(sql).fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return None


def tail(path: str, size: int = 1 << 16) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(max(0, os.path.getsize(path) - size))
            return f.read().decode(errors="replace")
    except OSError:
        return ""


def read_json(path: str) -> dict:
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


# Phases of the global mapper, as its log's "=== Running ... ===" lines name them (the last one seen is shown while
# it runs; other lines name phases too, e.g. a warning about bundle adjustment on the GPU during positioning).
GLOBAL_PHASES = (("running rotation averaging", "rotation averaging"), ("running track establishment", "tracks"),
                 ("running global positioning", "global positioning"),
                 ("running iterative bundle adjustment", "bundle adjustment"),
                 ("running iterative retriangulation", "retriangulation"))


def global_phase(log: str) -> str:
    text = tail(log, 1 << 14).lower()
    best, where = "", -1
    for needle, label in GLOBAL_PHASES:
        at = text.rfind(needle)
        if at > where:
            best, where = label, at
    return best
