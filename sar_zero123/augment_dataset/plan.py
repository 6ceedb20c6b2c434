"""The plan of an augmentation: which chips, which views of each, whether the pipeline was trained for
them, and each view's own random stream.

:func:`select_records` picks the chips, :func:`plan_views` lists every requested view of each (its pose
and its file), :func:`check_trained_ranges` refuses, before any generation, requests the pipeline would
refuse mid-run, and :func:`view_generator` seeds one view from its place in the plan alone, so its noise
does not depend on which other views share its batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sar_zero123.data import ChipRecord, wrap_azimuth_deg

__all__ = ["ViewRequest", "check_trained_ranges", "plan_views", "select_records", "view_generator"]

# The pipeline's own tolerance for the trained ranges.
_RANGE_TOL_DEG = 1e-6


@dataclass(frozen=True)
class ViewRequest:
    """One view to generate: a source chip, the pose change, and where the view goes.

    Attributes:
        row_index: The chip's position in the source index (0 = first chip).
        request_index: The request's position in the chip's list of requests.
        record: The source chip.
        d_az_deg: Azimuth change (target - input), degrees.
        d_el_deg: Depression change (target - input), degrees.
        azimuth_deg: The view's azimuth in [0, 360).
        depression_deg: The view's depression, ``record.depression_deg + d_el_deg``.
        path: The view's file, relative to the output folder.
    """

    row_index: int
    request_index: int
    record: ChipRecord
    d_az_deg: float
    d_el_deg: float
    azimuth_deg: float
    depression_deg: float
    path: Path


def select_records(
    records: Sequence[ChipRecord],
    classes: Sequence[str] = (),
    depressions_deg: Sequence[float] = (),
    max_chips_per_class: int | None = None,
) -> list[tuple[int, ChipRecord]]:
    """The chips to augment, with their positions in the source index.

    Args:
        records: The source index (:func:`~sar_zero123.data.load_index`).
        classes: Keep only these target classes; empty keeps all.
        depressions_deg: Keep only chips within 0.01 degrees of one of these depressions; empty keeps all.
        max_chips_per_class: Keep at most this many chips of each class, evenly spaced over the class's
            chips in index order (so they spread over the azimuths of an index sorted by azimuth).

    Returns:
        ``(row_index, record)`` pairs in index order.

    Raises:
        ValueError: naming ``classes`` for a class the index does not list, or ``depressions_deg`` /
            the selection when nothing is left.
    """
    unknown = sorted(set(classes) - {r.target_class for r in records})
    if unknown:
        listed = sorted({r.target_class for r in records})
        raise ValueError(f"classes: {unknown} not in the dataset, which lists {listed}")
    selected = [
        (row, record)
        for row, record in enumerate(records)
        if (not classes or record.target_class in classes)
        and (not depressions_deg or any(abs(record.depression_deg - d) < 0.01 for d in depressions_deg))
    ]
    if not selected:
        raise ValueError(f"depressions_deg: no chip of the selected classes at {list(depressions_deg)} deg")
    if max_chips_per_class is None:
        return selected
    keep = set()
    for target_class in {record.target_class for _, record in selected}:
        rows = [row for row, record in selected if record.target_class == target_class]
        picks = np.unique(np.linspace(0, len(rows) - 1, min(max_chips_per_class, len(rows))).round())
        keep.update(rows[int(i)] for i in picks)
    return [(row, record) for row, record in selected if row in keep]


def plan_views(
    selected: Sequence[tuple[int, ChipRecord]],
    d_az: Sequence[float] = (),
    target_azimuths_deg: Sequence[float] = (),
    d_el: Sequence[float] = (0.0,),
) -> list[ViewRequest]:
    """Every requested view of every selected chip: azimuth requests x ``d_el``, in that order.

    Args:
        selected: ``(row_index, record)`` pairs (:func:`select_records`).
        d_az: Azimuth changes in degrees; or
        target_azimuths_deg: absolute target azimuths in degrees (``d_az = wrap(target - input)`` in
            (-180, 180], :func:`~sar_zero123.data.wrap_azimuth_deg`).
        d_el: Depression changes in degrees.

    Returns:
        The views, chip after chip; request ``i * len(d_el) + j`` is azimuth request ``i`` with ``d_el[j]``.

    Raises:
        ValueError: naming ``d_el`` when a target depression leaves (0, 90) degrees.
    """
    views = []
    for row, record in selected:
        if target_azimuths_deg:
            azimuths = [(wrap_azimuth_deg(t - record.azimuth_deg), float(t)) for t in target_azimuths_deg]
        else:
            # 6 decimals keep the index readable (17.299999999999997); rounding up to 360 wraps to 0
            azimuths = [(float(a), round((record.azimuth_deg + a) % 360.0, 6) % 360.0) for a in d_az]
        requests = [(a, target, e) for a, target in azimuths for e in d_el]
        for request, (d_az_deg, azimuth_deg, d_el_deg) in enumerate(requests):
            depression_deg = round(record.depression_deg + float(d_el_deg), 6)
            if not 0.0 < depression_deg < 90.0:
                raise ValueError(
                    f"d_el: {record.path} at {record.depression_deg:g} deg + d_el {d_el_deg:g} leaves (0, 90)"
                )
            name = f"{record.path.stem}_r{row:06d}_v{request:03d}.npy"
            views.append(
                ViewRequest(
                    row_index=row,
                    request_index=request,
                    record=record,
                    d_az_deg=float(d_az_deg),
                    d_el_deg=float(d_el_deg),
                    azimuth_deg=float(azimuth_deg),
                    depression_deg=depression_deg,
                    path=Path("views") / record.target_class / name,
                )
            )
    return views


def check_trained_ranges(
    pose_config: Any, d_el: Sequence[float], input_depressions_deg: Sequence[float]
) -> None:
    """Refuse, before any generation, requests the pipeline would refuse mid-run.

    Args:
        pose_config: ``pipe.pose_projection.config`` (``trained_d_el_deg``, ``trained_depression_deg``,
            ``input_depression``; a range of ``None`` is unknown and not checked).
        d_el: The depression changes requested.
        input_depressions_deg: The depressions of the selected chips.

    Raises:
        ValueError: naming ``d_el`` or ``depressions_deg`` and the pipeline's field, for a change outside
            ``trained_d_el_deg``, or (for a pipeline whose pose carries the input's depression, the ones
            the pipeline checks) an input or target depression outside ``trained_depression_deg``.
    """
    trained_d_el = getattr(pose_config, "trained_d_el_deg", None)
    if trained_d_el is not None:
        low, high = float(trained_d_el[0]), float(trained_d_el[1])
        outside = sorted({v for v in d_el if not low - _RANGE_TOL_DEG <= v <= high + _RANGE_TOL_DEG})
        if outside:
            raise ValueError(
                f"d_el: {outside} deg lie outside the range the pipeline was trained on, [{low:g}, {high:g}] "
                "deg (pose_projection.config.trained_d_el_deg)"
            )
    trained_depression = getattr(pose_config, "trained_depression_deg", None)
    if trained_depression is None or not getattr(pose_config, "input_depression", False):
        return
    low, high = float(trained_depression[0]), float(trained_depression[1])
    inputs = sorted(set(input_depressions_deg))
    targets = sorted({i + e for i in inputs for e in d_el})
    for name, values in (("depressions_deg", inputs), ("d_el", targets)):
        outside = [v for v in values if not low - _RANGE_TOL_DEG <= v <= high + _RANGE_TOL_DEG]
        if outside:
            what = "input depressions" if name == "depressions_deg" else "target depressions (input + d_el)"
            raise ValueError(
                f"{name}: {what} {outside} deg lie outside the range the pipeline was trained on, "
                f"[{low:g}, {high:g}] deg (pose_projection.config.trained_depression_deg)"
            )


def view_generator(seed: int, row_index: int, request_index: int) -> torch.Generator:
    """CPU generator of one view; a pure function of its arguments, whatever else the batch holds.

    Args:
        seed: The run's seed.
        row_index: The source chip's position in the source index.
        request_index: The request's position in the chip's requests.

    Returns:
        A seeded ``torch.Generator``.
    """
    key = [seed, row_index, request_index, 0]  # the trailing 0: the noise stream, as views were always drawn
    state = np.random.SeedSequence(key).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))
