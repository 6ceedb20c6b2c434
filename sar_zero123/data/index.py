"""Chip records and the ``index.csv`` that lists them.

Two layouts are read by :func:`load_index`:

* an image folder with ``index.csv`` (the layout of the shared MSTAR JPEG chips and of the built-in
  simulator): columns ``path,target_class,target_type,serial,depression_deg,azimuth_deg,height,width``
  (``path`` relative to the folder; ``mstar_source`` optional);
* a folder tree of original MSTAR files without ``index.csv``: the headers are scanned once and the
  index is written next to them (temporary file + ``os.replace``, so no partial index is ever left),
  then reused.
"""

from __future__ import annotations

import csv
import io
import math
import os
import stat
import tempfile
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from sar_zero123.domain import INDEX_COLUMNS, INDEX_FILENAME, read_number

from .mstar_raw import is_mstar_raw, read_mstar_raw, target_class_from_type

__all__ = [
    "INDEX_COLUMNS",
    "INDEX_FILENAME",
    "MSTAR_SOURCE_COLUMN",
    "OPTIONAL_COLUMNS",
    "REQUIRED_COLUMNS",
    "ChipRecord",
    "class_names_of",
    "load_index",
    "write_index",
]

REQUIRED_COLUMNS = ("path", "target_class", "serial", "depression_deg", "azimuth_deg")
MSTAR_SOURCE_COLUMN = "mstar_source"  # the original MSTAR file a converted chip came from
OPTIONAL_COLUMNS = ("target_type", "height", "width", MSTAR_SOURCE_COLUMN)


@dataclass(frozen=True)
class ChipRecord:
    """Metadata of one chip file.

    Attributes:
        path: Absolute path of the image file (JPEG/PNG, ``.npy`` or original MSTAR).
        target_class: Class name (e.g. ``"T72"``); labels are indices into the sorted class names.
        serial: Serial number of the physical object; (target_class, serial) identifies one object.
        depression_deg: Nominal depression angle in degrees, in (0, 90).
        azimuth_deg: Target azimuth in degrees, in [0, 360).
        target_type: Finer type name if known (e.g. ``"t72_tank"``).
        height: Image height in pixels if known.
        width: Image width in pixels if known.
        source: Where the chip came from if known (the original MSTAR path for the shared data).
    """

    path: Path
    target_class: str
    serial: str
    depression_deg: float
    azimuth_deg: float
    target_type: str | None = None
    height: int | None = None
    width: int | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        # Accept str paths and integer angles at the boundary; store the declared types.
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "depression_deg", float(self.depression_deg))
        object.__setattr__(self, "azimuth_deg", float(self.azimuth_deg))
        if not self.target_class:
            raise ValueError(f"{self.path}: target_class must be a non-empty string")
        # the class names folders (augment writes views/<target_class>/): one plain name, never a path
        if self.target_class in (".", "..") or any(c in self.target_class for c in "/\\\0"):
            raise ValueError(
                f"{self.path}: target_class must be a plain name (no '/', '\\', NUL, '.' or '..'), "
                f"got {self.target_class!r}"
            )
        if not (math.isfinite(self.depression_deg) and 0.0 < self.depression_deg < 90.0):
            raise ValueError(
                f"{self.path}: depression_deg must lie in (0, 90) degrees, got {self.depression_deg}"
            )
        if not (math.isfinite(self.azimuth_deg) and 0.0 <= self.azimuth_deg < 360.0):
            raise ValueError(f"{self.path}: azimuth_deg must lie in [0, 360) degrees, got {self.azimuth_deg}")

    @property
    def object_id(self) -> tuple[str, str]:
        """(target_class, serial): the physical object the chip shows."""
        return (self.target_class, self.serial)


def _parse_float(value: str, column: str, where: str) -> float:
    try:
        number = read_number(value)  # strictly: Python's float reads "3_0" as 30
    except ValueError:
        raise ValueError(f"{where}: column '{column}' must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{where}: column '{column}' must be finite, got {value!r}")
    return number


def _parse_optional_int(value: str | None, column: str, where: str) -> int | None:
    if value is None or value == "":
        return None
    try:
        return int(read_number(value, integer=True))  # strictly: Python's int reads "6_4" as 64
    except ValueError:
        raise ValueError(f"{where}: column '{column}' must be an integer, got {value!r}") from None


def _index_text(index_path: Path) -> str:
    """The index file as text, refused in one line where it is empty or not UTF-8.

    utf-8-sig: spreadsheet programs save CSV with a byte-order mark, which would rename the first column.

    Raises:
        ValueError: Naming the file, and for a byte that is not UTF-8 its line and column.
    """
    data = index_path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data.count(b"\n", 0, error.start) + 1
        field = data[data.rfind(b"\n", 0, error.start) + 1 : error.start].count(b",")
        header = data.split(b"\n", 1)[0].decode("utf-8-sig", "replace").strip().split(",")
        column = f"column {header[field]!r}" if line > 1 and field < len(header) else "the header"
        raise ValueError(
            f"{index_path}:{line}: {column} holds the byte 0x{data[error.start]:02x}, which is not UTF-8; "
            "save the index as UTF-8 text"
        ) from None
    if not text.strip():
        expected = list(REQUIRED_COLUMNS)
        raise ValueError(f"{index_path}: the file is empty; expected a header line with {expected}")
    return text


