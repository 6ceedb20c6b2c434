"""How a command ends at the command line: its exit status and, when it stops early, one line saying why.

Every entry point (console scripts, ``train/`` scripts, ``python -m`` commands) runs under
:func:`run_command`. A command that returns exits 0. One that refuses its input (:data:`REFUSALS`: a bad
field, a missing file, a folder holding other work) prints ``<prog>: error: <message>`` and exits
:data:`REFUSED`. One that the file system stops part-way (:data:`FILE_SYSTEM_ERRORS`: a full disk, a
read-only folder) prints the same one line, what to do appended, and exits :data:`FILE_SYSTEM_FAILED`:
the input was fine, and the command continues (``--resume``) once the disk is fixed. A run that diverged
(``FloatingPointError``, naming the setting) prints its line and exits :data:`DIVERGED`. Anything else is
a bug and raises with its traceback, as does any of these with ``--traceback`` on the command line.
"""

from __future__ import annotations

import errno
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "DIVERGED",
    "FILE_SYSTEM_ERRORS",
    "FILE_SYSTEM_FAILED",
    "REFUSALS",
    "REFUSED",
    "TRACEBACK_FLAG",
    "refusal_line",
    "run_command",
]

#: What a command raises when it refuses its input (a bad field, a missing file, a folder holding other
#: work): at the command line one line names it, without a traceback (``--traceback`` shows one).
REFUSALS = (
    ValueError,
    FileNotFoundError,
    FileExistsError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
)
#: The exit status of a refused command (argparse's for a bad flag).
REFUSED = 2
#: ``errno`` of an ``OSError`` the file system raises part-way through a command's writes -> what to do.
FILE_SYSTEM_ERRORS = {
    errno.ENOSPC: "free space on that disk, or name an output folder on another one",
    errno.EDQUOT: "free space within your disk quota, or name an output folder elsewhere",
    errno.EFBIG: "a file-size limit stopped the write (ulimit -f, or the file system's own); name a "
    "folder on a file system that allows larger files",
    errno.EROFS: "that file system is read-only; name an output folder on a writable one",
    errno.EACCES: "permission denied: name paths you may read and an output folder you may write",
    errno.EPERM: "permission denied: name paths you may read and an output folder you may write",
    errno.EIO: "the disk reported an I/O error; check it, or name a folder on another disk",
    errno.ENAMETOOLONG: "the path is too long for the file system; name a shorter output folder",
}
#: The exit status of a command the file system stopped (sysexits' ``EX_IOERR``).
FILE_SYSTEM_FAILED = 74
#: The exit status of a run whose numbers stopped being finite (``FloatingPointError``: the message names the
#: setting to change, as a diverged training or a sampler pushed past float range raise it).
DIVERGED = 1
TRACEBACK_FLAG = "--traceback"


def refusal_line(error: BaseException, prog: str) -> tuple[str, int] | None:
    """The one line and exit status :func:`run_command` ends with for ``error``, or ``None`` for a bug.

    Args:
        error: What the command raised.
        prog: The command's name, leading the line (``sar-zero123-generate``).

    Returns:
        ``("<prog>: error: <message> (--traceback shows where)", status)``: :data:`REFUSED` for a refusal,
        :data:`FILE_SYSTEM_FAILED` for a file-system failure (what to do appended), :data:`DIVERGED` for
        numbers that stopped being finite; ``None`` otherwise.
    """
    message = " ".join(str(error).split()) or type(error).__name__
    if isinstance(error, OSError) and error.errno in FILE_SYSTEM_ERRORS:  # raised by the system, mid-work
        status = FILE_SYSTEM_FAILED
        message = f"{message}; {FILE_SYSTEM_ERRORS[error.errno]}"
    elif isinstance(error, REFUSALS):  # raised by the command's own checks (errno None), or a missing file
        status = REFUSED
    elif isinstance(error, FloatingPointError):
        status = DIVERGED
    else:
        return None
    return f"{prog}: error: {message} ({TRACEBACK_FLAG} shows where)", status


def run_command(function: Callable[[], Any], prog: str) -> int:
    """Run a command-line entry point (``function()`` reads ``sys.argv``); returns its exit status.

    0 once it returns, whatever it returns (a console script's launcher would print a returned folder and
    exit 1); a returned path (the command's output folder or file) is printed on stdout as its last line,
    for a shell to read (``out=$(sar-zero123-augment ... | tail -n 1)``). A refusal or a file-system failure
    prints one line on stderr (:func:`refusal_line`) and returns its status; ``--traceback`` anywhere on the
    command line (removed before the flags are parsed) lets it raise with its traceback instead. Any other
    exception raises (a bug shows where it is), and ``SystemExit`` (``--help``, a bad flag) passes through
    with its own code.
    """
    show_traceback = TRACEBACK_FLAG in sys.argv[1:]
    if show_traceback:
        sys.argv[1:] = [arg for arg in sys.argv[1:] if arg != TRACEBACK_FLAG]
    try:
        result = function()
    except Exception as error:
        ending = None if show_traceback else refusal_line(error, prog)
        if ending is None:
            raise
        line, status = ending
        print(line, file=sys.stderr)
        return status
    if isinstance(result, Path):
        print(result, flush=True)
    return 0
