"""The multi-view prior's training corpus: procedural vehicles at random azimuths and depressions.

``write_prior_corpus`` renders ``views_per_vehicle`` chips of each procedural vehicle at uniform random
azimuths and depressions from ``depression_range_deg`` (a share at MSTAR's 15 and 17 deg) into an image
folder with an MSTAR-style ``index.csv``; any two chips of one vehicle make a training pair. The last
``num_validation_vehicles`` get :data:`VALIDATION_CLASS`, for the ``ood-PROCVAL`` protocol.

Chips are float16 magnitudes in [0, 1] (half the disk; the dB error is negligible above the floor).
Resumable: chips are written atomically, finished ones kept, the index written last; a folder written
with other options is refused, naming each difference.
"""

from __future__ import annotations

import json
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from sar_zero123.domain import naming_write_errors
from sar_zero123.sim.dataset import write_index_atomic
from sar_zero123.sim.procedural import PROCEDURAL_CLASS, PROCEDURAL_SEED_KEY, make_procedural_target
from sar_zero123.sim.render import CLUTTER_DB, render_chip

__all__ = [
    "CORPUS_OPTIONS_FILE",
    "DEFAULT_CLUTTER_DB_SPREAD",
    "VALIDATION_CLASS",
    "check_corpus_options",
    "corpus_vehicle_seed",
    "corpus_views",
    "write_prior_corpus",
]

#: Class of the held-out validation vehicles (``--protocol ood-PROCVAL``).
VALIDATION_CLASS = "PROCVAL"
#: Options the corpus was written with, beside its index.
CORPUS_OPTIONS_FILE = "corpus.json"
_MSTAR_DEPRESSIONS_DEG = (15.0, 17.0)
_MAX_CORPUS_CHIPS = 400_000
#: Per-chip clutter level spread (+- dB) of a corpus, as in ``simulate_dataset``.
DEFAULT_CLUTTER_DB_SPREAD = 3.0


