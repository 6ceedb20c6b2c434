"""JSON files of the runs: a config as JSON-ready data, atomic writes (never a partial file) and reads whose
errors name the file.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from sar_zero123.domain import naming_write_errors

__all__ = ["config_to_dict", "read_json", "save_config", "write_json_atomic"]


def config_to_dict(config: Any) -> dict[str, Any]:
    """A JSON-serialisable dict of a config dataclass (paths become strings, tuples lists)."""

    def convert(value: Any) -> Any:
        if isinstance(value, Path):
            return str(value)
        if isinstance(value, (list, tuple)):
            return [convert(v) for v in value]
        if isinstance(value, dict):
            return {k: convert(v) for k, v in value.items()}
        return value

    return {f.name: convert(getattr(config, f.name)) for f in dataclasses.fields(config)}


def write_json_atomic(data: Any, path: str | os.PathLike) -> Path:
    """Write JSON to ``path`` through a temporary file and ``os.replace`` (never a partial file).

    Raises:
        OSError: If the file cannot be written (naming it; the previous file is unchanged).
    """
    path = Path(path)
    with naming_write_errors(path, "the previous file, if any, is unchanged"):
        return _write_json_atomic(data, path)


def _write_json_atomic(data: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as handle:
            json.dump(data, handle, indent=2, sort_keys=True)
            handle.write("\n")
            handle.flush()
            os.fsync(handle.fileno())
        # mkstemp creates owner-only files; give the result the usual umask-based mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_name, 0o666 & ~umask)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


def read_json(path: str | os.PathLike, what: str = "JSON") -> Any:
    """The JSON value stored in ``path``, with errors that name the file.

    Args:
        path: The file.
        what: What the file should hold, for the messages (e.g. ``"a DecibelScaling (min_db, max_db)"``).

    Returns:
        The parsed value.

    Raises:
        FileNotFoundError: If ``path`` is not a file.
        ValueError: If the file is not UTF-8 JSON; the message names the file, the line and the column.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; expected {what}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise ValueError(
            f"{path}: invalid JSON at line {error.lineno} column {error.colno} ({error.msg}); expected {what}"
        ) from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file; expected {what}") from None


def save_config(config: Any, directory: str | os.PathLike, name: str = "config.json") -> Path:
    """Save the resolved config as JSON next to a run's outputs; returns the file path."""
    return write_json_atomic(config_to_dict(config), Path(directory) / name)
