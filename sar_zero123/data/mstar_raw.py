"""Reader for chips in the original MSTAR ("Phoenix") file format.

An MSTAR chip file is an ASCII header followed by binary data::

    [PhoenixHeaderVer01.04]
    PhoenixHeaderLength= 01974
    NumberOfColumns= 128
    NumberOfRows= 128
    TargetType= bmp2_tank
    TargetSerNum= c21
    TargetAz= 13.191422
    DesiredDepression= 17
    ...
    [EndofPhoenixHeader]
    <rows*cols big-endian float32 magnitude><rows*cols big-endian float32 phase>

``PhoenixHeaderLength`` counts the header's bytes from the file's start; a non-zero
``native_header_length`` announces a second, binary header before the pixels. Some releases store only
the magnitude plane. No maintained Python package reads this format (readers in the wild fold or
truncate the azimuth).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "MSTARChip",
    "REQUIRED_HEADER_FIELDS",
    "is_mstar_raw",
    "read_mstar_header",
    "read_mstar_raw",
    "target_class_from_type",
]

PHOENIX_MAGIC = b"[PhoenixHeader"
END_OF_HEADER = "[EndofPhoenixHeader]"
# Fields needed to locate the pixels and to label the chip.
REQUIRED_HEADER_FIELDS = (
    "PhoenixHeaderLength",
    "NumberOfRows",
    "NumberOfColumns",
    "TargetType",
    "TargetSerNum",
    "TargetAz",
    "DesiredDepression",
)
# The header is a few kB; read at most this much when looking for its end.
_MAX_HEADER_BYTES = 1 << 16
_FIELD = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=\s*(.*?)\s*$")


@dataclass(frozen=True)
class MSTARChip:
    """One chip read from an original MSTAR file.

    Attributes:
        magnitude: Float32 magnitude as stored, (H, W).
        phase: Float32 phase in radians, (H, W), or ``None`` when the file holds only magnitude.
        header: Every ``key= value`` field of the Phoenix header, as strings.
        azimuth_deg: ``TargetAz`` in [0, 360), neither folded nor rounded.
        depression_deg: ``DesiredDepression`` (the protocols' nominal 15 or 17; the measured value is
            ``header["MeasuredDepression"]``).
    """

    magnitude: np.ndarray
    phase: np.ndarray | None
    header: dict[str, str]
    target_type: str
    serial: str
    azimuth_deg: float
    depression_deg: float

    @property
    def target_class(self) -> str:
        """The class name used by the MSTAR protocols (``"BMP2"``, ``"ZSU234"``, ...)."""
        return target_class_from_type(self.target_type)


def target_class_from_type(target_type: str) -> str:
    """Maps an MSTAR ``TargetType`` to the protocols' class name: the part before the first underscore,
    upper-cased, without hyphens (``bmp2_tank -> BMP2``, ``zsu23-4_gun -> ZSU234``).

    Raises:
        ValueError: If ``target_type`` is empty.
    """
    name = target_type.strip().split("_")[0].replace("-", "").upper()
    if not name:
        raise ValueError(f"TargetType must be a non-empty name, got {target_type!r}")
    return name


def is_mstar_raw(path: str | Path) -> bool:
    """Whether a file starts with a Phoenix header (cheap: reads 64 bytes)."""
    with open(path, "rb") as handle:
        return handle.read(64).lstrip().startswith(PHOENIX_MAGIC)


def _parse_header(text: str) -> dict[str, str]:
    """``key= value`` lines of a header text that ends at ``[EndofPhoenixHeader]``."""
    header: dict[str, str] = {}
    for line in text.splitlines():
        match = _FIELD.match(line)
        if match:
            header[match.group(1)] = match.group(2)
    return header


def _header_number(header: dict[str, str], key: str, path: Path, kind: type = float) -> float | int:
    if key not in header:
        raise ValueError(f"{path}: Phoenix header has no required field '{key}'")
    try:
        value = kind(header[key])
    except ValueError:
        raise ValueError(
            f"{path}: header field '{key}' must be {kind.__name__}, got {header[key]!r}"
        ) from None
    if kind is float and not math.isfinite(value):
        raise ValueError(f"{path}: header field '{key}' must be finite, got {header[key]!r}")
    return value


def read_mstar_header(path: str | Path) -> dict[str, str]:
    """Reads only the Phoenix header of an MSTAR file, every field as a string.

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        ValueError: If the file does not start with a Phoenix header or the header does not end.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"MSTAR file not found: {path}")
    with open(path, "rb") as handle:
        head = handle.read(_MAX_HEADER_BYTES)
    # Files of the public release start with a newline before the first header line.
    if not head.lstrip().startswith(PHOENIX_MAGIC):
        raise ValueError(f"{path}: expected an MSTAR file starting with '[PhoenixHeader', got {head[:20]!r}")
    end = head.find(END_OF_HEADER.encode())
    if end < 0:
        raise ValueError(f"{path}: no '{END_OF_HEADER}' line found; not a complete MSTAR Phoenix header")
    return _parse_header(head[:end].decode("latin-1"))


