"""Checks of the data layer on the real MSTAR chips: split counts and raw-vs-JPEG agreement.

    python -m sar_zero123.data.mstar_check --data ../shared/data/mstar --output docs/results/data/data.json

The report holds the chip counts of every protocol beside the paper's, a raw MSTAR chip against its JPEG
copy (the JPEGs map each chip's magnitude linearly to 0-255, so ``raw / raw.max()`` and ``pixel / 255``
agree up to compression error), the raw-folder index, the global dB bounds, and view-pair and reading costs.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from sar_zero123.data.datasets import ChipDataset
from sar_zero123.data.images import load_magnitude
from sar_zero123.data.index import load_index
from sar_zero123.data.mstar_raw import read_mstar_raw
from sar_zero123.data.scaling import DecibelScaling
from sar_zero123.data.splits import ood_validation_intervals, split_records
from sar_zero123.data.view_pairs import ViewPairDataset, wrap_azimuth_deg
from sar_zero123.domain import to_decibels

__all__ = [
    "JPEG_CHIP",
    "PAPER_COUNTS",
    "RAW_CHIP",
    "check_datasets",
    "check_mstar_data",
    "check_raw_folder",
    "check_raw_vs_jpeg",
    "check_scaling",
    "check_splits",
    "main",
]

#: The paper's chip counts per protocol and split.
PAPER_COUNTS = {
    "extended": {"train": 6059, "test": 5392},
    "soc": {"train": 2747, "test": 2425},
    "ood-T72": {"train": 5003, "test": 5850},
}
#: A raw MSTAR file of the folder and its JPEG copy, compared by :func:`check_raw_vs_jpeg`.
RAW_CHIP = "raw/HB03787.002"
JPEG_CHIP = "chips/17deg/BMP2/HB03787.002.jpeg"


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two images."""
    return float(np.corrcoef(a.ravel().astype(np.float64), b.ravel().astype(np.float64))[0, 1])


def check_splits(data: Path) -> dict[str, Any]:
    """Chip counts of ``extended``, ``soc`` and ``ood-T72`` (seeds 0-4) beside the paper's, the seed-0
    validation intervals and the seconds :func:`load_index` took."""
    start = time.perf_counter()
    records = load_index(data)
    seconds = time.perf_counter() - start
    report: dict[str, Any] = {
        "num_chips": len(records),
        "load_index_seconds": round(seconds, 3),
        "protocols": {},
    }
    for protocol in ("extended", "soc"):
        splits = split_records(records, protocol)
        report["protocols"][protocol] = {name: len(split) for name, split in splits.items()}
    for seed in range(5):
        splits = split_records(records, "ood-T72", seed=seed)
        report["protocols"][f"ood-T72 (seed {seed})"] = {name: len(split) for name, split in splits.items()}
    report["ood_intervals_seed0_deg"] = ood_validation_intervals(seed=0)
    report["paper"] = PAPER_COUNTS
    return report


def check_raw_vs_jpeg(data: Path) -> dict[str, Any]:
    """:data:`RAW_CHIP` read raw against its JPEG copy :data:`JPEG_CHIP`: the raw header, correlations
    (magnitude, 3x3 mean, normalised dB), the linear fit of JPEG on raw and the RMS difference."""
    chip = read_mstar_raw(data / RAW_CHIP)
    jpeg = load_magnitude(data / JPEG_CHIP)
    raw = chip.magnitude / chip.magnitude.max()  # per-chip linear normalisation, as the JPEG export did
    slope, intercept = np.polyfit(raw.ravel(), jpeg.ravel(), 1)
    scaling = DecibelScaling.for_unit_magnitude()
    return {
        "raw": {
            "shape": list(chip.magnitude.shape),
            "target_class": chip.target_class,
            "serial": chip.serial,
            "azimuth_deg": chip.azimuth_deg,
            "depression_deg": chip.depression_deg,
            "measured_depression_deg": float(chip.header["MeasuredDepression"]),
            "magnitude_max": float(chip.magnitude.max()),
            "magnitude_max_db": float(to_decibels(np.float64(chip.magnitude.max()))),
            "phase_range_rad": [float(chip.phase.min()), float(chip.phase.max())],
        },
        "jpeg_shape": list(jpeg.shape),
        "correlation_normalised_magnitude": _correlation(raw, jpeg),
        "correlation_after_3x3_mean": _correlation(uniform_filter(raw, 3), uniform_filter(jpeg, 3)),
        "correlation_normalised_db": _correlation(scaling.normalize(raw), scaling.normalize(jpeg)),
        "linear_fit_jpeg_vs_raw": {"slope": float(slope), "intercept": float(intercept)},
        "rms_difference": float(np.sqrt(np.mean((jpeg - raw) ** 2))),
        "argmax_raw": [int(i) for i in np.unravel_index(raw.argmax(), raw.shape)],
        "argmax_jpeg": [int(i) for i in np.unravel_index(jpeg.argmax(), jpeg.shape)],
    }