def corpus_views(
    seed: int, vehicle: int, views: int, depression_range_deg: tuple[float, float], mstar_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """Azimuths and depressions (deg) of one vehicle's views; deterministic in ``(seed, vehicle)``.

    Returns:
        ``(azimuth_deg, depression_deg)``, each ``(views,)`` float64, rounded to the index's 4 decimals.
    """
    rng = np.random.default_rng([PROCEDURAL_SEED_KEY, int(seed), int(vehicle), 2])
    azimuth = np.round(rng.uniform(0.0, 360.0, views), 4) % 360.0
    depression = rng.uniform(*depression_range_deg, views)
    at_mstar = rng.uniform(size=views) < mstar_fraction
    depression[at_mstar] = rng.choice(_MSTAR_DEPRESSIONS_DEG, size=int(at_mstar.sum()))
    return azimuth, np.round(depression, 4)


def corpus_vehicle_seed(serial: str) -> int:
    """The procedural seed of a corpus vehicle from its serial (``proc00042`` -> 42, as written here).

    Raises:
        ValueError: If ``serial`` is not a corpus vehicle's.
    """
    digits = serial[4:] if isinstance(serial, str) and serial.startswith("proc") else ""
    if len(digits) < 5 or not digits.isascii() or not digits.isdigit():
        raise ValueError(f"serial: expected a corpus vehicle's 'procNNNNN', got {serial!r}")
    return int(digits)


def _one_thread_each() -> None:
    """One BLAS/FFT thread per rendering process: N processes on N cores, not N x N threads."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _write_vehicle(args: tuple) -> list[tuple[str, ...]]:
    """Render and save one vehicle's chips (skipping finished ones); returns its index rows."""
    out, vehicle, class_name, seed, views, depression_range, mstar_fraction, size, spread = args
    target = make_procedural_target(vehicle)
    serial = f"proc{vehicle:05d}"  # corpus_vehicle_seed reads it back
    azimuths, depressions = corpus_views(seed, vehicle, views, depression_range, mstar_fraction)
    folder = Path(out) / "chips" / serial
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, (azimuth, depression) in enumerate(zip(azimuths, depressions)):
        rel = Path("chips") / serial / f"{serial}_{k:03d}.npy"
        if not (Path(out) / rel).is_file():
            rng = np.random.default_rng([PROCEDURAL_SEED_KEY, int(seed), int(vehicle), 3, k])
            clutter_db = CLUTTER_DB + rng.uniform(-spread, spread)
            chip = render_chip(target, float(azimuth), float(depression), size, rng, clutter_db=clutter_db)
            kept = "the chips written so far are kept (a re-run continues); the index is written last"
            with naming_write_errors(Path(out) / rel, kept):
                fd, tmp = tempfile.mkstemp(prefix=".chip-", suffix=".npy", dir=folder)
                try:
                    with os.fdopen(fd, "wb") as f:
                        np.save(f, chip.astype(np.float16))
                    os.replace(tmp, Path(out) / rel)
                except BaseException:
                    Path(tmp).unlink(missing_ok=True)
                    raise
        rows.append(
            (rel.as_posix(), class_name, "procedural_sim", serial, f"{depression:.4f}", f"{azimuth:.4f}",
             str(size), str(size))
        )  # fmt: skip
    return rows


def check_corpus_options(
    *,
    num_vehicles: int,
    views_per_vehicle: int,
    num_validation_vehicles: int,
    depression_range_deg: tuple[float, float],
    mstar_fraction: float,
    size: int,
    seed: int,
    clutter_db_spread: float,
    num_workers: int,
) -> dict:
    """The options of :func:`write_prior_corpus` checked, as its ``corpus.json`` records them.

    Raises:
        ValueError: Naming the first option out of range.
    """
    if int(num_vehicles) != num_vehicles or num_vehicles < 2:
        raise ValueError(f"num_vehicles: expected an integer >= 2, got {num_vehicles!r}")
    if int(views_per_vehicle) != views_per_vehicle or views_per_vehicle < 2:
        raise ValueError(f"views_per_vehicle: expected an integer >= 2, got {views_per_vehicle!r}")
    if not 0 < num_validation_vehicles < num_vehicles:
        raise ValueError(
            f"num_validation_vehicles: expected 1 .. num_vehicles - 1, got {num_validation_vehicles!r}"
        )
    low, high = (float(v) for v in depression_range_deg)
    if not 0.0 < low < high < 90.0:
        raise ValueError(f"depression_range_deg: expected 0 < low < high < 90, got {depression_range_deg!r}")
    if not 0.0 <= mstar_fraction <= 1.0:
        raise ValueError(f"mstar_fraction: expected a value in [0, 1], got {mstar_fraction!r}")
    if int(size) != size or size < 16:
        raise ValueError(f"size: expected an integer >= 16, got {size!r}")
    if num_vehicles * views_per_vehicle > _MAX_CORPUS_CHIPS:
        raise ValueError(
            f"num_vehicles x views_per_vehicle = {num_vehicles * views_per_vehicle} chips, more than "
            f"{_MAX_CORPUS_CHIPS}"
        )
    if int(num_workers) != num_workers or num_workers < 1:
        raise ValueError(f"num_workers: expected an integer >= 1, got {num_workers!r}")
    options = {
        "num_vehicles": int(num_vehicles),
        "views_per_vehicle": int(views_per_vehicle),
        "num_validation_vehicles": int(num_validation_vehicles),
        "depression_range_deg": [low, high],
        "mstar_fraction": float(mstar_fraction),
        "size": int(size),
        "seed": int(seed),
        "clutter_db_spread": float(clutter_db_spread),
        "format": "float16 magnitude .npy",
    }
    return options


def write_prior_corpus(
    out_dir: str | os.PathLike[str],
    *,
    num_vehicles: int = 2000,
    views_per_vehicle: int = 24,
    num_validation_vehicles: int = 32,
    depression_range_deg: tuple[float, float] = (10.0, 60.0),
    mstar_fraction: float = 0.25,
    size: int = 64,
    seed: int = 0,
    clutter_db_spread: float = DEFAULT_CLUTTER_DB_SPREAD,
    num_workers: int = 1,
    progress: bool = True,
) -> Path:
    """Render the prior's corpus into ``out_dir`` (or finish an interrupted one) and return it as a ``Path``.

    Vehicles are the procedural seeds ``0 .. num_vehicles - 1``; the named
    :data:`~sar_zero123.sim.TARGET_CLASSES` are never in it.

    Args:
        num_vehicles: Procedural vehicles, validation ones included.
        depression_range_deg: ``(low, high)`` of the uniform depression draw, within (0, 90).
        mstar_fraction: Share of the views put at 15 or 17 deg instead.
        size: Chip side in pixels.
        seed: Corpus seed (views, clutter, noise); the vehicles depend only on their own seed.
        clutter_db_spread: Per-chip clutter level spread (+- dB).

    Raises:
        ValueError: For an out-of-range option, a corpus over 400,000 chips, or a folder holding a corpus
            written with other options (naming each difference).
    """
    # 1. check inputs and the folder's record
    options = check_corpus_options(
        num_vehicles=num_vehicles, views_per_vehicle=views_per_vehicle,
        num_validation_vehicles=num_validation_vehicles, depression_range_deg=depression_range_deg,
        mstar_fraction=mstar_fraction, size=size, seed=seed, clutter_db_spread=clutter_db_spread,
        num_workers=num_workers,
    )  # fmt: skip
    low, high = options["depression_range_deg"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    options_path = out / CORPUS_OPTIONS_FILE
    if options_path.is_file():
        try:
            old = json.loads(options_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise ValueError(
                f"{options_path}: invalid JSON ({error}); expected the options the corpus was written with"
            ) from None
        changed = {k: (old.get(k), v) for k, v in options.items() if old.get(k) != v}
        if changed:
            listed = ", ".join(f"{k} {a!r} -> {b!r}" for k, (a, b) in sorted(changed.items()))
            raise ValueError(f"out_dir: {str(out)!r} holds a corpus written with other options ({listed})")
        if (out / "index.csv").is_file():
            return out
    elif any(out.iterdir()):
        raise ValueError(f"out_dir: {str(out)!r} is not empty and holds no {CORPUS_OPTIONS_FILE}")
    options_path.write_text(json.dumps(options, indent=2) + "\n")

    # 2. render every vehicle's chips
    first_validation = num_vehicles - num_validation_vehicles
    jobs = [
        (str(out), vehicle, VALIDATION_CLASS if vehicle >= first_validation else PROCEDURAL_CLASS, seed,
         int(views_per_vehicle), (low, high), float(mstar_fraction), int(size), float(clutter_db_spread))
        for vehicle in range(int(num_vehicles))
    ]  # fmt: skip
    rows: list[tuple[str, ...]] = []
    if num_workers == 1:
        results = map(_write_vehicle, jobs)
    else:
        executor = ProcessPoolExecutor(max_workers=int(num_workers), initializer=_one_thread_each)
        results = executor.map(_write_vehicle, jobs, chunksize=8)
    for done, vehicle_rows in enumerate(results, start=1):
        rows += vehicle_rows
        if progress and done % 100 == 0:
            print(f"corpus: {done}/{num_vehicles} vehicles", flush=True)
    if num_workers > 1:
        executor.shutdown()

    # 3. the index last, atomically
    write_index_atomic(out, rows)
    return out
