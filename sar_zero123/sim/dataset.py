"""Write a simulated dataset as an image folder with an MSTAR-style ``index.csv``."""

from __future__ import annotations

import csv
import math
import os
import tempfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from sar_zero123.domain import INDEX_COLUMNS, INDEX_FILENAME, naming_write_errors
from sar_zero123.sim.render import CALIBRATION_AMPLITUDE, CLUTTER_DB, render_chip
from sar_zero123.sim.targets import TARGET_CLASSES, make_target

__all__ = [
    "check_simulation_options",
    "chip_generator",
    "simulate_dataset",
    "write_index_atomic",
]


def chip_generator(
    seed: int, class_name: str, instance: int, depression_deg: float, index: int
) -> np.random.Generator:
    """Independent random stream of one chip, seeded from all five arguments (hundredths of a degree of the
    depression), so a chip does not depend on which others are made."""
    key = [
        int(seed),
        zlib.crc32(class_name.encode()),
        int(instance),
        int(round(depression_deg * 100)),
        int(index),
    ]
    return np.random.default_rng(key)


#: Upper bound on the chips one call writes (MSTAR has about 15,000; 200,000 chips of 128 px are 13 GB).
MAX_SIM_CHIPS = 200_000
#: Largest chip side (pixels): MSTAR chips are 128-192 px; every command that sizes images stops at 1,024.
MAX_SIM_SIZE = 1024
#: Upper bound on the bytes of chips one call writes (float32 ``.npy``).
MAX_SIM_BYTES = 16 * 2**30


def check_simulation_options(
    classes: Sequence[str],
    instances: int,
    azimuth_step_deg: float,
    depressions_deg: Sequence[float],
    size: int,
    seed: int,
    azimuth_jitter_deg: float,
    normalization: str,
    clutter_db_spread: float,
) -> None:
    """Refuse options :func:`simulate_dataset` cannot honour, naming the option and what it expects.

    Raises:
        ValueError: For an unknown class, a count below 1, an angle out of range, more chips than
            ``MAX_SIM_CHIPS``, a size above ``MAX_SIM_SIZE`` or more bytes than ``MAX_SIM_BYTES``.
    """
    if not classes:
        raise ValueError(f"classes: none given; expected names from {list(TARGET_CLASSES)}")
    unknown = [c for c in classes if c not in TARGET_CLASSES]
    if unknown:
        raise ValueError(f"classes: {unknown} not among the simulator's classes {list(TARGET_CLASSES)}")
    if int(instances) != instances or instances < 1:
        raise ValueError(f"instances: expected an integer >= 1, got {instances!r}")
    if not 0.0 < azimuth_step_deg <= 360.0:
        raise ValueError(f"azimuth_step_deg: expected a value in (0, 360], got {azimuth_step_deg!r}")
    if not depressions_deg or any(not 0.0 < d < 90.0 for d in depressions_deg):
        raise ValueError(f"depressions_deg: expected values in (0, 90), got {list(depressions_deg)!r}")
    if len(set(depressions_deg)) != len(depressions_deg):
        raise ValueError(f"depressions_deg: duplicate values in {list(depressions_deg)!r}")
    if len(set(classes)) != len(classes):
        raise ValueError(f"classes: duplicate names in {list(classes)!r} (each would be written twice)")
    chips = len(classes) * int(instances) * len(depressions_deg) * math.ceil(360.0 / azimuth_step_deg - 1e-9)
    if chips > MAX_SIM_CHIPS:
        raise ValueError(
            f"azimuth_step_deg={azimuth_step_deg!r} with {len(classes)} classes x {instances} instances x "
            f"{len(depressions_deg)} depressions would write {chips:.3g} chips, more than {MAX_SIM_CHIPS}; "
            "use a larger azimuth step"
        )
    if int(size) != size or not 16 <= size <= MAX_SIM_SIZE:
        raise ValueError(f"size: expected an integer in [16, {MAX_SIM_SIZE}] (pixels), got {size!r}")
    gib = chips * size * size * 4 / 2**30  # float32 .npy chips
    if gib > MAX_SIM_BYTES / 2**30:
        raise ValueError(
            f"size: {chips} chips of {size} x {size} px would write {gib:.1f} GiB, "
            f"more than {MAX_SIM_BYTES / 2**30:.0f} GiB; use a smaller size or fewer chips"
        )
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    if not 0.0 <= azimuth_jitter_deg < azimuth_step_deg:
        raise ValueError(
            f"azimuth_jitter_deg: expected a value in [0, azimuth_step_deg), got {azimuth_jitter_deg!r}"
        )
    if normalization not in ("peak", "calibrated"):
        raise ValueError(f"normalization: expected 'peak' or 'calibrated', got {normalization!r}")
    if not 0.0 <= clutter_db_spread < 20.0:
        raise ValueError(f"clutter_db_spread: expected a value in [0, 20) dB, got {clutter_db_spread!r}")


def _format_deg(value: float) -> str:
    """``15.0 -> '15'``, ``15.5 -> '15.5'`` (folder names and index values)."""
    return f"{value:g}"


