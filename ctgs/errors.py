"""Errors a user can cause. The CLI prints them as one line and exits non-zero, without a traceback."""


class UserError(Exception):
    """Bad input or environment: the message names the file/cause and the fix."""

    exit_code = 2


class Terminated(SystemExit):
    """Raised by the CLI's SIGTERM handler (`kill`, `timeout`, a cluster's time limit): the stage unwinds as on Ctrl-C,
    so what it had half-made is removed, and the process exits with 128 + 15 (143), as if the signal had ended it.
    A SystemExit rather than a KeyboardInterrupt: with a KeyboardInterrupt raised during a module import, CPython 3.11
    ended the process by SIGINT (exit -2) even after click had handled it (seen in tests/train/test_resume_and_guard)."""

    def __init__(self, signum: int = 15) -> None:
        super().__init__(128 + signum)
