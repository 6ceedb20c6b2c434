"""Selections of chip records: seeded subsets, a hold-out, one depression, even azimuth spacing, a sector,
cross-validation folds. Two subset draws exist because recorded runs depend on each: :func:`select_chips`
(numpy, SimCLR) and :func:`subsample` (torch, the evaluators)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .index import ChipRecord

__all__ = [
    "at_depression",
    "circular_distance_deg",
    "cv_folds",
    "hold_out",
    "keep_evenly_spaced",
    "keep_sector",
    "select_chips",
    "subsample",
]


def select_chips(records: list[ChipRecord], max_chips: int | None, seed: int) -> list[ChipRecord]:
    """A seeded random subset of ``max_chips`` records in index order (all when None): random rather than the
    first N, so quick runs keep every class."""
    if max_chips is None or max_chips >= len(records):
        return list(records)
    keep = np.random.default_rng(seed).choice(len(records), size=max_chips, replace=False)
    return [records[i] for i in sorted(keep)]


def subsample(records: list[ChipRecord], max_chips: int | None, seed: int) -> list[ChipRecord]:
    """At most `max_chips` of the records (a seeded draw, in record order); all when `max_chips` is None."""
    if max_chips is None or len(records) <= max_chips:
        return records
    keep = torch.randperm(len(records), generator=torch.Generator().manual_seed(seed))
    return [records[i] for i in sorted(keep[:max_chips].tolist())]


def hold_out(
    records: list[ChipRecord], fraction: float, seed: int
) -> tuple[list[ChipRecord], list[ChipRecord]]:
    """Splits the records into `(train, test)` with `round(fraction * n)` (at least 1) seeded test chips.

    Raises:
        ValueError: If fewer than two records are given.
    """
    if len(records) < 2:
        raise ValueError(f"a train/test split needs at least 2 chips, got {len(records)}")
    count = min(max(1, round(fraction * len(records))), len(records) - 1)
    order = torch.randperm(len(records), generator=torch.Generator().manual_seed(seed)).tolist()
    test = set(order[:count])
    train = [record for i, record in enumerate(records) if i not in test]
    return train, [records[i] for i in sorted(test)]


def at_depression(records: Sequence[ChipRecord], depression_deg: float) -> list[ChipRecord]:
    """The records within 0.01 deg of a depression."""
    return [r for r in records if abs(r.depression_deg - depression_deg) < 0.01]


def circular_distance_deg(a: float, b: float) -> float:
    """Smallest angle between two azimuths in degrees, in [0, 180]."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def keep_evenly_spaced(records: Sequence[ChipRecord], k: int) -> list[ChipRecord]:
    """Per class, the `k` chips nearest to the azimuths ``i * 360 / k`` (each chip once), in record order.

    Raises:
        ValueError: If a class has fewer than `k` chips.
    """
    kept: set[int] = set()
    for name in sorted({r.target_class for r in records}):
        members = [i for i, r in enumerate(records) if r.target_class == name]
        if len(members) < k:
            raise ValueError(f"class {name} has {len(members)} chips, fewer than k={k}")
        for i in range(k):
            grid_deg = i * 360.0 / k
            free = [j for j in members if j not in kept]
            kept.add(min(free, key=lambda j: circular_distance_deg(records[j].azimuth_deg, grid_deg)))
    return [records[i] for i in sorted(kept)]


def keep_sector(records: Sequence[ChipRecord], sector_deg: float) -> list[ChipRecord]:
    """The chips with azimuth in ``[0, sector_deg)``."""
    return [r for r in records if r.azimuth_deg < sector_deg]


def cv_folds(records: Sequence[ChipRecord], folds: int, seed: int = 0) -> list[int]:
    """A fold index in ``[0, folds)`` per record: each class's records in a seeded random order, dealt
    round-robin, so every fold holds each class in proportion.

    Raises:
        ValueError: If `folds` is below 2 or a class has fewer records than folds.
    """
    if folds < 2:
        raise ValueError(f"folds must be >= 2, got {folds}")
    assignment = [0] * len(records)
    rng = np.random.default_rng(seed)
    for name in sorted({r.target_class for r in records}):
        members = [i for i, r in enumerate(records) if r.target_class == name]
        if len(members) < folds:
            raise ValueError(f"class {name} has {len(members)} chips, fewer than {folds} folds")
        for position, j in enumerate(rng.permutation(len(members))):
            assignment[members[j]] = position % folds
    return assignment
