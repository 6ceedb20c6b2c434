"""How a command ends at the command line (``runs/refusals.py``): its exit status and its one line."""

from __future__ import annotations

import errno
import sys
from pathlib import Path

import pytest

from sar_zero123.domain import naming_write_errors
from sar_zero123.runs.refusals import (
    DIVERGED,
    FILE_SYSTEM_ERRORS,
    FILE_SYSTEM_FAILED,
    REFUSED,
    refusal_line,
    run_command,
)


def _raising(error: BaseException):
    def command():
        raise error

    return command


def test_each_kind_of_ending_has_its_status_and_one_line():
    assert (REFUSED, FILE_SYSTEM_FAILED, DIVERGED) == (2, 74, 1)
    assert refusal_line(ValueError("seed: expected an integer,\n  got 'x'"), "p") == (
        "p: error: seed: expected an integer, got 'x' (--traceback shows where)",
        2,
    )
    # a refusal the command raised itself (no errno) stays a refusal, a missing input file too
    assert refusal_line(PermissionError("out: 'x' cannot be written; name a writable folder"), "p")[1] == 2
    assert refusal_line(FileNotFoundError(errno.ENOENT, "No such file or directory", "in.png"), "p") == (
        "p: error: [Errno 2] No such file or directory: 'in.png' (--traceback shows where)",
        2,
    )
    # the file system, part-way: what to do appended (errno mapped by OSError to its subclass or not)
    line, status = refusal_line(OSError(errno.EROFS, "Read-only file system", "/ro/view.npy"), "p")
    assert status == 74 and line == (
        "p: error: [Errno 30] Read-only file system: '/ro/view.npy'; that file system is read-only; name an "
        "output folder on a writable one (--traceback shows where)"
    )
    line, status = refusal_line(OSError(errno.EACCES, "Permission denied", "/x/a.npy"), "p")
    assert status == 74 and line.endswith("permission denied: name paths you may read and an output folder "
                                          "you may write (--traceback shows where)")  # fmt: skip
    with pytest.raises(OSError) as named:
        with naming_write_errors("/full/view_00", "the run is not marked finished (--resume redoes it)"):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert refusal_line(named.value, "sar-zero123-generate") == (
        "sar-zero123-generate: error: [Errno 28] could not write '/full/view_00': No space left on device; "
        "the run is not marked finished (--resume redoes it); free space on that disk, or name an output "
        "folder on another one (--traceback shows where)",
        74,
    )
    assert refusal_line(FloatingPointError("learning_rate: the loss is nan at step 3; lower it"), "p") == (
        "p: error: learning_rate: the loss is nan at step 3; lower it (--traceback shows where)",
        1,
    )
    # a bug, or an OSError the file system table does not know: its traceback
    assert refusal_line(RuntimeError("a bug"), "p") is None
    assert refusal_line(OSError(errno.ECONNREFUSED, "Connection refused"), "p") is None
    assert errno.ENOENT not in FILE_SYSTEM_ERRORS  # a missing input is the user's to fix: a refusal


def test_run_command_prints_the_line_returns_the_status_and_raises_bugs_and_on_traceback(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["prog", "--x", "1"])
    full = OSError(errno.ENOSPC, "No space left on device", "/d/a.npy")
    assert run_command(_raising(full), "sar-zero123-simulate") == 74
    assert capsys.readouterr().err == (
        "sar-zero123-simulate: error: [Errno 28] No space left on device: '/d/a.npy'; free space on that "
        "disk, or name an output folder on another one (--traceback shows where)\n"
    )
    assert run_command(_raising(FloatingPointError("diverged")), "p") == 1
    with pytest.raises(KeyError):
        run_command(_raising(KeyError("a bug")), "p")
    monkeypatch.setattr(sys, "argv", ["prog", "--traceback", "--x", "1"])
    with pytest.raises(OSError, match="No space left"):
        run_command(_raising(full), "p")
    assert sys.argv == ["prog", "--x", "1"]
    assert run_command(lambda: Path("out/folder"), "p") == 0
    assert capsys.readouterr().out.splitlines()[-1] == "out/folder"