def simulate_dataset(
    out_dir: str | os.PathLike[str],
    classes: Sequence[str] | None = None,
    instances: int = 2,
    azimuth_step_deg: float = 5.0,
    depressions_deg: Sequence[float] = (15.0, 17.0),
    size: int = 128,
    seed: int = 0,
    *,
    azimuth_jitter_deg: float = 0.0,
    normalization: Literal["peak", "calibrated"] = "peak",
    calibration: float = CALIBRATION_AMPLITUDE,
    clutter_db_spread: float = 3.0,
) -> Path:
    """Simulate every (class, instance, depression, azimuth) chip and write an image folder; returns it.

    Layout: ``<out_dir>/chips/<dep>deg/<CLASS>/<CLASS>_<serial>_<k>.npy`` (float32 magnitude in [0, 1])
    and ``<out_dir>/index.csv`` (:data:`INDEX_COLUMNS`, paths relative to ``out_dir``). An existing index is
    removed first and the new one written last and atomically, so an interrupted run never leaves an index
    listing missing chips. Each chip has its own random stream: the same seed gives the same bytes, whatever
    subset of classes is simulated.

    Args:
        classes: Classes to simulate; None for all of :data:`TARGET_CLASSES`.
        instances: Instances (serials ``sim00``, ``sim01``, ...) per class.
        azimuth_step_deg: Azimuth grid step; azimuths ``k * step`` in [0, 360).
        azimuth_jitter_deg: If > 0, each azimuth moves by a seeded uniform offset in
            ``[-jitter/2, jitter/2)``.
        normalization: ``"peak"`` or ``"calibrated"`` (``sim.render.normalize_magnitude``).
        clutter_db_spread: Per-chip clutter level spread (+- dB), as the ground under real chips differs.

    Raises:
        ValueError: For an unknown class or an out-of-range argument (the message names it).
    """
    # 1. check inputs
    classes = list(TARGET_CLASSES) if classes is None else [str(c).upper() for c in classes]
    depressions = [float(d) for d in depressions_deg]
    check_simulation_options(
        classes,
        instances,
        azimuth_step_deg,
        depressions,
        size,
        seed,
        azimuth_jitter_deg,
        normalization,
        clutter_db_spread,
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    index_path = out / "index.csv"
    index_path.unlink(missing_ok=True)
    n_az = int(np.ceil(360.0 / azimuth_step_deg - 1e-9))

    # 2. render and save the chips
    rows: list[tuple[str, ...]] = []
    for class_name in classes:
        for instance in range(int(instances)):
            target = make_target(class_name, instance)
            for depression in depressions:
                folder = out / "chips" / f"{_format_deg(depression)}deg" / class_name
                folder.mkdir(parents=True, exist_ok=True)
                for k in range(n_az):
                    rng = chip_generator(seed, class_name, instance, depression, k)
                    azimuth = k * azimuth_step_deg
                    if azimuth_jitter_deg > 0:
                        azimuth += rng.uniform(-azimuth_jitter_deg / 2, azimuth_jitter_deg / 2)
                    # the index stores 4 decimals; render exactly the azimuth it lists
                    azimuth = round(azimuth % 360.0, 4) % 360.0
                    clutter_db = CLUTTER_DB + rng.uniform(-clutter_db_spread, clutter_db_spread)
                    chip = render_chip(
                        target,
                        azimuth,
                        depression,
                        size,
                        rng,
                        normalization=normalization,
                        calibration=calibration,
                        clutter_db=clutter_db,
                    )
                    rel = Path("chips") / f"{_format_deg(depression)}deg" / class_name
                    rel = rel / f"{class_name}_{target.serial}_{k:04d}.npy"
                    kept = "the index is written last: no reader sees this dataset (--resume redoes it)"
                    with naming_write_errors(out / rel, kept):
                        np.save(out / rel, chip)
                    rows.append(
                        (
                            rel.as_posix(),
                            class_name,
                            target.target_type,
                            target.serial,
                            _format_deg(depression),
                            f"{azimuth:.4f}",
                            str(size),
                            str(size),
                        )
                    )

    # 3. write the index last and atomically
    write_index_atomic(out, rows)
    return out


def write_index_atomic(out_dir: str | os.PathLike[str], rows: Sequence[Sequence[str]]) -> Path:
    """Write ``out_dir/index.csv`` (:data:`INDEX_COLUMNS`, then ``rows``) through a temporary file and
    ``os.replace``, so a reader never sees a half-written index; returns its path."""
    index_path = Path(out_dir) / INDEX_FILENAME
    with naming_write_errors(index_path, "the previous index, if any, is unchanged"):
        fd, tmp = tempfile.mkstemp(prefix=".index-", suffix=".csv.tmp", dir=out_dir)
        try:
            with os.fdopen(fd, "w", newline="") as f:
                writer = csv.writer(f, lineterminator="\n")
                writer.writerow(INDEX_COLUMNS)
                writer.writerows(rows)
            os.replace(tmp, index_path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return index_path
