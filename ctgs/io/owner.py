"""Output folders ctgs owns: a stage writes only into a folder it made or marked as its own, never into one of the
user's, and deletes nothing it did not write.

Every output folder a stage makes holds MARKER (`.ctgs-output`), a small JSON file: {"kind": what the folder is
("run", "model", "eval", ...), "entries": the names the stage wrote there}. A folder a stage writes into over time (a
run folder) is marked without entries: every name in it is the stage's to write. Before a stage writes into or
replaces OUT, `check_ours` passes when OUT is absent or empty, or holds the marker of that kind and nothing besides
what the marker lists and what the kind adds later (`also`: a model folder's web/, a scene's images_N); otherwise
one line names what is not ctgs's and nothing is changed. Folders written before markers existed are recognised by a
test of each stage (`legacy`) that accepts only the names that stage writes.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from ctgs.errors import UserError
from ctgs.io import atomic

MARKER = ".ctgs-output"
# the atomic helpers' hidden temporaries (ctgs.io.atomic): a killed writer's, ours to sweep
_TEMPORARY = re.compile(r"^\..+" + re.escape(atomic.TMP_TAG))
NamesTest = Callable[[list[str]], bool]


def read_marker(folder: str) -> dict | None:
    """The marker of `folder` ({"kind", "entries"?}), None when there is none or it cannot be read."""
    try:
        with open(os.path.join(folder, MARKER), encoding="utf-8") as fh:
            marker = json.load(fh)
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) and isinstance(marker.get("kind"), str) else None


def kind_of(folder: str) -> str | None:
    marker = read_marker(folder)
    return None if marker is None else marker["kind"]


def mark(folder: str, kind: str, entries: list[str] | None = None) -> None:
    """Write `folder`'s marker: a folder of `kind` holding `entries` (None: written into over time, every name ours)."""
    marker: dict = {"kind": kind}
    if entries is not None:
        marker["entries"] = sorted(e for e in entries if e != MARKER)
    atomic.write_json(os.path.join(folder, MARKER), marker, indent=None)


def mark_written(folder: str, kind: str) -> None:
    """Mark `folder` as holding what is in it now (a folder just built in full)."""
    mark(folder, kind, os.listdir(folder))


def foreign_names(folder: str, kind: str, *, legacy: NamesTest | None = None,
                  also: Callable[[str], bool] | None = None) -> list[str]:
    """The names in the existing folder `folder` that are not ctgs's to replace as a folder of `kind` (sorted)."""
    names = sorted(n for n in os.listdir(folder) if n != MARKER and not _TEMPORARY.match(n))
    marker = read_marker(folder)
    if marker is not None and marker["kind"] == kind:
        entries = marker.get("entries")
        if entries is None:
            return []
        return [n for n in names if n not in entries and not (also and also(n))]
    if marker is None and legacy is not None and legacy(names):
        return []
    return names


def _listed(names: list[str]) -> str:
    shown = ", ".join(names[:3])
    return shown + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def check_ours(out_dir: str, kind: str, what: str, *, legacy: NamesTest | None = None,
               also: Callable[[str], bool] | None = None) -> None:
    """UserError (one line, nothing changed) unless `out_dir` is absent, an empty folder, or a folder of `kind`
    holding nothing but ctgs's own files (see the module docstring). `what`: the folder a stage may replace
    ("an earlier `ctgs render` folder")."""
    if not os.path.lexists(out_dir):
        return
    if os.path.islink(out_dir) or not os.path.isdir(out_dir):
        raise UserError(f"{out_dir}: exists and is not a folder; choose another output (-o)")
    foreign = foreign_names(out_dir, kind, legacy=legacy, also=also)
    if foreign:
        marker = read_marker(out_dir)
        whose = (f"a ctgs {marker['kind']} folder, not {what}" if marker is not None and marker["kind"] != kind
                 else f"not {what}: it holds files ctgs did not write ({_listed(foreign)})")
        raise UserError(f"{out_dir}: {whose}; nothing was changed: choose another output folder (-o), or empty it")


@contextmanager
def owned_dir(out_dir: str, kind: str) -> Iterator[str]:
    """atomic.atomic_dir that marks the folder, once built, as a `kind` folder holding what was written in it."""
    with atomic.atomic_dir(out_dir) as tmp:
        yield tmp
        mark_written(tmp, kind)


def names_within(allowed: set[str] | frozenset[str], required: str | None = None) -> NamesTest:
    """A `legacy` test: every name in `allowed` (and `required` among them)."""
    return lambda names: set(names) <= allowed and (required is None or required in names)
