"""One writer per run folder: an `fcntl` lock on RUN_DIR/.ctgs-lock.

`ctgs train` holds it exclusively for the whole run; a stage writing inside a run folder (an export or eval into
RUN_DIR/...) holds it shared, so a training and a stage writing there never run together while several readers may.
The kernel releases the lock when its process ends, however it ends (kill -9 included): a lock file left by a dead
process never blocks anyone. The exclusive holder writes its pid, host and start time into the file, which the refused
command's one line repeats.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

from ctgs.errors import UserError
from ctgs.io.atomic import pid_alive

LOCK_NAME = ".ctgs-lock"


def _holder(path: str) -> str:
    """Who holds the lock: the exclusive holder's record, unless that is of a process gone (a crashed training's,
    while readers hold the lock now)."""
    try:
        with open(path, encoding="utf-8") as fh:
            info = json.loads(fh.read() or "{}")
        pid, host = int(info["pid"]), str(info["host"])
        if host != socket.gethostname() or pid_alive(pid):
            return (f"`{info['command']}` (pid {pid} on {host}, since "
                    f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(float(info['since'])))})")
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return "another ctgs command (an export, eval or render writing there)"


class RunLock:
    """RUN_DIR's lock, held from construction until release() (exclusive: `command`, e.g. "ctgs train", is the
    folder's one writer; shared: a stage writing into it). UserError naming the holder when another process holds it.
    `run_dir` is made if missing."""

    def __init__(self, run_dir: str, command: str, *, shared: bool = False) -> None:
        os.makedirs(run_dir, exist_ok=True)
        self.shared = shared
        path = os.path.join(run_dir, LOCK_NAME)
        self.fd: int | None = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(self.fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                os.close(self.fd)  # not ours: the holder's record stays
                self.fd = None
                raise UserError(f"{run_dir}: in use by {_holder(path)}; wait for it to end, or write to another "
                                "folder (-o)") from None
            # a filesystem without locks (some network mounts): on unguarded, saying so
            print(f"ctgs: {run_dir}: this filesystem cannot lock ({exc.strerror}); make sure one command at a time "
                  "writes this run folder", file=sys.stderr)
        if not shared:
            info = {"command": command, "pid": os.getpid(), "host": socket.gethostname(), "since": time.time()}
            try:
                os.ftruncate(self.fd, 0)
                os.pwrite(self.fd, (json.dumps(info) + "\n").encode(), 0)
            except OSError:
                pass  # a full disk: the lock holds all the same, a refused command names no holder

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            if not self.shared:
                os.ftruncate(self.fd, 0)  # no holder on record once it is done
        except OSError:
            pass  # the folder was removed (a run that failed before its first checkpoint)
        os.close(self.fd)  # releases the lock
        self.fd = None


@contextmanager
def inside_run(out: str) -> Iterator[None]:
    """The shared lock of the run folder `out` is written into (its parent, when that holds a lock file: a run
    folder) for the block; nothing to hold otherwise."""
    parent = os.path.dirname(os.path.abspath(out))
    if not os.path.isfile(os.path.join(parent, LOCK_NAME)):
        yield
        return
    held = RunLock(parent, "", shared=True)
    try:
        yield
    finally:
        held.release()
