"""``ViewPairDataset``: two views of the same object (``target_class`` and ``serial``) and their relative
pose::

    d_az_deg = wrap(target azimuth - input azimuth)   in (-180, 180]
    d_el_deg = target depression - input depression

The pair list is drawn once from ``seed`` and the epoch, so every DataLoader worker sees the same pairs.
"""

from __future__ import annotations

import functools
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from .datasets import load_chip, resolve_class_names
from .index import ChipRecord
from .scaling import DecibelScaling
from .splits import _DEPRESSION_TOL_DEG, prepare_splits

__all__ = ["ViewPairDataset", "subsample_objects", "wrap_azimuth_deg"]


def wrap_azimuth_deg(angle_deg: float | np.ndarray) -> float | np.ndarray:
    """Wraps an angle difference in degrees to (-180, 180] (so -180 becomes +180)."""
    wrapped = 180.0 - np.mod(180.0 - np.asarray(angle_deg, dtype=np.float64), 360.0)
    # np.mod(-1e-14, 360) rounds to 360.0, which would give exactly -180
    wrapped = np.where(wrapped <= -180.0, wrapped + 360.0, wrapped)
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def _near_any(depressions_deg: np.ndarray, wanted_deg: Sequence[float]) -> np.ndarray:
    """Which depressions lie within the protocols' nominal tolerance of one of ``wanted_deg``."""
    distance = np.abs(depressions_deg[:, None] - np.asarray(wanted_deg, dtype=np.float64)[None, :])
    return (distance < _DEPRESSION_TOL_DEG).any(axis=1)