def _chip_path(root: Path, value: str, where: str) -> Path:
    """A row's ``path`` as the file it names: relative paths are read under the data folder ``root`` and
    never above it; an absolute path (how ``augment`` lists the real chips it keeps in place) as written.

    Raises:
        ValueError: Naming the file, the line and the column, for an empty path, a NUL byte, or a relative
            path that climbs out of ``root`` with ``..``.
    """
    if not value or "\0" in value:
        raise ValueError(f"{where}: column 'path' must name a chip file, got {value!r}")
    if Path(value).is_absolute():
        return root / value
    relative = os.path.normpath(value)
    if relative == os.pardir or relative.startswith(os.pardir + os.sep):
        raise ValueError(
            f"{where}: column 'path' {value!r} leads out of the data folder {root}; a relative path must "
            "stay inside it"
        )
    return root / relative


def _read_index_csv(index_path: Path) -> list[ChipRecord]:
    root = index_path.parent.resolve()
    with io.StringIO(_index_text(index_path), newline="") as handle:
        reader = csv.DictReader(handle)
        columns = reader.fieldnames or []
        missing = [name for name in REQUIRED_COLUMNS if name not in columns]
        if missing:
            raise ValueError(
                f"{index_path}: missing column(s) {missing}; expected at least {list(REQUIRED_COLUMNS)}"
            )
        unknown = [name for name in columns if name not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
        if unknown:
            raise ValueError(
                f"{index_path}: unknown column(s) {unknown}; expected only "
                f"{list(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)}"
            )
        records = []
        first_line: dict[Path, tuple[int, str]] = {}  # chip file -> (line, class) where it was listed first
        for line_number, row in enumerate(reader, start=2):
            where = f"{index_path}:{line_number}"
            if None in row or any(row[name] is None for name in columns):
                raise ValueError(f"{where}: expected {len(columns)} fields, got a row of a different length")
            path = _chip_path(root, row["path"], where)
            if path in first_line:
                line, target_class = first_line[path]
                what = (
                    f"under two classes ({target_class!r} on line {line}, {row['target_class']!r} here)"
                    if target_class != row["target_class"]
                    else f"twice (also on line {line})"
                )
                raise ValueError(f"{where}: chip file '{row['path']}' is listed {what}; list each chip once")
            first_line[path] = (line_number, row["target_class"])
            if not path.is_file():
                raise FileNotFoundError(f"{where}: chip file '{row['path']}' does not exist ({path})")
            azimuth_deg = _parse_float(row["azimuth_deg"], "azimuth_deg", where)
            if not 0.0 <= azimuth_deg < 360.0:
                raise ValueError(f"{where}: column 'azimuth_deg' must lie in [0, 360), got {azimuth_deg}")
            depression_deg = _parse_float(row["depression_deg"], "depression_deg", where)
            if not 0.0 < depression_deg < 90.0:
                raise ValueError(
                    f"{where}: column 'depression_deg' must lie in (0, 90) degrees, got {depression_deg}"
                )
            records.append(
                ChipRecord(
                    path=path,
                    target_class=row["target_class"],
                    serial=row["serial"],
                    depression_deg=depression_deg,
                    azimuth_deg=azimuth_deg,
                    target_type=row.get("target_type") or None,
                    height=_parse_optional_int(row.get("height"), "height", where),
                    width=_parse_optional_int(row.get("width"), "width", where),
                    source=row.get(MSTAR_SOURCE_COLUMN) or None,
                )
            )
    if not records:
        raise ValueError(f"{index_path}: the index lists no chips")
    return records


def write_index(records: Sequence[ChipRecord], root: str | Path) -> Path:
    """Writes ``root/index.csv`` atomically (temporary file, then ``os.replace``).

    Args:
        records: The chips; their paths must lie inside ``root`` (they are stored relative to it).
        root: The folder the index describes.

    Returns:
        The path of the written ``index.csv``.

    Raises:
        ValueError: If ``records`` is empty or a path lies outside ``root``.
    """
    root = Path(root).resolve()
    if not records:
        raise ValueError(f"{root}: refusing to write an index without chips")
    rows = []
    for record in records:
        try:
            relative = Path(record.path).resolve().relative_to(root)
        except ValueError:
            raise ValueError(f"{record.path}: chip path must lie inside the indexed folder {root}") from None
        rows.append(
            {
                "path": relative.as_posix(),
                "target_class": record.target_class,
                "target_type": record.target_type or "",
                "serial": record.serial,
                "depression_deg": repr(float(record.depression_deg)),
                "azimuth_deg": repr(float(record.azimuth_deg)),
                "height": "" if record.height is None else record.height,
                "width": "" if record.width is None else record.width,
                MSTAR_SOURCE_COLUMN: record.source or "",
            }
        )
    index_path = root / INDEX_FILENAME
    handle = tempfile.NamedTemporaryFile(
        "w", dir=root, prefix=".index.", suffix=".csv.tmp", delete=False, newline=""
    )
    try:
        with handle:
            writer = csv.DictWriter(handle, fieldnames=[*INDEX_COLUMNS, MSTAR_SOURCE_COLUMN])
            writer.writeheader()
            writer.writerows(rows)
        os.chmod(handle.name, 0o644)  # NamedTemporaryFile creates 0600; an index is meant to be shared
        os.replace(handle.name, index_path)
    except BaseException:
        Path(handle.name).unlink(missing_ok=True)
        raise
    return index_path


def _scan_raw_folder(root: Path) -> list[ChipRecord]:
    records = []
    for path in sorted(p for p in root.rglob("*") if p.is_file() and not p.name.startswith(".")):
        if path.name == INDEX_FILENAME or not is_mstar_raw(path):
            continue
        # Reading the whole chip validates the data length and values before the index is written.
        chip = read_mstar_raw(path)
        records.append(
            ChipRecord(
                path=path.resolve(),
                target_class=target_class_from_type(chip.target_type),
                serial=chip.serial,
                depression_deg=chip.depression_deg,
                azimuth_deg=chip.azimuth_deg,
                target_type=chip.target_type,
                height=chip.magnitude.shape[0],
                width=chip.magnitude.shape[1],
                source=path.relative_to(root).as_posix(),
            )
        )
    return records


def _stale_raw_scan(root: Path, records: list[ChipRecord], index_path: Path) -> str | None:
    """Why an ``index.csv`` that :func:`load_index` cached for a raw MSTAR folder no longer describes it
    (a file added, removed or changed after the index was written), or ``None``. Indexes written by
    other tools (whose paths are not their ``mstar_source``) are never stale."""
    if not all(r.source is not None and r.path == (root / r.source).resolve() for r in records):
        return None
    written_ns = index_path.stat().st_mtime_ns
    listed = {r.path for r in records}
    for path in sorted(p for p in root.rglob("*") if p.is_file() and not p.name.startswith(".")):
        if path.name == INDEX_FILENAME:
            continue
        if path.resolve() in listed:
            if path.stat().st_mtime_ns > written_ns:
                return f"{path} changed after the index was written"
        elif is_mstar_raw(path):
            return f"{path} is not in the index"
    return None


def load_index(root: str | Path) -> list[ChipRecord]:
    """Lists the chips of a data folder.

    Args:
        root: A folder with ``index.csv`` (paths in it relative to the folder), or a folder tree of
            original MSTAR files (indexed on first use; the index is cached as ``root/index.csv``, or
            not cached, with a warning, when the folder is read-only; a cached index is rescanned, with
            a warning, when a raw file was added or changed after it was written).

    Returns:
        One record per chip, in index order, with absolute paths.

    Raises:
        FileNotFoundError: If ``root`` does not exist or a path in the index does not exist.
        ValueError: If the index is empty or not UTF-8, misses a required column or has an unknown one, a
            value is malformed or out of range (azimuth outside [0, 360), depression outside (0, 90), a
            relative path that leads out of the folder; the message names the file, line and column), a
            chip file is listed twice (or under two classes), or the folder holds no chips.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"data folder not found: {root}")
    index_path = root / INDEX_FILENAME
    if index_path.is_file():
        records = _read_index_csv(index_path)
        stale = _stale_raw_scan(root.resolve(), records, index_path)
        if stale is None:
            return records
        message = f"{index_path}: cached index of a raw MSTAR folder is stale ({stale}); rescanning"
        warnings.warn(message, stacklevel=2)
    records = _scan_raw_folder(root.resolve())
    if not records:
        raise ValueError(
            f"{root}: no '{INDEX_FILENAME}' and no original MSTAR files "
            "(files starting with '[PhoenixHeader') found"
        )
    # A read-only data folder (e.g. a shared mount) still works; it is rescanned on every call. The mode
    # bits are checked too because root may write into folders marked read-only.
    if os.access(root, os.W_OK) and root.stat().st_mode & stat.S_IWUSR:
        write_index(records, root)
    else:
        warnings.warn(f"{root}: read-only folder, index not cached (rescanned next time)", stacklevel=2)
    return records


def class_names_of(records: Iterable[ChipRecord]) -> list[str]:
    """Sorted distinct class names: ``label = class_names.index(record.target_class)``."""
    return sorted({record.target_class for record in records})
