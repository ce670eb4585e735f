"""Atomic writes: a file or folder either appears complete under its final name or not at all.

Every writer in ctgs goes through here (reports, checkpoints, model.pt, PLY, images, model folders, the
demo scene, eval folders...). Files are written under a hidden temporary name in the destination's own
folder (same filesystem, so the final `os.replace` is atomic) and renamed; folders are built in a hidden
temporary sibling and renamed into place. On any exception the temporary is removed, so a failure never
leaves a half-written artifact behind, and a crash (kill -9) leaves at most a hidden `.NAME.tmp-PID-HOST-*`,
which the next write to the same folder removes once process PID of machine HOST is gone (`sweep_temps`).

An OSError raised while writing (a full disk, a read-only folder: `fh.write` names no file) leaves here with
its `filename` set to the final path, so the CLI's one line names the file the user asked for.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager

from ctgs.errors import UserError
from ctgs.io.signals import signals_deferred

TMP_TAG = ".tmp-"  # every temporary is ".<final name>.tmp-<pid>-<host>-<random>": hidden, says what for and whose
# mkstemp/mkdtemp create private (0600/0700) entries; the results are ordinary output files and folders.
FILE_MODE = 0o644
DIR_MODE = 0o755


# Temporaries of a process that is gone (crash, kill -9) older than this are removed even when their name carries no
# process id (names from before ids were added) or the id was reused by an unrelated process since.
STALE_TEMP_S = 24 * 3600.0
# ".NAME.tmp-PID-HOST-<mkstemp's 8 characters>[.ext]" (groups: PID, HOST), or as named before ids were added
_TEMP_NAME = re.compile(r"^\..+" + re.escape(TMP_TAG) + r"(?:(\d+)-([0-9a-f]{6})-(?:old-)?)?[a-z0-9_]{8}(?:\.[^.]*)?$")


def _host_tag() -> str:
    """6 hex digits of this machine's name: a process id only says whether its writer is alive on the machine
    that wrote it (a folder on a network share is written by several)."""
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:6]


_HOST = _host_tag()


def _tmp_prefix(path: str) -> str:
    return "." + os.path.basename(os.path.normpath(path)) + TMP_TAG + f"{os.getpid()}-{_HOST}-"


def pid_alive(pid: int) -> bool:
    """Whether process `pid` of this machine is running."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: alive, another user's
        return True
    return True


