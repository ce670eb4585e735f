"""Signals held for the length of a block: a write that must not be cut by Ctrl-C or SIGTERM finishes first.

`ctgs.io.atomic.torch_save` holds them while a checkpoint or model.pt is written; the trainer holds them for a
whole step, so that the checkpoint written on a stop holds that step.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


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
