"""Run `ctgs ARGS` with the atomic-write helpers instrumented (tests/faults): CTGS_KILL_AT_WRITE=N makes the
process SIGKILL itself inside the N-th atomic write, after its temporary is complete and before the rename (where
a kill -9 hurts most)."""

from __future__ import annotations

import os
import signal
import sys
from contextlib import contextmanager

from ctgs.io import atomic

KILL_AT = int(os.environ.get("CTGS_KILL_AT_WRITE") or 0)
_count = 0


def _instrument(original):
    @contextmanager
    def wrapped(*args, **kwargs):
        global _count
        _count += 1
        n = _count
        with original(*args, **kwargs) as tmp:
            yield tmp
            if n == KILL_AT:
                os.kill(os.getpid(), signal.SIGKILL)

    return wrapped


atomic.atomic_path = _instrument(atomic.atomic_path)
atomic.atomic_dir = _instrument(atomic.atomic_dir)

if __name__ == "__main__":
    from ctgs.cli import main

    sys.argv[0] = "ctgs"
    main()
