"""Seeded selections of chip records: a subset for quick runs, a train/test hold-out.

Two subset draws exist because recorded runs depend on them: :func:`select_chips` (numpy, the SimCLR
stage's ``max_train_chips``) and :func:`subsample` (torch, the evaluators' ``max_train_chips``).
"""

from __future__ import annotations

import numpy as np
import torch

from .index import ChipRecord

__all__ = ["hold_out", "select_chips", "subsample"]


def select_chips(records: list[ChipRecord], max_chips: int | None, seed: int) -> list[ChipRecord]:
    """A seeded random subset of `max_chips` records in index order (all of them when None).

    A random subset rather than the first N keeps every class present in quick runs.
    """
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
