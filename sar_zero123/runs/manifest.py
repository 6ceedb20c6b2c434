"""Sealed folders: a folder lists its other files with their sizes and SHA-256 in :data:`MANIFEST_FILE`, and a
reader checks the folder against it before trusting it."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from sar_zero123.config.json_io import write_json_atomic

__all__ = ["MANIFEST_FILE", "file_sha256", "manifest_problem", "unlisted_files", "write_manifest"]

#: The file a sealed folder (a checkpoint, a pipeline) lists its other files in, with their sizes and SHA-256.
MANIFEST_FILE = "manifest.json"
_HASH_CHUNK = 1 << 22


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes (read in chunks; synced, so that they are the bytes on disk)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_HASH_CHUNK):
            digest.update(chunk)
        os.fsync(handle.fileno())
    return digest.hexdigest()


def _sealed_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST_FILE)


def write_manifest(folder: str | os.PathLike) -> Path:
    """Write :data:`MANIFEST_FILE` (atomically, last): the size and SHA-256 of every other file under
    ``folder``."""
    folder = Path(folder)
    files = {
        path.relative_to(folder).as_posix(): {"bytes": path.stat().st_size, "sha256": file_sha256(path)}
        for path in _sealed_files(folder)
    }
    return write_json_atomic({"files": files}, folder / MANIFEST_FILE)


def manifest_problem(folder: str | os.PathLike, check_hashes: bool = True) -> str | None:
    """Why ``folder`` does not match its :data:`MANIFEST_FILE` (naming the file), or ``None`` when it does or
    has none; ``check_hashes`` also compares digests, not only sizes."""
    folder = Path(folder)
    manifest_file = folder / MANIFEST_FILE
    if not manifest_file.is_file():
        return None
    try:
        files = json.loads(manifest_file.read_text())["files"]
        entries = [(str(name), int(entry["bytes"]), str(entry["sha256"])) for name, entry in files.items()]
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        return f"{str(manifest_file)!r} is not a valid manifest ({error})"
    root = folder.resolve()
    for name, size, _ in sorted(entries):
        file = folder / name
        if not file.resolve().is_relative_to(root):
            return f"{MANIFEST_FILE} of {str(folder)!r} lists {name!r}, outside the folder"
        if not file.is_file():
            return f"{str(file)!r}, listed in {MANIFEST_FILE}, is missing"
        if file.stat().st_size != size:
            actual = file.stat().st_size
            return f"{str(file)!r} has {actual} bytes, {MANIFEST_FILE} records {size} (truncated?)"
    if check_hashes:
        for name, _, digest in sorted(entries):
            if file_sha256(folder / name) != digest:
                file = str(folder / name)
                return f"{file!r} does not match its SHA-256 in {MANIFEST_FILE} (changed or corrupt)"
    return None


def unlisted_files(folder: str | os.PathLike) -> list[str]:
    """The files under ``folder`` (relative POSIX paths) its manifest does not list; ``[]`` without a valid
    one."""
    folder = Path(folder)
    try:
        listed = set(json.loads((folder / MANIFEST_FILE).read_text())["files"])
    except (OSError, ValueError, KeyError, TypeError):
        return []
    names = (path.relative_to(folder).as_posix() for path in _sealed_files(folder))
    return [name for name in names if name not in listed]