def read_mstar_raw(path: str | Path) -> MSTARChip:
    """Reads an MSTAR chip: Phoenix header, then big-endian float32 magnitude and phase.

    Shape:
        ``magnitude`` and ``phase``: (NumberOfRows, NumberOfColumns).

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        ValueError: If a required header field is missing or malformed, the file length is not the headers
            plus exactly one or two planes, the magnitude is negative or not finite, ``TargetAz`` lies outside
            [0, 360) or ``DesiredDepression`` outside (0, 90).
    """
    # 1. header
    path = Path(path)
    header = read_mstar_header(path)
    for key in REQUIRED_HEADER_FIELDS:
        if key not in header:
            raise ValueError(f"{path}: Phoenix header has no required field '{key}'")
    header_length = int(_header_number(header, "PhoenixHeaderLength", path, int))
    rows = int(_header_number(header, "NumberOfRows", path, int))
    cols = int(_header_number(header, "NumberOfColumns", path, int))
    native_length = 0
    if "native_header_length" in header:
        native_length = int(_header_number(header, "native_header_length", path, int))
    if rows <= 0 or cols <= 0:
        raise ValueError(f"{path}: NumberOfRows and NumberOfColumns must be positive, got {rows} x {cols}")
    azimuth_deg = float(_header_number(header, "TargetAz", path))
    if not 0.0 <= azimuth_deg < 360.0:
        raise ValueError(f"{path}: header field 'TargetAz' must lie in [0, 360) degrees, got {azimuth_deg}")
    depression_deg = float(_header_number(header, "DesiredDepression", path))
    if not 0.0 < depression_deg < 90.0:
        raise ValueError(
            f"{path}: header field 'DesiredDepression' must lie in (0, 90) degrees, got {depression_deg}"
        )
    if not header["TargetType"].strip():
        raise ValueError(f"{path}: header field 'TargetType' is empty; expected a name such as 't72_tank'")

    # 2. pixels: magnitude plane, then (optionally) the phase plane
    raw = path.read_bytes()
    header_end = raw.find(END_OF_HEADER.encode()) + len(END_OF_HEADER)
    if header_length < header_end or native_length < 0:
        raise ValueError(
            f"{path}: header field 'PhoenixHeaderLength' ({header_length}) must cover the ASCII header "
            f"({header_end} bytes) and 'native_header_length' must be >= 0, got {native_length}"
        )
    data_start = header_length + native_length
    data = raw[data_start:]
    plane_bytes = rows * cols * 4
    # the data is exactly one plane (magnitude only) or two (magnitude, phase): any other length means
    # the header's sizes or lengths do not describe this file (edited, or the file was cut)
    if len(data) not in (plane_bytes, 2 * plane_bytes):
        if len(data) < plane_bytes:
            problem, detail = "truncated MSTAR file", "the magnitude plane is incomplete"
        elif len(data) < 2 * plane_bytes:
            problem, detail = "truncated MSTAR file", "the phase plane is incomplete"
        else:
            problem = "MSTAR file longer than its header declares"
            detail = f"{len(data) - 2 * plane_bytes} bytes after the phase plane"
        raise ValueError(
            f"{path}: {problem}: header declares {rows} x {cols} float32 pixels ({plane_bytes} bytes per "
            f"plane: magnitude, then optionally phase) after PhoenixHeaderLength={header_length} + "
            f"native_header_length={native_length} bytes, so the file should have {data_start + plane_bytes} "
            f"or {data_start + 2 * plane_bytes} bytes, but it has {len(raw)} ({detail})"
        )
    magnitude = np.frombuffer(data, dtype=">f4", count=rows * cols).reshape(rows, cols).astype(np.float32)
    phase = None
    if len(data) == 2 * plane_bytes:
        phase = np.frombuffer(data, dtype=">f4", count=rows * cols, offset=plane_bytes)
        phase = phase.reshape(rows, cols).astype(np.float32)
    if not np.isfinite(magnitude).all():
        raise ValueError(f"{path}: magnitude contains non-finite values (NaN or inf); expected finite floats")
    if (magnitude < 0).any():
        raise ValueError(f"{path}: magnitude contains negative values; expected magnitudes >= 0")
    return MSTARChip(
        magnitude=magnitude,
        phase=phase,
        header=header,
        target_type=header["TargetType"],
        serial=header["TargetSerNum"],
        azimuth_deg=azimuth_deg,
        depression_deg=depression_deg,
    )
