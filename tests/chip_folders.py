"""Small chip folders and encoder settings shared by the evaluator and evaluation tests."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image

from sar_zero123.data import ChipRecord, write_index

TINY_ENCODER = {
    "image_size": 16,
    "in_channels": 1,
    "cifar_stem": True,
    "depths": (1, 1),
    "hidden_sizes": (8, 16),
}


def write_chip_folder(
    root: Path,
    classes: tuple[str, ...] = ("A", "B"),
    azimuths_deg: tuple[float, ...] = tuple(range(0, 360, 30)),
    depressions_deg: tuple[float, ...] = (15.0, 17.0),
    size: int = 16,
    spot_px_per_depression_deg: float = 0.0,
) -> Path:
    """Writes `.npy` magnitude chips + `index.csv`: a class-dependent shape rotated to the azimuth, and a
    bright spot that moves down `spot_px_per_depression_deg` pixels per degree of depression."""
    root.mkdir(parents=True, exist_ok=True)
    records = []
    yy, xx = np.mgrid[:size, :size].astype(np.float32) - (size - 1) / 2
    for class_index, name in enumerate(classes):
        for depression in depressions_deg:
            for azimuth in azimuths_deg:
                angle = math.radians(azimuth)
                along = xx * math.cos(angle) + yy * math.sin(angle)
                across = -xx * math.sin(angle) + yy * math.cos(angle)
                length = 2.0 + 2.0 * class_index
                chip = np.exp(-(along**2) / (2 * length**2) - across**2 / 2.0) * (0.5 + 0.02 * depression)
                row = size // 2 + int(3 * math.cos(angle)) + round(spot_px_per_depression_deg * depression)
                chip[row, size // 2 + int(3 * math.sin(angle))] = 1.0
                path = root / f"{name}_{int(depression)}_{int(azimuth):03d}.npy"
                np.save(path, np.clip(chip, 0.0, 1.0).astype(np.float32))
                records.append(
                    ChipRecord(
                        path=path,
                        target_class=name,
                        serial=f"{name}1",
                        depression_deg=depression,
                        azimuth_deg=float(azimuth),
                        height=size,
                        width=size,
                    )
                )
    write_index(records, root)
    return root


def write_png_chip_folder(root: Path, size: tuple[int, int] = (20, 24)) -> Path:
    """Two classes x two depressions x three 8-bit PNG chips of ``size`` (larger than a 16 px crop), with an
    index.csv."""
    rng = np.random.default_rng(0)
    root.mkdir(parents=True)
    records = []
    for target_class in ("A", "B"):
        for depression in (15.0, 17.0):
            for i in range(3):
                path = root / f"{target_class}_{int(depression)}_{i}.png"
                Image.fromarray(rng.integers(0, 256, size=size, dtype=np.uint8)).save(path)
                records.append(ChipRecord(path, target_class, f"s{i % 2}", depression, 120.0 * i + 7.5))
    write_index(records, root)
    return root