def check_raw_folder(data: Path) -> dict[str, Any]:
    """The records :func:`load_index` reads from ``data/raw`` in place (read-only: scanned, not cached) and in
    a writable copy (cached as ``index.csv``), which must agree."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        in_place = load_index(data / "raw")
    with tempfile.TemporaryDirectory() as scratch:
        for path in (data / "raw").iterdir():
            shutil.copy(path, scratch)
        cached = load_index(scratch)
        index_written = (Path(scratch) / "index.csv").is_file()
    return {
        "records": [
            {
                "file": r.path.name,
                "class": r.target_class,
                "serial": r.serial,
                "azimuth_deg": r.azimuth_deg,
                "depression_deg": r.depression_deg,
                "height": r.height,
                "width": r.width,
            }
            for r in in_place
        ],
        "read_only_warning": [str(w.message) for w in caught],
        "copy_index_written": index_written,
        "copy_records_equal": [(r.target_class, r.serial, r.azimuth_deg) for r in cached]
        == [(r.target_class, r.serial, r.azimuth_deg) for r in in_place],
    }


def check_scaling(data: Path) -> dict[str, Any]:
    """The dB bounds :meth:`DecibelScaling.fit` finds on the extended training chips, the unit default, the
    time."""
    train = split_records(load_index(data), "extended")["train"]
    start = time.perf_counter()
    fitted = DecibelScaling.fit(train)
    return {
        "extended_train_fit": fitted.to_dict(),
        "unit_magnitude_default": DecibelScaling.for_unit_magnitude().to_dict(),
        "fit_seconds": round(time.perf_counter() - start, 2),
    }


def check_datasets(data: Path) -> dict[str, Any]:
    """The view pairs of the extended training chips (count, build seconds, ``d_az`` statistics) and the
    milliseconds :class:`ChipDataset` takes per 128 px item."""
    train = split_records(load_index(data), "extended")["train"]
    start = time.perf_counter()
    pairs = ViewPairDataset(train, size=128, max_d_az_deg=None, same_depression=True, seed=0)
    build_seconds = time.perf_counter() - start
    d_az = np.array([wrap_azimuth_deg(train[j].azimuth_deg - train[i].azimuth_deg) for i, j in pairs.pairs])
    chips = ChipDataset(train, size=128)
    start = time.perf_counter()
    for index in range(0, len(chips), len(chips) // 256):
        chips[index]
    per_item_ms = 1000 * (time.perf_counter() - start) / len(range(0, len(chips), len(chips) // 256))
    return {
        "view_pairs_extended_train": {
            "pairs": len(pairs),
            "build_seconds": round(build_seconds, 3),
            "abs_d_az_deg_mean": float(np.abs(d_az).mean()),
            "d_az_range_deg": [float(d_az.min()), float(d_az.max())],
        },
        "chip_dataset_item_ms": round(per_item_ms, 2),
    }


def check_mstar_data(data: str | Path) -> dict[str, Any]:
    """Every check of this module on one MSTAR folder (an ``index.csv`` of JPEG chips beside ``raw/``).

    Returns:
        ``{"data", "splits", "raw_vs_jpeg", "raw_folder_index", "scaling", "datasets"}``.

    Raises:
        FileNotFoundError: If the folder has no ``index.csv``.
    """
    data = Path(data)
    if not (data / "index.csv").is_file():
        raise FileNotFoundError(f"no MSTAR index at {data / 'index.csv'}; pass --data")
    return {
        "data": str(data.resolve()),
        "splits": check_splits(data),
        "raw_vs_jpeg": check_raw_vs_jpeg(data),
        "raw_folder_index": check_raw_folder(data),
        "scaling": check_scaling(data),
        "datasets": check_datasets(data),
    }


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``python -m sar_zero123.data.mstar_check``: prints the report and writes it to ``--output``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/mstar"), help="MSTAR folder")
    parser.add_argument(
        "--output", type=Path, default=Path("docs/results/data/data.json"), help="JSON report"
    )
    args = parser.parse_args(argv)
    report = check_mstar_data(args.data)
    text = json.dumps(report, indent=2)
    print(text)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text + "\n")
    return report


if __name__ == "__main__":
    main()