class ViewPairDataset(Dataset):
    """Pairs of chips of one object at two poses, for novel-view training and evaluation.

    Each item is ``{"input": (1, S, S), "target": (1, S, S)`` float32 normalised dB, ``"d_az_deg"``
    in (-180, 180], ``"d_el_deg"``, ``"label"``, ``"input_azimuth_deg"``, ``"target_azimuth_deg"``,
    ``"input_depression_deg"``, ``"target_depression_deg"}``, plus ``"input_magnitude"`` and
    ``"target_magnitude"`` (1, S, S) when ``return_magnitude``.

    Every input chip with an admissible partner (same object, not itself, within ``max_d_az_deg``, the
    depressions asked for, matched within 0.5 deg) gives ``pairs_per_chip`` pairs with targets drawn
    uniformly from its partners; or, with ``num_pairs``, that many pairs with uniformly drawn inputs.

    Args:
        scaling: Decibel bounds (default :meth:`DecibelScaling.for_unit_magnitude`).
        same_depression: Pair only chips at the same depression.
        class_names: Names defining the labels (default: sorted classes of ``records``).
        crop_size: Side of the centre crop before resizing to ``size``.

    Raises:
        ValueError: For a bad option or when no chip has an admissible partner.
    """

    def __init__(
        self,
        records: Sequence[ChipRecord],
        size: int = 128,
        scaling: DecibelScaling | None = None,
        max_d_az_deg: float | None = None,
        same_depression: bool = True,
        seed: int = 0,
        pairs_per_chip: int = 1,
        num_pairs: int | None = None,
        class_names: Sequence[str] | None = None,
        return_magnitude: bool = False,
        crop_size: int | None = None,
        input_depressions_deg: Sequence[float] | None = None,
        target_depressions_deg: Sequence[float] | None = None,
    ) -> None:
        if size < 1:
            raise ValueError(f"size must be >= 1, got {size}")
        if max_d_az_deg is not None and not 0.0 <= max_d_az_deg <= 180.0:
            raise ValueError(f"max_d_az_deg must lie in [0, 180] degrees or be None, got {max_d_az_deg}")
        if pairs_per_chip < 1:
            raise ValueError(f"pairs_per_chip must be >= 1, got {pairs_per_chip}")
        if num_pairs is not None and num_pairs < 1:
            raise ValueError(f"num_pairs must be >= 1 or None, got {num_pairs}")
        self.records = list(records)
        self.class_names = resolve_class_names(self.records, class_names)
        self.size = size
        self.crop_size = crop_size
        self.scaling = scaling if scaling is not None else DecibelScaling.for_unit_magnitude()
        self.max_d_az_deg = max_d_az_deg
        self.same_depression = same_depression
        self.input_depressions_deg = None if input_depressions_deg is None else list(input_depressions_deg)
        self.target_depressions_deg = None if target_depressions_deg is None else list(target_depressions_deg)
        self.seed = seed
        self.pairs_per_chip = pairs_per_chip
        self.num_pairs = num_pairs
        self.return_magnitude = return_magnitude
        self._label = {name: i for i, name in enumerate(self.class_names)}
        self._groups = self._group_objects()
        if not any(allowed.any() for _, allowed in self._groups):
            raise ValueError(
                f"no chip has a partner view of the same object (max_d_az_deg={max_d_az_deg}, "
                f"same_depression={same_depression}, input_depressions_deg={input_depressions_deg}, "
                f"target_depressions_deg={target_depressions_deg}, {len(self.records)} chips at depressions "
                f"{sorted({r.depression_deg for r in self.records})})"
            )
        self.set_epoch(0)

    def _group_objects(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per object (and depression): member indices and the (n, n) admissible-pair mask."""
        groups: dict[tuple, list[int]] = defaultdict(list)
        for i, record in enumerate(self.records):
            key = record.object_id + ((round(record.depression_deg, 3),) if self.same_depression else ())
            groups[key].append(i)
        result = []
        for members in groups.values():
            azimuths = np.array([self.records[i].azimuth_deg for i in members])
            d_az = np.abs(wrap_azimuth_deg(azimuths[None, :] - azimuths[:, None]))  # (n_input, n_target)
            allowed = ~np.eye(len(members), dtype=bool)
            if self.max_d_az_deg is not None:
                allowed &= d_az <= self.max_d_az_deg
            depressions = np.array([self.records[i].depression_deg for i in members])
            if self.input_depressions_deg is not None:
                allowed &= _near_any(depressions, self.input_depressions_deg)[:, None]
            if self.target_depressions_deg is not None:
                allowed &= _near_any(depressions, self.target_depressions_deg)[None, :]
            result.append((np.asarray(members, dtype=np.int64), allowed))
        return result

    def set_epoch(self, epoch: int) -> None:
        """Redraws the pair list for an epoch (deterministic in ``(seed, epoch)``); call it before
        iterating."""
        rng = np.random.default_rng([self.seed, epoch])
        # Admissible inputs in record order, with their partner sets.
        candidates: dict[int, np.ndarray] = {}
        for members, allowed in self._groups:
            for row, i in enumerate(members):
                if allowed[row].any():
                    candidates[int(i)] = members[allowed[row]]
        inputs = np.array(sorted(candidates), dtype=np.int64)
        if self.num_pairs is not None:
            inputs = rng.choice(inputs, size=self.num_pairs, replace=True)
        else:
            inputs = np.repeat(inputs, self.pairs_per_chip)
        targets = np.array([candidates[int(i)][rng.integers(len(candidates[int(i)]))] for i in inputs])
        self.epoch = epoch
        self.pairs = np.stack([inputs, targets], axis=1).astype(np.int64)  # (N, 2) record indices

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def num_admissible_pairs(self) -> int:
        """How many distinct (input, target) pairs the records admit (``num_pairs`` draws with
        replacement)."""
        return sum(int(allowed.sum()) for _, allowed in self._groups)

    def pair_fields(self, index: int) -> dict[str, Any]:
        """Everything of item ``index`` except the images: the relative pose, the label and both poses."""
        return {name: value.item() for name, value in self.pair_fields_batch([index]).items()}

    @functools.cached_property
    def _record_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every record's azimuth, depression (float64) and label (int64), for :meth:`pair_fields_batch`."""
        azimuths = np.array([record.azimuth_deg for record in self.records], dtype=np.float64)
        depressions = np.array([record.depression_deg for record in self.records], dtype=np.float64)
        labels = np.array([self._label[record.target_class] for record in self.records], dtype=np.int64)
        return azimuths, depressions, labels

    def pair_fields_batch(self, indices: Sequence[int]) -> dict[str, torch.Tensor]:
        """:meth:`pair_fields` of several items at once, as ``default_collate`` would stack them (float64
        angles, int64 labels), each ``(len(indices),)``."""
        pairs = self.pairs[np.asarray(indices, dtype=np.int64)]
        azimuths, depressions, labels = self._record_arrays
        source, target = pairs[:, 0], pairs[:, 1]
        fields = {
            "d_az_deg": np.atleast_1d(wrap_azimuth_deg(azimuths[target] - azimuths[source])),
            "d_el_deg": depressions[target] - depressions[source],
            "label": labels[source],
            "input_azimuth_deg": azimuths[source],
            "target_azimuth_deg": azimuths[target],
            "input_depression_deg": depressions[source],
            "target_depression_deg": depressions[target],
        }
        return {name: torch.from_numpy(np.ascontiguousarray(value)) for name, value in fields.items()}

    @functools.cached_property
    def object_members(self) -> dict[tuple[str, str], list[int]]:
        """Record indices of each object's chips, at every depression."""
        members: dict[tuple[str, str], list[int]] = defaultdict(list)
        for i, record in enumerate(self.records):
            members[record.object_id].append(i)
        return members

    def target_at_input_depression(self, index: int, azimuth_tol_deg: float = 0.01) -> int | None:
        """The record of the same object at pair ``index``'s target azimuth (within ``azimuth_tol_deg``) and
        its input's depression; ``None`` where there is none or the target is already at that depression."""
        source, target = (self.records[i] for i in self.pairs[index])
        if abs(target.depression_deg - source.depression_deg) < _DEPRESSION_TOL_DEG:
            return None
        for i in self.object_members[source.object_id]:
            record = self.records[i]
            if (
                abs(record.depression_deg - source.depression_deg) < _DEPRESSION_TOL_DEG
                and abs(wrap_azimuth_deg(record.azimuth_deg - target.azimuth_deg)) <= azimuth_tol_deg
            ):
                return i
        return None

    def __getitem__(self, index: int) -> dict[str, Any]:
        source, target = (self.records[i] for i in self.pairs[index])
        input_magnitude = torch.from_numpy(load_chip(source.path, self.size, self.crop_size))[None]
        target_magnitude = torch.from_numpy(load_chip(target.path, self.size, self.crop_size))[None]
        item: dict[str, Any] = {
            "input": self.scaling.normalize(input_magnitude),
            "target": self.scaling.normalize(target_magnitude),
            **self.pair_fields(index),
        }
        if self.return_magnitude:
            item["input_magnitude"] = input_magnitude
            item["target_magnitude"] = target_magnitude
        return item


class MixedPairs(Dataset):
    """A task's training pairs with rehearsal pairs mixed in, so that a fine-tune keeps what its prior knows.

    Every task pair plus ``round(len(task) * fraction / (1 - fraction))`` rehearsal slots, so a shuffled batch
    holds a ``fraction`` share on average. Each epoch maps the slots to a fresh seeded permutation of the
    rehearsal pairs, so a resumed run sees the same pairs. Both datasets' items must have the same keys.

    Raises:
        ValueError: If ``fraction`` is outside [0, 1) or either dataset is empty.
    """

    def __init__(self, task: Dataset, rehearsal: Dataset, fraction: float, seed: int = 0) -> None:
        if not 0.0 <= fraction < 1.0:
            raise ValueError(f"rehearsal fraction must lie in [0, 1), got {fraction}")
        if len(task) == 0 or len(rehearsal) == 0:
            raise ValueError(
                f"task ({len(task)} pairs) and rehearsal ({len(rehearsal)} pairs) must be non-empty"
            )
        self.task, self.rehearsal, self.fraction, self.seed = task, rehearsal, fraction, seed
        self.num_rehearsal = round(len(task) * fraction / (1.0 - fraction))
        self._slots = self._permutation(0)

    def _permutation(self, epoch: int) -> torch.Tensor:
        state = np.random.SeedSequence([self.seed, epoch, 7]).generate_state(1)
        generator = torch.Generator().manual_seed(int(state[0]))
        return torch.randperm(len(self.rehearsal), generator=generator)

    def set_epoch(self, epoch: int) -> None:
        for dataset in (self.task, self.rehearsal):
            if hasattr(dataset, "set_epoch"):
                dataset.set_epoch(epoch)
        self._slots = self._permutation(epoch)

    def __len__(self) -> int:
        return len(self.task) + self.num_rehearsal

    def __getitem__(self, index: int) -> dict[str, Any]:
        if index < len(self.task):
            return self.task[index]
        slot = (index - len(self.task)) % len(self.rehearsal)
        return self.rehearsal[int(self._slots[slot])]


def subsample_objects(records: Sequence[ChipRecord], max_chips: int, seed: int = 0) -> list[ChipRecord]:
    """Whole objects, drawn in a seeded order while their chips fit in ``max_chips``, kept in record order (an
    object's chips stay together so its pairs survive).

    Raises:
        ValueError: If ``max_chips`` is below 1.
    """
    if max_chips < 1:
        raise ValueError(f"max_chips must be >= 1, got {max_chips}")
    if len(records) <= max_chips:
        return list(records)
    members: dict[tuple[str, str], list[int]] = defaultdict(list)
    for i, record in enumerate(records):
        members[record.object_id].append(i)
    objects = sorted(members)
    kept: list[int] = []
    for j in np.random.default_rng(seed).permutation(len(objects)):
        chips = members[objects[j]]
        if len(kept) + len(chips) <= max_chips:
            kept += chips
    return [records[i] for i in sorted(kept)]


def train_validation_pairs(
    data: str | os.PathLike | None,
    protocol: str,
    work_dir: str | os.PathLike,
    *,
    image_size: int,
    scaling: str = "unit",
    max_d_az_deg: float | None = None,
    num_validation_pairs: int = 4,
    seed: int = 0,
    same_depression: bool = True,
) -> tuple[ViewPairDataset, ViewPairDataset, DecibelScaling]:
    """Training and validation view pairs of a protocol's splits, and the dB scaling both use.

    Validation pairs come from the first split in which some chip has a partner view: ``val`` (seen classes
    at held-out azimuths), else ``test``, else ``train``.

    Args:
        data: Dataset folder with ``index.csv``; ``None`` simulates the built-in dataset into ``work_dir``.
        protocol: ``extended``, ``soc`` or ``ood-<CLASS>`` (:func:`prepare_splits`).
        scaling: ``"unit"``, ``"mstar_raw"`` or ``"fit"`` (fitted on the training split).
        num_validation_pairs: Fixed validation pairs drawn with seed ``seed + 1``.

    Returns:
        ``(train_pairs, validation_pairs, scaling)``.

    Raises:
        ValueError: For an unknown protocol, an empty training split or a split without pairs.
    """
    splits = prepare_splits(data, protocol, Path(work_dir), seed=seed)
    if not splits.get("train"):
        raise ValueError(f"data: protocol {protocol!r} gives an empty training split")
    decibel_scaling = DecibelScaling.from_choice(scaling, splits["train"])
    train = ViewPairDataset(
        splits["train"],
        size=image_size,
        scaling=decibel_scaling,
        max_d_az_deg=max_d_az_deg,
        seed=seed,
        same_depression=same_depression,
    )
    for name in ("val", "test", "train"):
        if not splits.get(name):
            continue
        try:
            validation = ViewPairDataset(
                splits[name],
                size=image_size,
                scaling=decibel_scaling,
                max_d_az_deg=max_d_az_deg,
                seed=seed + 1,
                num_pairs=num_validation_pairs,
                same_depression=same_depression,
            )
        except ValueError:  # no chip of this split has a partner view
            continue
        break
    return train, validation, decibel_scaling
