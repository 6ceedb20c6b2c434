"""One writer per output folder: an exclusive lock taken before a stage or command touches the folder.

Two runs started together into the same folder would otherwise both pass the run-folder checks (the
folder is empty for both) and interleave their files. :func:`lock_output_folder` takes an exclusive,
non-blocking ``flock`` on ``<parent>/.<name>.lock``, beside the folder rather than in it, so that the
folder's own contents (and the checks of whether it is empty) are untouched, and ``--restart``, which moves
the folder aside, keeps the lock on the name. The holder writes who it is (process id, host, command, UTC
start) into the lock file; a second writer is refused with a ``ValueError`` that names it.

The operating system drops the lock when the holder exits, however it exits (a kill included), so a
crashed run never leaves a stale lock behind. A process may lock the same folder again (re-entrant);
:func:`release_output_folder` releases it early (:func:`~sar_zero123.runs.folder.finish_run`
does, once the run is finished). Hand-written because ``filelock``, the usual library, truncates the lock
file when a contender opens it, which erases the holder's name that the refusal must give.
"""

from __future__ import annotations

import atexit
import json
import os
import socket
import sys
from datetime import datetime, timezone
from pathlib import Path

try:  # POSIX; elsewhere the lock is not taken (the project's machines are Linux)
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

__all__ = ["is_lock_file", "lock_output_folder", "lock_path", "release_output_folder"]

_HELD: dict[Path, int] = {}  # resolved folder -> open descriptor of its lock file, for this process


def lock_path(folder: str | os.PathLike) -> Path:
    """The lock file of an output folder: ``<parent>/.<name>.lock``."""
    folder = Path(folder).resolve()
    return folder.parent / f".{folder.name}.lock"


def is_lock_file(path: str | os.PathLike) -> bool:
    """Whether `path` is named like a lock file of a sibling folder (``.<name>.lock``): emptiness checks
    skip it, since a killed writer leaves its (unlocked) file behind."""
    name = Path(path).name
    return name.startswith(".") and name.endswith(".lock")


def _holder(fd: int) -> str:
    try:
        text = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()
        info = json.loads(text)
        return (
            f"process {info['pid']} on {info['host']} (since {info['since']}, command: {info['command']})"
        )
    except (OSError, ValueError, KeyError, TypeError):
        return "another process (it has not said which yet)"


def lock_output_folder(folder: str | os.PathLike, flag_hint: str = "output_dir") -> None:
    """Takes the exclusive writer lock of `folder` for this process, or refuses a second writer.

    Creates the folder's parent if needed (not the folder). Nothing happens where the lock is already
    held by this process, or where the platform has no ``fcntl``.

    Args:
        folder: The output folder a stage or command is about to check and write.
        flag_hint: The user's name for it, used in the message.

    Raises:
        ValueError: Naming `flag_hint`, the folder and the holder, if another process holds the lock.
    """
    folder = Path(folder).resolve()
    if fcntl is None or folder in _HELD:
        return
    path = lock_path(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise ValueError(
                f"{flag_hint}: {str(folder)!r} is being written by {holder}; two writers would mix their "
                "files. Wait for it to end, or choose another folder"
            ) from None
        try:  # a holder that released it may have unlinked the file we opened: lock the live file
            if os.fstat(fd).st_ino == os.stat(path).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    info = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "since": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(sys.argv)[:300],
    }
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)
    _HELD[folder] = fd


def release_output_folder(folder: str | os.PathLike) -> None:
    """Releases this process's writer lock of `folder` (and removes its lock file); a no-op if not held."""
    folder = Path(folder).resolve()
    fd = _HELD.pop(folder, None)
    if fd is None:
        return
    try:
        lock_path(folder).unlink()
    except FileNotFoundError:
        pass
    os.close(fd)  # closing the descriptor drops the lock


@atexit.register
def _release_all() -> None:
    for folder in list(_HELD):
        release_output_folder(folder)
