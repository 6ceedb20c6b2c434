"""``ChipDataset``: single chips as normalised-dB tensors with class label and pose."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from .images import center_crop_resize, load_magnitude
from .index import ChipRecord, class_names_of
from .scaling import DecibelScaling

__all__ = ["ChipDataset", "load_chip", "resolve_class_names"]


def resolve_class_names(records: Sequence[ChipRecord], class_names: Sequence[str] | None) -> list[str]:
    """Class names that define the labels: given, or the sorted classes of ``records``. The training set's
    names keep labels stable on a split lacking some classes (the MSTAR-OOD test split holds only T72).

    Raises:
        ValueError: If ``records`` is empty, names repeat, or a record's class is not among the names.
    """
    if not records:
        raise ValueError("records must hold at least one chip")
    names = class_names_of(records) if class_names is None else list(class_names)
    if len(set(names)) != len(names):
        raise ValueError(f"class_names must be distinct, got {names}")
    unknown = sorted({r.target_class for r in records} - set(names))
    if unknown:
        raise ValueError(f"class_names {names} lack the record classes {unknown}")
    return names


def load_chip(path: Any, size: int, crop_size: int | None = None) -> np.ndarray:
    """Reads a chip file as magnitude, centre-cropped and resized to ``size``. Shape: (size, size).

    Raises:
        ValueError: If the file is unreadable or smaller than :data:`~sar_zero123.data.MIN_CHIP_SIZE`.
    """
    return center_crop_resize(load_magnitude(path), size=size, crop_size=crop_size, name=str(path))


class ChipDataset(Dataset):
    """Chips as model inputs.

    Each item is ``{"image": (1, S, S) float32 normalised dB, "label": int, "azimuth_deg": float,
    "depression_deg": float}`` plus ``"magnitude": (1, S, S) float32`` when ``return_magnitude`` (co-domain
    augmentations act on magnitude).

    Args:
        scaling: Decibel bounds; default :meth:`DecibelScaling.for_unit_magnitude`. Pass a fitted scaling
            for raw MSTAR magnitudes.
        class_names: Names defining the labels (default: sorted classes of ``records``).
        crop_size: Side of the centre crop before resizing to ``size``.

    Raises:
        ValueError: If ``records`` is empty, ``size`` < 1 or ``class_names`` misses a class.
    """

    def __init__(
        self,
        records: Sequence[ChipRecord],
        size: int = 128,
        scaling: DecibelScaling | None = None,
        return_magnitude: bool = False,
        class_names: Sequence[str] | None = None,
        crop_size: int | None = None,
    ) -> None:
        if size < 1:
            raise ValueError(f"size must be >= 1, got {size}")
        self.records = list(records)
        self.class_names = resolve_class_names(self.records, class_names)
        self.size = size
        self.crop_size = crop_size
        self.scaling = scaling if scaling is not None else DecibelScaling.for_unit_magnitude()
        self.return_magnitude = return_magnitude
        self._label = {name: i for i, name in enumerate(self.class_names)}

    def __len__(self) -> int:
        return len(self.records)

    def label_of(self, record: ChipRecord) -> int:
        """Index of the record's class in :attr:`class_names`."""
        return self._label[record.target_class]

    def __getitem__(self, index: int) -> dict[str, Any]:
        record = self.records[index]
        magnitude = torch.from_numpy(load_chip(record.path, self.size, self.crop_size))[None]  # (1, S, S)
        item: dict[str, Any] = {
            "image": self.scaling.normalize(magnitude),
            "label": self.label_of(record),
            "azimuth_deg": float(record.azimuth_deg),
            "depression_deg": float(record.depression_deg),
        }
        if self.return_magnitude:
            item["magnitude"] = magnitude
        return item
