"""Simulator throughput on one CPU core: chips per second of ``render_chip`` and ``simulate_dataset``.

    python benchmarks/bench_sim.py --size 128 --chips-per-class 72 --output bench_sim.json

BLAS/OpenMP threads are pinned to 1 before numpy is imported, so the figure is per core.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from _common import script_parser  # noqa: E402

from sar_zero123.sim import TARGET_CLASSES, make_target, render_chip, simulate_dataset  # noqa: E402


def _chip_statistics(magnitude: np.ndarray) -> dict[str, float]:
    """Peak-normalised dB statistics of one chip's centre 128 x 128."""
    h, w = magnitude.shape
    top, left = max(0, (h - 128) // 2), max(0, (w - 128) // 2)
    m = magnitude[top : top + 128, left : left + 128].astype(np.float64)
    db = 20 * np.log10(m / m.max() + 1e-3)
    return {
        "median_db": float(np.median(db)),  # clutter level below the peak
        "p99_db": float(np.percentile(db, 99)),
        "bright_fraction": float(np.mean(db > -20.0)),  # target extent
        "dark_fraction": float(np.mean(db < np.median(db) - 10.0)),  # shadow and dark speckle
    }


def compare_statistics(real_root: str, depression_deg: float, per_class: int = 24) -> dict:
    """Mean chip statistics of real MSTAR chips (every class) and simulated chips (every class)."""
    import csv
    from pathlib import Path

    from PIL import Image

    root = Path(real_root)
    with open(root / "index.csv", newline="") as f:
        records = [r for r in csv.DictReader(f) if abs(float(r["depression_deg"]) - depression_deg) < 0.5]
    real = []
    for class_name in sorted({r["target_class"] for r in records}):
        recs = sorted((r for r in records if r["target_class"] == class_name), key=lambda r: r["path"])
        for r in recs[:: max(1, len(recs) // per_class)][:per_class]:
            pixels = np.asarray(Image.open(root / r["path"]).convert("L"), dtype=np.float64) / 255.0
            real.append(_chip_statistics(pixels))
    sim = []
    rng = np.random.default_rng(0)
    for class_name in TARGET_CLASSES:
        target = make_target(class_name, 0)
        for az in np.arange(per_class) * 360.0 / per_class:
            sim.append(_chip_statistics(render_chip(target, float(az), depression_deg, 128, rng)))

    def mean(rows: list[dict[str, float]]) -> dict[str, float]:
        return {k: round(float(np.mean([r[k] for r in rows])), 4) for k in rows[0]}

    return {"real": mean(real), "sim": mean(sim), "real_chips": len(real), "sim_chips": len(sim)}


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark, print and write a JSON summary; returns it."""
    parser = script_parser(__doc__)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--chips-per-class", type=int, default=72, help="azimuths per class (evenly spaced)")
    parser.add_argument("--depression", type=float, default=17.0)
    parser.add_argument("--repeats", type=int, default=3, help="timed passes; the fastest pass is reported")
    parser.add_argument("--output", default="bench_sim.json")
    parser.add_argument("--real-root", default=None,
                        help="MSTAR image folder: also compare image statistics of sim and real chips")
    args = parser.parse_args(argv)

    # 1. target construction (once per class and instance in a dataset)
    start = time.perf_counter()
    targets = [make_target(c, 0) for c in TARGET_CLASSES]
    make_target_ms = (time.perf_counter() - start) * 1000 / len(targets)

    # 2. rendering: best of `repeats` passes over all classes and azimuths
    azimuths = np.arange(args.chips_per_class) * 360.0 / args.chips_per_class
    render_chip(targets[0], 0.0, args.depression, args.size, np.random.default_rng(0))  # warm-up
    # wall time per chip, and process CPU time per pass (the machine may be shared: CPU time is
    # what one core spends, wall time includes waiting for it)
    per_chip: list[float] = []
    pass_times, pass_cpu = [], []
    for rep in range(args.repeats):
        rng = np.random.default_rng(rep)
        times = []
        cpu0 = time.process_time()
        for target in targets:
            for az in azimuths:
                t0 = time.perf_counter()
                render_chip(target, float(az), args.depression, args.size, rng)
                times.append(time.perf_counter() - t0)
        pass_cpu.append(time.process_time() - cpu0)
        pass_times.append(sum(times))
        if sum(times) <= min(pass_times):
            per_chip = times
    per_chip_ms = np.array(per_chip) * 1000
    cpu_ms = min(pass_cpu) * 1000 / len(per_chip)

    # 3. the dataset writer end to end (rendering + .npy files + index), one class
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        simulate_dataset(tmp, classes=[TARGET_CLASSES[0]], instances=1, azimuth_step_deg=5.0,
                         depressions_deg=(17.0,), size=args.size)
        dataset_s = time.perf_counter() - t0
    n_dataset = int(np.ceil(360 / 5.0))

    result = {
        "size": args.size, "chips_timed": int(per_chip_ms.size),
        "render_ms_mean": round(float(per_chip_ms.mean()), 3),
        "render_ms_median": round(float(np.median(per_chip_ms)), 3),
        "render_ms_p95": round(float(np.percentile(per_chip_ms, 95)), 3),
        "render_chips_per_s": round(float(1000 / per_chip_ms.mean()), 1),
        "render_cpu_ms_mean": round(cpu_ms, 3), "render_chips_per_cpu_s": round(1000 / cpu_ms, 1),
        "make_target_ms": round(make_target_ms, 2),
        "simulate_dataset_chips_per_s": round(n_dataset / dataset_s, 1),
        "threads": os.environ["OMP_NUM_THREADS"], "numpy": np.__version__,
        "python": platform.python_version(), "machine": platform.machine(), "cpu_count": os.cpu_count(),
    }  # fmt: skip
    if args.real_root is not None:
        result["image_statistics"] = compare_statistics(args.real_root, args.depression)
    print(json.dumps(result, indent=2))
    with open(args.output, "w") as f:
        json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
