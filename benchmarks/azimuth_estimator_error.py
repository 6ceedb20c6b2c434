"""How well does a pipeline's AzimuthEstimator read the input's azimuth, per split? (learning.md, sec. 4b)

    python benchmarks/azimuth_estimator_error.py --pipeline RUN/pipeline --data DATA --protocol ood-TANK \\
        --out azimuth_estimator_error.json

For every chip of each split of the protocol (``ood-*``: train, val = held-out azimuth intervals of the
seen classes, test = the unseen class), the circular error between the estimator's azimuth and the
chip's true one: mean, median, and the share above 135 deg (front and back confused).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from sar_zero123.data import SCALING_FILE, DecibelScaling, load_chip, load_index, split_records
from sar_zero123.evaluation.metrics import azimuth_error_deg
from sar_zero123.model.conditioning import encode_condition_latents
from sar_zero123.model.orientation import azimuth_deg
from sar_zero123.model.pipeline import SARZero123Pipeline


def encode_chips(records, vae, scaling: DecibelScaling, size: int, batch_size: int = 256):
    """Condition latents of the chips of `records` and their true azimuths (deg, float64).

    Encoded in chunks of `batch_size`: all of MSTAR's T72 chips at once would need ~10 GB of activations.
    """
    chips = [torch.from_numpy(scaling.normalize(load_chip(r.path, size)))[None] for r in records]
    with torch.no_grad():
        chunks = torch.stack(chips).float().split(batch_size)
        latents = torch.cat([encode_condition_latents(vae, chunk) for chunk in chunks])
    return latents, torch.tensor([r.azimuth_deg for r in records], dtype=torch.float64)


def error_summary(estimate: torch.Tensor, true_deg: torch.Tensor) -> dict[str, float]:
    """Chips, mean and median circular error (deg) and the share above 135 deg of estimator outputs."""
    error = azimuth_error_deg(azimuth_deg(estimate), true_deg)
    return {
        "chips": len(error),
        "mean_deg": error.mean().item(),
        "median_deg": error.median().item(),
        "above_135_deg_percent": (error > 135).double().mean().item() * 100,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", required=True, help="a saved pipeline with an azimuth_estimator")
    parser.add_argument("--data", required=True)
    parser.add_argument("--protocol", default="ood-TANK", help="the default preset holds out TANK")
    parser.add_argument("--seed", type=int, default=0, help="seed of the protocol's validation intervals")
    parser.add_argument("--batch_size", type=int, default=256, help="chips encoded at once")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    pipe = SARZero123Pipeline.from_pretrained(args.pipeline)
    if pipe.azimuth_estimator is None:
        raise ValueError(f"pipeline: {args.pipeline} has no azimuth_estimator (trained without it)")
    scaling = DecibelScaling.from_dict(json.loads((Path(args.pipeline) / SCALING_FILE).read_text()))
    size = pipe.vae.config.sample_size
    result = {"pipeline": args.pipeline, "protocol": args.protocol, "splits": {}}
    for name, records in split_records(load_index(args.data), args.protocol, seed=args.seed).items():
        latents, true_deg = encode_chips(records, pipe.vae, scaling, size, args.batch_size)
        with torch.no_grad():
            estimate = pipe.azimuth_estimator(latents)
        result["splits"][name] = error_summary(estimate, true_deg)
        print(name, json.dumps(result["splits"][name]), flush=True)
    Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
