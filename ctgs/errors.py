"""Errors a user can cause. The CLI prints them as one line and exits non-zero, without a traceback."""

import errno
import os


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


# Exit status of a fault of the machine (a full disk, a read-only or unreadable folder, a device gone): sysexits'
# EX_IOERR, distinct from a UserError's 2 (bad input).
OS_ERROR_EXIT = 74

# errno name -> (what happened, what to do). The fix names the path the error carries.
_FIXES = {
    "ENOSPC": ("no space left on the device", "free space there or write the output elsewhere (-o)"),
    "EDQUOT": ("disk quota exceeded", "free space within your quota or write the output elsewhere (-o)"),
    "EFBIG": ("file too large for this filesystem", "write the output to another filesystem (-o)"),
    "EROFS": ("read-only filesystem", "write the output to a writable folder (-o)"),
    "EACCES": ("permission denied", "check its permissions and its folder's (ls -l); for an output, choose a "
               "folder you may write to (-o)"),
    "EPERM": ("operation not permitted", "check its permissions and its folder's (ls -l); for an output, choose a "
              "folder you may write to (-o)"),
    "EIO": ("input/output error (a failing disk or a lost network mount)", "check the device (dmesg) and run again"),
    "ENODEV": ("no such device (a disk or mount went away)", "remount it and run again"),
    "ENXIO": ("no such device or address (a disk or mount went away)", "remount it and run again"),
    "ESTALE": ("stale network file handle", "remount the network share and run again"),
    "ENOTCONN": ("transport endpoint is not connected (a network or FUSE mount went away)",
                 "remount it and run again"),
    "EMFILE": ("too many open files", "raise the limit (ulimit -n) and run again"),
    "ENFILE": ("too many open files on the system", "close other programs or raise the limit and run again"),
    "EEXIST": ("already exists", "choose another output (-o); ctgs does not write over it"),
    "ENOENT": ("no such file or folder", "check the path"),
    "ENOTDIR": ("a part of the path is not a folder", "check the path"),
    "EISDIR": ("is a folder, a file was expected", "check the path"),
    "ENAMETOOLONG": ("file name too long", "use a shorter output path"),
    "ELOOP": ("too many levels of symbolic links", "check the links on the path"),
}


def machine_fault(exc: OSError) -> bool:
    """Whether `exc` is the machine's (permissions, a device or mount failing), not a damaged file: a reader's
    OSError on a cut file (torch's EINVAL) is the file's, and is said as such."""
    return exc.errno in (errno.EACCES, errno.EPERM, errno.EIO, errno.ENODEV, errno.ENXIO, errno.ESTALE,
                         errno.ENOTCONN)


def describe_os_error(exc: OSError) -> str:
    """One line for an operating-system error: the path it names, what happened and the fix."""
    name = errno.errorcode.get(exc.errno or -1, "")
    what, fix = _FIXES.get(name, (None, "check the path and the device, then run again"))
    standard = os.strerror(exc.errno) if exc.errno else ""
    detail = exc.strerror or standard or str(exc)
    if what is None:
        what = detail
    elif detail != standard:  # a message of ours or a library's (what and how much): keep it
        what = f"{what} ({detail})"
    paths = [p for p in (exc.filename, exc.filename2) if p is not None]
    where = " -> ".join(os.fsdecode(p) for p in paths) if paths else "(no file named)"
    return " ".join(f"{where}: {what}; {fix}".split())
