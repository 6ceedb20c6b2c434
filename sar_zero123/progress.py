"""Progress bars that suit where they are written: a live bar on a terminal, one line per interval in a log.

``tqdm`` redraws with carriage returns, which a log file turns into one unreadable line; elsewhere than a
terminal :func:`progress_bar` writes a plain line every :data:`LOG_INTERVAL_S` seconds and the last
state. ``TQDM_DISABLE=1`` silences both.
"""

from __future__ import annotations

import sys
from typing import Any, TextIO

from tqdm.auto import tqdm

__all__ = ["LOG_INTERVAL_S", "progress_bar"]

#: Seconds between two progress lines in a non-interactive log.
LOG_INTERVAL_S = 30.0


class _Lines:
    """A stream that turns tqdm's carriage-return redraws into whole lines."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        for line in text.replace("\r", "\n").split("\n"):
            if line.strip():
                self.stream.write(line.rstrip() + "\n")

    def flush(self) -> None:
        self.stream.flush()


class _LogBar(tqdm):
    """A bar whose postfix and description wait for the next interval's line instead of forcing one."""

    def set_postfix(self, ordered_dict: Any = None, refresh: bool = False, **kwargs: Any) -> None:
        super().set_postfix(ordered_dict, refresh=False, **kwargs)

    def set_description(self, desc: str | None = None, refresh: bool = False) -> None:
        super().set_description(desc, refresh=False)


def progress_bar(*args: Any, **kwargs: Any) -> tqdm:
    """``tqdm(*args, **kwargs)`` on a terminal; in a log, one line per :data:`LOG_INTERVAL_S` seconds."""
    stream = kwargs.get("file") or sys.stderr
    if getattr(stream, "isatty", lambda: False)():
        return tqdm(*args, **kwargs)
    kwargs["file"] = _Lines(stream)
    kwargs.setdefault("mininterval", LOG_INTERVAL_S)
    kwargs.setdefault("maxinterval", LOG_INTERVAL_S * 10)
    kwargs.setdefault("ascii", True)
    return _LogBar(*args, **kwargs)
