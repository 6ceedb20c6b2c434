"""Decibel scaling: magnitude -> decibels -> [0, 1] with dataset-global bounds::

    db = 20 * log10(m + 1e-3)                 # to_decibels; zero magnitude is -60 dB
    x  = (db - min_db) / (max_db - min_db)    # DecibelScaling.normalize, in [0, 1]

One ``(min_db, max_db)`` for the whole dataset, so relative brightness between chips survives; the bounds
are stored with every run so a model and its pipeline normalise identically.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sar_zero123.config.json_io import read_json
from sar_zero123.domain import DB_EPS, Array, from_decibels, to_decibels

from .images import load_magnitude

__all__ = [
    "SCALING_CHOICES",
    "SCALING_FILE",
    "check_magnitude",
    "MSTAR_RAW_MAX_DB",
    "UNIT_MAGNITUDE_MAX_DB",
    "ZERO_MAGNITUDE_DB",
    "DecibelScaling",
]

SCALING_FILE = "decibel_scaling.json"  # the DecibelScaling a VAE or pipeline folder expects (to_dict)
SCALING_CHOICES = ("unit", "mstar_raw", "fit")  # the training scripts' --scaling values
ZERO_MAGNITUDE_DB = 20.0 * math.log10(DB_EPS)  # -60 dB
# Largest decibel value of magnitudes normalised to [0, 1] (8-bit images as pixel/255, the simulator).
UNIT_MAGNITUDE_MAX_DB = 20.0 * math.log10(1.0 + DB_EPS)  # 0.00868 dB
# Upper bound the paper's reference implementation uses for calibrated (raw) MSTAR magnitudes.
MSTAR_RAW_MAX_DB = 24.4912


def check_magnitude(magnitude: Array, name: str = "magnitude") -> None:
    """Refuse magnitudes that are not finite and >= 0 (a negative one has no decibel value).

    Raises:
        ValueError: Naming ``name``, how many values are bad and the smallest one.
    """
    if isinstance(magnitude, torch.Tensor):
        values = magnitude.detach()
        finite, negative = torch.isfinite(values), values < 0
    else:
        values = np.asarray(magnitude)
        finite, negative = np.isfinite(values), values < 0
    if bool(finite.all()) and not bool(negative.any()):
        return
    smallest = float(values[finite].min()) if bool(finite.any()) else float("nan")
    raise ValueError(
        f"{name} must be finite and >= 0 (decibels of a negative magnitude are NaN), got "
        f"{int(negative.sum())} negative (smallest finite value {smallest:.4g}) and {int((~finite).sum())} "
        f"non-finite of {int(np.prod(values.shape))} values"
    )


@dataclass(frozen=True)
class DecibelScaling:
    """Min-max normalisation of decibels with dataset-global bounds (``min_db`` -> 0, ``max_db`` -> 1).

    The defaults fit magnitudes in [0, 1] (8-bit images read as pixel/255, the simulator). For calibrated
    raw MSTAR use :meth:`for_mstar_raw` (the paper's reference bound) or :meth:`fit` on the training chips.
    """

    min_db: float = ZERO_MAGNITUDE_DB
    max_db: float = UNIT_MAGNITUDE_MAX_DB

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_db) and math.isfinite(self.max_db)):
            raise ValueError(f"min_db and max_db must be finite, got {self.min_db} and {self.max_db}")
        if not self.max_db > self.min_db:
            raise ValueError(f"max_db must exceed min_db, got min_db={self.min_db}, max_db={self.max_db}")

    @classmethod
    def for_unit_magnitude(cls) -> DecibelScaling:
        """Bounds for magnitudes in [0, 1]: [-60 dB, 20*log10(1.001) dB] (the default)."""
        return cls(min_db=ZERO_MAGNITUDE_DB, max_db=UNIT_MAGNITUDE_MAX_DB)

    @classmethod
    def for_mstar_raw(cls) -> DecibelScaling:
        """Bounds for calibrated raw MSTAR magnitudes: [-60 dB, 24.4912 dB] (paper's reference code)."""
        return cls(min_db=ZERO_MAGNITUDE_DB, max_db=MSTAR_RAW_MAX_DB)

    @classmethod
    def from_choice(cls, choice: str, records: Iterable[Any] = ()) -> DecibelScaling:
        """The bounds a training script's ``--scaling`` names: ``"unit"``, ``"mstar_raw"`` or ``"fit"`` (on
        ``records``).

        Raises:
            ValueError: For another choice, or ``"fit"`` without records.
        """
        if choice == "unit":
            return cls.for_unit_magnitude()
        if choice == "mstar_raw":
            return cls.for_mstar_raw()
        if choice == "fit":
            return cls.fit(records)
        raise ValueError(f"scaling must be one of {SCALING_CHOICES}, got {choice!r}")

    @classmethod
    def fit(cls, data: Iterable[Any]) -> DecibelScaling:
        """The smallest and largest decibel value over all pixels of ``data`` (magnitude arrays or
        ChipRecords).

        Raises:
            ValueError: If ``data`` is empty, a magnitude is negative or not finite, or all pixels are equal.
        """
        low, high, count = math.inf, -math.inf, 0
        for item in data:
            if isinstance(item, torch.Tensor):
                magnitude = item.detach().cpu().numpy()
            elif isinstance(item, np.ndarray):
                magnitude = item
            else:
                magnitude = load_magnitude(item.path)
            if not np.isfinite(magnitude).all() or (magnitude < 0).any():
                raise ValueError(f"magnitude #{count} must be finite and >= 0 to fit decibel bounds")
            low = min(low, float(magnitude.min()))
            high = max(high, float(magnitude.max()))
            count += 1
        if count == 0:
            raise ValueError("data must hold at least one magnitude image to fit decibel bounds")
        return cls(min_db=float(to_decibels(np.float64(low))), max_db=float(to_decibels(np.float64(high))))

    def normalize(self, magnitude: Array, clip: bool = True) -> Array:
        """``(to_decibels(m) - min_db) / (max_db - min_db)``, clamped to [0, 1] with ``clip``; arrays or
        tensors.

        Raises:
            ValueError: If a magnitude is negative or not finite.
        """
        check_magnitude(magnitude)
        x = (to_decibels(magnitude) - self.min_db) / (self.max_db - self.min_db)
        if clip:
            return x.clamp(0.0, 1.0) if isinstance(x, torch.Tensor) else np.clip(x, 0.0, 1.0)
        return x

    def denormalize(self, x: Array) -> Array:
        """``from_decibels(min_db + x * (max_db - min_db))``, the inverse of :meth:`normalize` inside the
        bounds."""
        return from_decibels(self.min_db + x * (self.max_db - self.min_db))

    def to_dict(self) -> dict[str, float]:
        """JSON-serialisable bounds, e.g. ``{"min_db": -60.0, "max_db": 0.0087}``."""
        return {"min_db": float(self.min_db), "max_db": float(self.max_db)}

    def isclose(self, other: DecibelScaling, abs_tol: float = 1e-6) -> bool:
        """Whether ``other`` has the same bounds to ``abs_tol`` dB (a saved and a refitted scaling agree)."""
        return math.isclose(self.min_db, other.min_db, abs_tol=abs_tol) and math.isclose(
            self.max_db, other.max_db, abs_tol=abs_tol
        )

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DecibelScaling:
        """Rebuilds the scaling saved by :meth:`to_dict`.

        Raises:
            ValueError: If ``values`` is not a dict, or ``min_db`` or ``max_db`` is missing or invalid.
        """
        if not isinstance(values, dict):
            raise ValueError(f"decibel scaling must be a mapping with 'min_db' and 'max_db', got {values!r}")
        missing = [key for key in ("min_db", "max_db") if key not in values]
        if missing:
            raise ValueError(f"decibel scaling dict lacks {missing}; expected keys 'min_db' and 'max_db'")
        try:
            min_db, max_db = float(values["min_db"]), float(values["max_db"])
        except (TypeError, ValueError):
            raise ValueError(
                f"decibel scaling: min_db and max_db must be numbers, got {values['min_db']!r} and "
                f"{values['max_db']!r}"
            ) from None
        return cls(min_db=min_db, max_db=max_db)

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> DecibelScaling:
        """Reads a scaling saved as JSON by :meth:`to_dict`.

        Raises:
            FileNotFoundError: If ``path`` is not a file.
            ValueError: If the file is not a valid scaling; the message names the file.
        """
        values = read_json(path, what="a decibel scaling {'min_db': ..., 'max_db': ...}")
        try:
            return cls.from_dict(values)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
