"""Fabricated MSTAR files in the Phoenix format, for the tests of the raw reader and of `generate`."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_mstar(
    path: Path,
    magnitude: np.ndarray,
    phase: np.ndarray | None = None,
    fields: dict[str, str] | None = None,
    drop: tuple[str, ...] = (),
    declared_shape: tuple[int, int] | None = None,
) -> Path:
    """Writes a Phoenix-format chip the way the public release does (leading newline, big-endian)."""
    rows, cols = declared_shape or magnitude.shape
    values = {
        "PhoenixHeaderLength": "0",
        "native_header_length": "0",
        "NumberOfColumns": str(cols),
        "NumberOfRows": str(rows),
        "TargetType": "t72_tank",
        "TargetSerNum": "132",
        "TargetAz": "271.5",
        "DesiredDepression": "17",
        "MeasuredDepression": "17.093750",
    }
    values.update(fields or {})
    for key in drop:
        values.pop(key)

    def header_text(length: int) -> bytes:
        lines = ["", "[PhoenixHeaderVer01.04]"]
        lines += [
            f"{k}= {length:05d}" if k == "PhoenixHeaderLength" else f"{k}= {v}" for k, v in values.items()
        ]
        return ("\n".join(lines + ["[EndofPhoenixHeader]", ""])).encode("latin-1")

    length = len(header_text(0))
    data = header_text(length) + magnitude.astype(">f4").tobytes()
    if phase is not None:
        data += phase.astype(">f4").tobytes()
    path.write_bytes(data)
    return path
