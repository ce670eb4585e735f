"""Errors a user can cause. The CLI prints them as one line and exits non-zero, without a traceback."""


class UserError(Exception):
    """Bad input or environment: the message names the file/cause and the fix."""

    exit_code = 2
