"""Atomic writes: a file or folder either appears complete under its final name or not at all.

Every writer in ctgs goes through here (reports, checkpoints, model.pt, PLY, images, model folders, the
demo scene, eval folders...). Files are written under a hidden temporary name in the destination's own
folder (same filesystem, so the final `os.replace` is atomic) and renamed; folders are built in a hidden
temporary sibling and renamed into place. On any exception the temporary is removed, so a failure never
leaves a half-written artifact behind, and a crash (kill -9) leaves at most a hidden `.NAME.tmp-*`.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from ctgs.errors import UserError

TMP_TAG = ".tmp-"  # every temporary name is ".<final name>.tmp-<random>": hidden, and says what it was for
# mkstemp/mkdtemp create private (0600/0700) entries; the results are ordinary output files and folders.
FILE_MODE = 0o644
DIR_MODE = 0o755


def _tmp_prefix(path: str) -> str:
    return "." + os.path.basename(os.path.normpath(path)) + TMP_TAG


@contextmanager
def atomic_path(path: str, *, fsync: bool = False) -> Iterator[str]:
    """Yield a temporary file name next to `path` (same extension: writers that pick the format from it
    keep working); on success it is renamed to `path`, on any exception removed.

    fsync: flush the file to disk before the rename (checkpoints: survive a power cut, not just a kill).
    """
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=_tmp_prefix(path), suffix=os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    try:
        yield tmp
        if fsync:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def write_bytes(path: str, data: bytes, *, fsync: bool = False) -> None:
    with atomic_path(path, fsync=fsync) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def write_text(path: str, text: str, *, fsync: bool = False) -> None:
    # newline="": the text is written exactly as given (CSV writers already put their own line ends).
    with atomic_path(path, fsync=fsync) as tmp, open(tmp, "w", newline="") as fh:
        fh.write(text)


def write_json(path: str, obj, *, indent: int | None = 2) -> None:
    write_text(path, json.dumps(obj, indent=indent) + "\n")


@contextmanager
def signals_deferred(signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM until the block ends, then deliver them to the handlers that were in place.

    For writers whose own cleanup breaks when an exception lands mid-write: torch.save's zip writer, interrupted by
    the CLI's SIGTERM handler, failed again in its __exit__ ("unexpected pos 64 vs 0") and that RuntimeError replaced
    the stop, so `ctgs train` ended with a traceback and exit 1 instead of 143 (seen in CI). The block completes
    (the file is renamed into place), then the process stops as it would have. Outside the main thread (where
    handlers cannot be changed) and for handlers installed outside Python, nothing is deferred.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = {s: signal.getsignal(s) for s in signums}
    previous = {s: h for s, h in previous.items() if h is not None}
    for s in previous:
        signal.signal(s, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(caught):
            signal.raise_signal(s)


def torch_save(obj, path: str, *, fsync: bool = True) -> None:
    """torch.save to `path` atomically (fsync by default: checkpoints and model.pt are what a run is for).

    Ctrl-C and SIGTERM wait until the file is in place (signals_deferred): a checkpoint takes a fraction of a second,
    and a stop that lands inside torch.save otherwise ends in torch's own error instead of a clean stop."""
    import torch

    with signals_deferred(), atomic_path(path, fsync=fsync) as tmp, open(tmp, "wb") as fh:
        torch.save(obj, fh)


def ensure_replaceable(out_dir: str, looks_ours: Callable[[list[str]], bool], what: str) -> None:
    """UserError unless `out_dir` is absent, an empty folder, or a folder whose entry names `looks_ours`
    accepts. Replacing a folder deletes it: only ever an earlier output of the same kind (never, say, the
    run folder passed as -o by mistake)."""
    if not os.path.lexists(out_dir):
        return
    if os.path.isdir(out_dir) and not os.path.islink(out_dir):
        names = os.listdir(out_dir)
        if not names or looks_ours(names):
            return
    raise UserError(f"{out_dir}: exists and is not {what}; choose another output folder (-o) or remove it")


@contextmanager
def atomic_dir(out_dir: str, *, replace: bool = True) -> Iterator[str]:
    """Yield an empty temporary folder next to `out_dir`; fill it, and on success it becomes `out_dir`.

    replace: an existing `out_dir` is swapped out and deleted (callers decide beforehand whether that
    folder may be deleted); otherwise an existing `out_dir` makes the rename fail with OSError. On any
    exception the temporary folder and everything in it is removed and `out_dir` is left as it was.
    """
    out_dir = os.path.normpath(out_dir)
    parent = os.path.dirname(os.path.abspath(out_dir))
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=_tmp_prefix(out_dir), dir=parent)
    os.chmod(tmp, DIR_MODE)
    try:
        yield tmp
        _move_into_place(tmp, out_dir, replace)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _move_into_place(tmp: str, out_dir: str, replace: bool) -> None:
    if not os.path.lexists(out_dir):
        os.rename(tmp, out_dir)
        return
    if not replace or os.path.islink(out_dir) or not os.path.isdir(out_dir):
        raise FileExistsError(f"{out_dir}: already exists; choose another output folder")
    # Two renames: the old folder stays whole until the new one is complete, and is deleted last.
    old = tempfile.mkdtemp(prefix=_tmp_prefix(out_dir) + "old-", dir=os.path.dirname(os.path.abspath(out_dir)))
    os.rmdir(old)
    os.rename(out_dir, old)
    try:
        os.rename(tmp, out_dir)
    except BaseException:
        os.rename(old, out_dir)
        raise
    shutil.rmtree(old, ignore_errors=True)
