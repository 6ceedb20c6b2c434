"""Is the input view rotated by d_az a better floor than the input itself? (docs/results/history/learning.md)

    python benchmarks/rotation_floor.py --evaluators runs/quickstart/evaluators --data runs/quickstart/data \\
        --protocol ood-SPG --n 128 --out rotation_floor.json

Scores, on the evaluate stage's pairs (`sar_zero123.evaluation.protocol.build_pair_sets`) and with its
evaluators, the input copy and the input rotated in the image plane by +d_az and by -d_az (bilinear,
reflection padding), and writes the scores as JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from sar_zero123.evaluation.evaluators import load_evaluators
from sar_zero123.evaluation.protocol import build_pair_sets, score
from sar_zero123.model.conditioning import embed_pose, rotate_condition_latents


def rotate(images: torch.Tensor, angle_deg: torch.Tensor) -> torch.Tensor:
    """Rotates each `(1, S, S)` image by its angle about the chip centre, as the spatial pose input turns
    latents (`rotate_condition_latents`, sign +1). Shape: `(N, 1, S, S)`."""
    pose = embed_pose(angle_deg.double(), 0.0)  # (N, 1, 4): only sin and cos of the angle are read
    return rotate_condition_latents(images, pose, rotation_sign=1).clamp(0.0, 1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--evaluators", required=True)
    parser.add_argument("--data", default=None)
    parser.add_argument("--protocol", default="extended")
    parser.add_argument("--n", type=int, default=128)
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--work_dir", default="rotation_floor_cache")
    parser.add_argument("--out", default="rotation_floor.json")
    args = parser.parse_args()
    evaluators = load_evaluators(args.evaluators)
    pair_sets = build_pair_sets(
        evaluators, data=args.data, protocol=args.protocol, n=args.n, image_size=args.image_size,
        work_dir=args.work_dir, evaluators_name=args.evaluators,
    )  # fmt: skip
    # the evaluate stage's scoring settings (its defaults: 256 px before the paper's crop, 32 views a call)
    scoring = {"crop_size": min(64, args.image_size), "paper_scoring_size": 256, "batch_size": 32,
               "device": "cpu"}  # fmt: skip
    rows = {}
    for group, pairs in pair_sets.items():
        candidates = {
            "input copy": pairs.inputs,
            "input rotated by +d_az": rotate(pairs.inputs, pairs.d_az_deg),
            "input rotated by -d_az": rotate(pairs.inputs, -pairs.d_az_deg),
        }
        for name, views in candidates.items():
            scores = score(views, pairs, evaluators, **scoring)
            rows.setdefault(name, {})[group] = scores
            error, se = scores["azimuth_error_deg"], scores["azimuth_error_deg_se"]
            print(f"{group:7s} {name:24s} acc {scores['accuracy']:5.1f} %  az {error:5.1f} ± {se:.1f} deg")
    Path(args.out).write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
