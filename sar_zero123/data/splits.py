"""Train/validation/test protocols of the paper (MSTAR extended, MSTAR SOC, MSTAR-OOD).

* ``"extended"``: train = 17 deg depression, test = 15 deg, every serial.
* ``"soc"``: the same with BMP2 restricted to serial 9563 and T72 to serial 132 (on the simulator, whose
  classes differ, it equals ``extended``).
* ``"ood-<CLASS>"`` (paper: ``"ood-T72"``): test = every chip of the held-out class at every depression;
  of the other classes, chips whose absolute azimuth falls into one of 12 intervals [3k, 3k + 3),
  k drawn without replacement from 0..119 by ``numpy.random.default_rng(seed)``, form ``"val"``; the rest
  is ``"train"``.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sar_zero123.config.json_io import read_json
from sar_zero123.domain import INDEX_FILENAME

from .index import ChipRecord, load_index

__all__ = [
    "OOD_INTERVAL_WIDTH_DEG",
    "OOD_NUM_INTERVALS",
    "PROTOCOLS",
    "check_protocol",
    "SOC_SERIALS",
    "TEST_DEPRESSION_DEG",
    "TRAIN_DEPRESSION_DEG",
    "ood_validation_intervals",
    "prepare_splits",
    "split_records",
]

PROTOCOLS = ("extended", "soc", "ood-<CLASS>")
SIM_OPTIONS_FILENAME = "sim_options.json"
TRAIN_DEPRESSION_DEG = 17.0
TEST_DEPRESSION_DEG = 15.0
# Standard operating condition: one serial per class for the two classes with several in MSTAR.
SOC_SERIALS = {"BMP2": "9563", "T72": "132"}
OOD_NUM_INTERVALS = 12
OOD_INTERVAL_WIDTH_DEG = 3.0
# Depressions are nominal (15, 17, ...); tolerate float noise in indexes.
_DEPRESSION_TOL_DEG = 0.5


def ood_validation_intervals(
    seed: int = 0, num_intervals: int = OOD_NUM_INTERVALS, width_deg: float = OOD_INTERVAL_WIDTH_DEG
) -> list[tuple[float, float]]:
    """The azimuth intervals removed from training as the MSTAR-OOD validation split.

    Returns:
        Sorted half-open intervals ``(start_deg, end_deg)`` = [k * width, (k + 1) * width).

    Raises:
        ValueError: If 360 is not a multiple of ``width_deg`` or more intervals are asked than exist.
    """
    count = 360.0 / width_deg
    if width_deg <= 0 or not math.isclose(count, round(count)):
        raise ValueError(f"width_deg must divide 360, got {width_deg}")
    count = round(count)
    if not 0 < num_intervals <= count:
        raise ValueError(f"num_intervals must lie in [1, {count}], got {num_intervals}")
    starts = np.sort(np.random.default_rng(seed).choice(count, size=num_intervals, replace=False))
    return [(float(k * width_deg), float((k + 1) * width_deg)) for k in starts]


def _at_depression(record: ChipRecord, depression_deg: float) -> bool:
    return abs(record.depression_deg - depression_deg) < _DEPRESSION_TOL_DEG


def _warn_unassigned(
    records: Sequence[ChipRecord], splits: dict[str, list[ChipRecord]], protocol: str
) -> None:
    """Warn (with counts and example files) about chips at a depression no split of the protocol takes."""
    assigned = {id(r) for split in splits.values() for r in split}
    left = [r for r in records if id(r) not in assigned]
    if not left:
        return
    depressions = sorted({r.depression_deg for r in left})
    examples = ", ".join(str(r.path) for r in left[:3]) + (", ..." if len(left) > 3 else "")
    warnings.warn(
        f"protocol {protocol!r}: {len(left)} of {len(records)} chips are at depressions {depressions} deg, "
        f"in no split (train {TRAIN_DEPRESSION_DEG:g} +- {_DEPRESSION_TOL_DEG:g}, test "
        f"{TEST_DEPRESSION_DEG:g} +- {_DEPRESSION_TOL_DEG:g} deg); they are not used: {examples}",
        stacklevel=3,
    )


def _resolve_class(records: Sequence[ChipRecord], name: str) -> str:
    classes = sorted({record.target_class for record in records})
    if name in classes:
        return name
    matches = [c for c in classes if c.lower() == name.lower()]
    if len(matches) == 1:
        return matches[0]
    raise ValueError(f"protocol 'ood-{name}': unknown held-out class {name!r}; the records hold {classes}")


def check_protocol(protocol: str, field: str = "protocol") -> str:
    """Validates a protocol name before any data is read; returns it. Whether the held-out class exists is
    checked by :func:`split_records`, which sees the data.

    Raises:
        ValueError: Naming ``field``, if the name is not ``"extended"``, ``"soc"`` or ``"ood-<CLASS>"``.
    """
    if protocol in ("extended", "soc") or (protocol.startswith("ood-") and len(protocol) > len("ood-")):
        return protocol
    raise ValueError(f"{field}: unknown protocol {protocol!r}; expected one of {list(PROTOCOLS)}")


def split_records(records: Sequence[ChipRecord], protocol: str, seed: int = 0) -> dict[str, list[ChipRecord]]:
    """Splits chips by one of the paper's protocols (see the module docstring), deterministic in ``seed``.

    The ``ood-<CLASS>`` name matches the records' class case-insensitively when unambiguous.

    Returns:
        ``{"train": [...], "test": [...]}``, plus ``"val"`` for ``ood-*``; records keep their input order.

    Raises:
        ValueError: If the protocol is unknown, the held-out class does not occur, or a split is empty.
    """
    check_protocol(protocol)
    records = list(records)
    splits: dict[str, list[ChipRecord]]
    if protocol in ("extended", "soc"):
        if protocol == "soc":
            records = [r for r in records if SOC_SERIALS.get(r.target_class, r.serial) == r.serial]
        splits = {
            "train": [r for r in records if _at_depression(r, TRAIN_DEPRESSION_DEG)],
            "test": [r for r in records if _at_depression(r, TEST_DEPRESSION_DEG)],
        }
        _warn_unassigned(records, splits, protocol)
    else:
        held_out = _resolve_class(records, protocol[len("ood-") :])
        intervals = ood_validation_intervals(seed)

        def in_val(record: ChipRecord) -> bool:
            return any(start <= record.azimuth_deg < end for start, end in intervals)

        others = [r for r in records if r.target_class != held_out]
        splits = {
            "train": [r for r in others if not in_val(r)],
            "val": [r for r in others if in_val(r)],
            "test": [r for r in records if r.target_class == held_out],
        }
    for name, split in splits.items():
        if not split:
            depressions = sorted({r.depression_deg for r in records})
            raise ValueError(
                f"protocol {protocol!r} gives an empty '{name}' split "
                f"({len(records)} chips, depressions {depressions})"
            )
    return splits


def prepare_splits(
    data: str | Path | None, protocol: str, work_dir: str | Path, seed: int = 0, **sim_kwargs: Any
) -> dict[str, list[ChipRecord]]:
    """Loads a dataset (or simulates the built-in one) and splits it.

    With ``data=None`` the built-in dataset is simulated into ``work_dir / "sim_data"`` and reused while it
    was made with the same ``seed`` and ``sim_kwargs`` (``sar_zero123.sim.simulate_dataset``'s), recorded in
    ``sim_options.json``.

    Raises:
        ValueError: If ``sim_kwargs`` are given together with ``data``, or as :func:`split_records`.
    """
    if data is None:
        root = Path(work_dir) / "sim_data"
        options = json.loads(json.dumps({"seed": seed, **sim_kwargs}))  # tuples -> lists, as stored
        options_path = root / SIM_OPTIONS_FILENAME
        cached = (root / INDEX_FILENAME).is_file() and options_path.is_file()
        if not cached or read_json(options_path, what="the simulator options of the cached data") != options:
            # Imported here: the simulator is only needed for the built-in dataset.
            from sar_zero123.sim import simulate_dataset

            options_path.unlink(missing_ok=True)
            simulate_dataset(root, seed=seed, **sim_kwargs)
            options_path.write_text(json.dumps(options, indent=2, sort_keys=True) + "\n")
    else:
        if sim_kwargs:
            raise ValueError(f"simulator options {sorted(sim_kwargs)} only apply when data is None")
        root = Path(data)
    return split_records(load_index(root), protocol, seed=seed)
