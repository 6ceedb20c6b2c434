"""How well the simulator proxy fits a chip with a vehicle in it, and a chip of clutter alone.

    python benchmarks/proxy_fit_floor.py --mstar ../shared/data/mstar --out proxy_fit_floor.json [--n 128]

For ``--n`` real MSTAR chips (seeded, every class, 15 and 17 deg): the 64 px centre crop at the native
0.2 m spacing (the vehicle, as the pipelines read MSTAR) and one 64 px corner crop of the same chip (its
clutter, no vehicle), each fitted by the bundled proxy prior's bank and learned shortlist at the chip's
header pose (:func:`sar_zero123.model.proxy.fit_scores`). Writes each group's score quantiles and, for each
candidate floor, the share of vehicle chips it would refuse and of clutter chips it would pass.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _common import script_parser

from sar_zero123 import SIM_PRIOR_IDENTITY, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling, load_magnitude
from sar_zero123.model.proxy import fit_scores

SIZE = 64


def crops(magnitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centre crop (the vehicle) and the top-left corner crop (clutter) of one chip, ``SIZE`` px each."""
    rows, cols = magnitude.shape
    top, left = (rows - SIZE) // 2, (cols - SIZE) // 2
    return magnitude[top : top + SIZE, left : left + SIZE], magnitude[:SIZE, :SIZE]


def main(argv: list[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--mstar", type=Path, required=True, help="MSTAR folder with index.csv")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--n", type=int, default=128, help="chips (each gives a vehicle and a clutter crop)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    folder = resolve_pretrained(SIM_PRIOR_IDENTITY)
    proxy = json.loads((folder / "model_index.json").read_text())["proxy"]
    scaling = DecibelScaling.from_file(folder / SCALING_FILE)
    with open(args.mstar / "index.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    chosen = np.random.default_rng(args.seed).choice(len(rows), size=args.n, replace=False)
    vehicles, clutter, poses = [], [], []
    for k in chosen:
        row = rows[int(k)]
        centre, corner = crops(load_magnitude(args.mstar / row["path"]))
        vehicles.append(scaling.normalize(centre))
        clutter.append(scaling.normalize(corner))
        poses.append((float(row["azimuth_deg"]), float(row["depression_deg"])))
    azimuth = torch.tensor([p[0] for p in poses])
    depression = torch.tensor([p[1] for p in poses])
    start = time.perf_counter()
    scores = {name: fit_scores(torch.from_numpy(np.stack(chips)[:, None].astype(np.float32)), azimuth,
                               depression, proxy)
              for name, chips in (("vehicle", vehicles), ("clutter", clutter))}  # fmt: skip
    seconds = time.perf_counter() - start
    quantiles = (0.0, 0.01, 0.05, 0.25, 0.5, 0.75, 0.95, 0.99, 1.0)
    floors = [round(float(f), 2) for f in np.arange(0.0, 0.61, 0.05)]
    result = {
        "command": "python benchmarks/proxy_fit_floor.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "device": f"{platform.machine()} CPU, {os.cpu_count()} cores, {torch.get_num_threads()} torch "
        f"threads, torch {torch.__version__}",
        "date": time.strftime("%Y-%m-%d"), "n": args.n, "seconds_per_fit": seconds / (2 * args.n),
        "quantiles": {
            name: dict(zip(map(str, quantiles), np.quantile(s, quantiles).round(4).tolist()))
            for name, s in scores.items()
        },  # fmt: skip
        "floors": [{"floor": f, "vehicle_refused": float(np.mean(scores["vehicle"] < f)),
                    "clutter_passed": float(np.mean(scores["clutter"] >= f))} for f in floors],  # fmt: skip
    }
    write_json_atomic(result, args.out)
    for line in result["floors"]:
        print(line)
    print(json.dumps(result["quantiles"], indent=1))
    return result


if __name__ == "__main__":
    main()