def sweep_temps(folder: str) -> list[str]:
    """Remove the hidden temporaries (`.NAME.tmp-PID-HOST-*`, files or folders) that killed writers left in `folder`:
    those of this machine whose process is no longer running, and any older than STALE_TEMP_S. A live writer's are
    kept (two runs writing into one folder), and so are another machine's. Returns the names removed; never raises
    (a sweep must not fail a run)."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = _TEMP_NAME.match(entry.name)
        if m is None or (m.group(1) == str(os.getpid()) and m.group(2) == _HOST):
            continue
        try:
            dead = m.group(2) == _HOST and not pid_alive(int(m.group(1)))
            if not dead and now - entry.stat(follow_symlinks=False).st_mtime <= STALE_TEMP_S:
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.remove(entry.path)
            removed.append(entry.name)
        except OSError:
            continue
    return removed


def _named(exc: OSError, path: str, tmp: str | None = None) -> OSError:
    """`exc` naming `path`: when it names no file (`fh.write` on a full disk), or a file inside the temporary `tmp`
    (the user knows the final name, not the hidden one)."""
    if exc.errno is None:
        return exc
    name = exc.filename
    if name is None or (isinstance(name, str) and os.path.basename(name).startswith(_tmp_prefix(path))):
        name = path  # no file named, or the temporary itself (its creation failed: a read-only folder)
    elif tmp is not None and isinstance(name, str):
        if name == tmp:
            name = path
        elif name.startswith(tmp + os.sep):
            name = os.path.join(path, name[len(tmp) + 1:])
    if name == exc.filename:
        return exc
    new = type(exc)(exc.errno, exc.strerror or os.strerror(exc.errno), name)
    new.__cause__ = exc
    return new


def named(exc: OSError, path: str) -> OSError:
    """`exc` naming `path` when it names no file (for writers outside the atomic helpers: a log, a download)."""
    return _named(exc, path)


def _os_error_inside(exc: BaseException) -> OSError | None:
    """The OSError behind `exc` (a RuntimeError of torch's zip writer has the failed write as its context)."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, OSError):
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


@contextmanager
def atomic_path(path: str, *, fsync: bool = False) -> Iterator[str]:
    """Yield a temporary file name next to `path` (same extension: writers that pick the format from it
    keep working); on success it is renamed to `path`, on any exception removed.

    fsync: flush the file to disk before the rename (checkpoints: survive a power cut, not just a kill).
    """
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
        sweep_temps(folder)
        fd, tmp = tempfile.mkstemp(prefix=_tmp_prefix(path), suffix=os.path.splitext(path)[1], dir=folder)
        os.close(fd)
    except OSError as exc:
        raise _named(exc, path) from None
    try:
        yield tmp
        if fsync:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException as exc:
        _remove_quietly(tmp)
        if isinstance(exc, OSError):
            raise _named(exc, path, tmp) from None
        raise


def _remove_quietly(path: str) -> None:
    try:
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
        elif os.path.lexists(path):
            os.remove(path)
    except OSError:
        pass  # a read-only folder: nothing could be written there either


def write_bytes(path: str, data: bytes, *, fsync: bool = False) -> None:
    with atomic_path(path, fsync=fsync) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def write_text(path: str, text: str, *, fsync: bool = False) -> None:
    # newline="": the text is written exactly as given (CSV writers already put their own line ends).
    with atomic_path(path, fsync=fsync) as tmp, open(tmp, "w", newline="") as fh:
        fh.write(text)


def append_text(path: str, text: str) -> None:
    """Append to a log (not atomic: a log grows line by line); an OSError names `path` (a full disk's write
    names no file)."""
    try:
        with open(path, "a") as fh:
            fh.write(text)
    except OSError as exc:
        raise named(exc, path) from None


def write_json(path: str, obj, *, indent: int | None = 2) -> None:
    write_text(path, json.dumps(obj, indent=indent) + "\n")


def torch_save(obj, path: str, *, fsync: bool = True) -> None:
    """torch.save to `path` atomically (fsync by default: checkpoints and model.pt are what a run is for).

    Ctrl-C and SIGTERM wait until the file is in place (signals_deferred): a checkpoint takes a fraction of a second,
    and a stop that lands inside torch.save otherwise ends in torch's own error instead of a clean stop."""
    # torch only for torch_save: demo-scene, sfm and fetch write files without it
    import torch

    try:
        with signals_deferred(), atomic_path(path, fsync=fsync) as tmp, open(tmp, "wb") as fh:
            torch.save(obj, fh)
    except RuntimeError as exc:
        # torch's zip writer reports a failed write (a full disk) as "enforce fail ... unexpected pos": the
        # OSError it hit is its context; that one says what happened
        inner = _os_error_inside(exc)
        if inner is None:
            raise
        raise _named(inner, path) from None


@contextmanager
def atomic_dir(out_dir: str, *, replace: bool = True) -> Iterator[str]:
    """Yield an empty temporary folder next to `out_dir`; fill it, and on success it becomes `out_dir`.

    replace: an existing `out_dir` is swapped out and deleted (callers decide beforehand whether that
    folder may be deleted: ctgs.io.owner); otherwise an existing `out_dir` is refused with a FileExistsError naming
    it. On any exception the temporary folder and everything in it is removed and `out_dir` is left as it was.
    """
    out_dir = os.path.normpath(out_dir)
    parent = os.path.dirname(os.path.abspath(out_dir))
    try:
        os.makedirs(parent, exist_ok=True)
        sweep_temps(parent)
        tmp = tempfile.mkdtemp(prefix=_tmp_prefix(out_dir), dir=parent)
        os.chmod(tmp, DIR_MODE)
    except OSError as exc:
        raise _named(exc, out_dir) from None
    try:
        yield tmp
        _move_into_place(tmp, out_dir, replace)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and not isinstance(exc, FileExistsError):
            raise _named(exc, out_dir, tmp) from None
        raise


def _move_into_place(tmp: str, out_dir: str, replace: bool) -> None:
    if not os.path.lexists(out_dir):
        try:
            os.rename(tmp, out_dir)
            return
        except OSError as exc:  # a folder put there by another writer since the check: as if it had been there before
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not os.path.lexists(out_dir):
                raise
    if not replace or os.path.islink(out_dir) or not os.path.isdir(out_dir):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), out_dir)
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
