"""One writer per output folder: an exclusive lock taken before a stage or command touches the folder.

Two runs started together into one empty folder would both pass the run-folder checks and interleave
their files. :func:`lock_output_folder` takes a non-blocking ``flock`` on ``<parent>/.<name>.lock``, beside
the folder so its contents stay untouched and ``--restart`` keeps the lock on the name; the holder writes
who it is, so a second writer is refused naming it. The OS drops the lock however the holder exits (no
stale locks). Hand-written because ``filelock`` truncates the lock file when a contender opens it.
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
    """Whether ``path`` is named like a sibling's lock file: emptiness checks skip it, since a killed writer
    leaves its (unlocked) file behind."""
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
    """Takes the exclusive writer lock of ``folder`` for this process, or refuses a second writer.

    Creates the folder's parent (not the folder). Re-entrant; a no-op without ``fcntl``.

    Raises:
        ValueError: Naming ``flag_hint``, the folder and the holder, if another process holds the lock.
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
