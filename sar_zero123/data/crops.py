"""A chip folder as the exact centre crops its stages read (:func:`write_crops`): small lossless 8-bit
files with the same records, a working copy that fits where the original folder does not (a device call's
carried files)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from PIL import Image

from .datasets import load_chip
from .index import ChipRecord, load_index, write_index

__all__ = ["write_crops"]


def write_crops(data: str | Path, out: str | Path, image_size: int = 64, every: int = 1) -> Path:
    """Each chip of ``data`` as the ``image_size`` px centre crop the stages read (``load_chip`` at
    ``crop_size=None``), an 8-bit PNG in ``out/chips`` with an ``index.csv`` of the same records; with
    ``every`` > 1 only every ``every``-th chip of each class, serial and depression in azimuth order (a
    sparser azimuth grid). Returns the index file.

    Raises:
        FileNotFoundError: If ``data`` has no chip index.
        ValueError: If ``out`` already holds files, ``every`` < 1, or a chip is not 8-bit (its crop would
            not be exact).
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"out: {out} already holds files; give an empty or new folder")
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    records = load_index(data)
    if every > 1:
        groups: dict[tuple, list[ChipRecord]] = {}
        for record in records:
            groups.setdefault((record.target_class, record.serial, record.depression_deg), []).append(record)
        kept = set()
        for group in groups.values():
            kept.update(id(record) for record in sorted(group, key=lambda r: r.azimuth_deg)[::every])
        records = [record for record in records if id(record) in kept]
    (out / "chips").mkdir(parents=True, exist_ok=True)
    cropped = []
    for number, record in enumerate(records):
        magnitude = load_chip(record.path, image_size)
        pixels = np.rint(magnitude * 255.0)
        if np.abs(pixels - magnitude * 255.0).max() > 1e-3:
            raise ValueError(f"{record.path}: not an 8-bit chip; its crop cannot be stored exactly as 8 bits")
        path = out / "chips" / f"{number:06d}.png"
        Image.fromarray(pixels.astype(np.uint8)).save(path, optimize=True)
        cropped.append(dataclasses.replace(record, path=path.resolve(), height=image_size, width=image_size))
    return write_index(cropped, out)
