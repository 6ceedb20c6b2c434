"""Reader for the SAMPLE dataset (Synthetic and Measured Paired Labeled Experiment).

Layout of the public release::

    png_images/{decibel,qpm}/{real,synth}/<class>/<name>.png
    mat_files/{real,synth}/<class>/<name>.mat        # keys complex_img, azimuth, elevation, ...

with names such as ``2s1_real_A_elevDeg_015_azCenter_010_22_serial_b01.png`` (class ``2s1``, elevation
15 deg, azimuth 10.22 deg, serial ``b01``). A measured chip and its synthetic twin share class, elevation,
azimuth and serial; :func:`load_sample` pairs them on exactly that. The PNGs are 8-bit (read as pixel/255),
the ``.mat`` complex image is read as its modulus.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from .index import ChipRecord

__all__ = ["SAMPLE_FORMATS", "SamplePair", "load_sample", "parse_sample_name"]

SAMPLE_FORMATS = ("decibel", "qpm", "mat")
_NAME = re.compile(
    r"^(?P<target>[A-Za-z0-9]+)_(?P<kind>real|synth)_(?P<variant>[A-Za-z0-9]+)_elevDeg_(?P<elevation>\d+)"
    r"_azCenter_(?P<az_int>\d+)_(?P<az_frac>\d+)_serial_(?P<serial>[A-Za-z0-9-]+)$"
)


@dataclass(frozen=True)
class SamplePair:
    """A measured chip and its synthetic twin (same class, elevation, azimuth and serial)."""

    real: ChipRecord
    synth: ChipRecord


def parse_sample_name(path: str | Path) -> tuple[str, ChipRecord]:
    """Parses a SAMPLE file name into ``(kind, record)``, kind ``"real"`` or ``"synth"``; the class is
    upper-cased (``"2S1"``) and the elevation is the depression.

    Raises:
        ValueError: If the name does not follow the SAMPLE pattern or the azimuth lies outside [0, 360).
    """
    path = Path(path)
    match = _NAME.match(path.stem)
    if match is None:
        raise ValueError(
            f"{path}: not a SAMPLE file name; expected "
            "'<class>_<real|synth>_<variant>_elevDeg_<EEE>_azCenter_<AAA>_<FF>_serial_<serial>'"
        )
    azimuth_deg = float(f"{int(match['az_int'])}.{match['az_frac']}")
    if not 0.0 <= azimuth_deg < 360.0:
        raise ValueError(f"{path}: azimuth must lie in [0, 360) degrees, got {azimuth_deg}")
    record = ChipRecord(
        path=path.resolve(),
        target_class=match["target"].upper(),
        serial=match["serial"],
        depression_deg=float(int(match["elevation"])),
        azimuth_deg=azimuth_deg,
        target_type=match["target"],
        source=match["variant"],
    )
    return match["kind"], record


def _format_dir(root: Path, image_format: str, kind: str) -> Path:
    if image_format == "mat":
        return root / "mat_files" / kind
    return root / "png_images" / image_format / kind


def load_sample(root: str | Path, image_format: str = "qpm") -> list[SamplePair]:
    """The measured/synthetic pairs of a SAMPLE folder, sorted by (class, serial, elevation, azimuth); chips
    without a twin are left out. ``image_format``: ``"qpm"``, ``"decibel"`` (PNG) or ``"mat"``.

    Raises:
        FileNotFoundError: If the folder of real or synthetic chips for the format does not exist.
        ValueError: If ``image_format`` is unknown, a file name does not parse, two chips of one kind
            share a pose, or no pair matches.
    """
    if image_format not in SAMPLE_FORMATS:
        raise ValueError(f"image_format must be one of {list(SAMPLE_FORMATS)}, got {image_format!r}")
    root = Path(root)
    suffix = ".mat" if image_format == "mat" else ".png"
    by_kind: dict[str, dict[tuple, ChipRecord]] = {}
    for kind in ("real", "synth"):
        folder = _format_dir(root, image_format, kind)
        if not folder.is_dir():
            raise FileNotFoundError(f"SAMPLE folder not found: {folder} (expected <class>/*{suffix} inside)")
        chips: dict[tuple, ChipRecord] = {}
        for path in sorted(folder.glob(f"*/*{suffix}")):
            parsed_kind, record = parse_sample_name(path)
            if parsed_kind != kind:
                raise ValueError(f"{path}: a '{parsed_kind}' chip inside the '{kind}' folder")
            key = (record.target_class, record.serial, record.depression_deg, record.azimuth_deg)
            if key in chips:
                raise ValueError(f"{path}: same class/serial/elevation/azimuth as {chips[key].path}")
            chips[key] = record
        by_kind[kind] = chips
    keys = sorted(by_kind["real"].keys() & by_kind["synth"].keys())
    if not keys:
        counts = {kind: len(chips) for kind, chips in by_kind.items()}
        raise ValueError(f"{root}: no real/synth pair shares class, serial, elevation, azimuth ({counts})")
    return [SamplePair(real=by_kind["real"][k], synth=by_kind["synth"][k]) for k in keys]
