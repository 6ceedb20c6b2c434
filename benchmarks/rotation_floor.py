"""Is the input view rotated by d_az a better floor than the input view itself? (docs/results/learning.md)

    python benchmarks/rotation_floor.py --evaluators runs/quickstart/evaluators --data runs/quickstart/data \\
        --protocol ood-SPG --n 128 --out rotation_floor.json

Scores, on `train/evaluate.py`'s pairs and with its evaluators, the input copy and the input rotated in the
image plane by +d_az and by -d_az (bilinear, reflection padding), and writes the scores as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from sar_zero123.evaluators import load_evaluators

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `train`
from train import evaluate  # noqa: E402


def rotate(images: torch.Tensor, angle_deg: torch.Tensor) -> torch.Tensor:
    """Rotates each `(1, S, S)` image by its angle about the chip centre. Shape: `(N, 1, S, S)`."""
    theta = torch.deg2rad(angle_deg.float())
    cos, sin, zero = torch.cos(theta), torch.sin(theta), torch.zeros_like(theta)
    rows = [torch.stack([cos, -sin, zero], -1), torch.stack([sin, cos, zero], -1)]
    matrix = torch.stack(rows, 1)  # (N, 2, 3)
    grid = F.affine_grid(matrix, list(images.shape), align_corners=False)
    return F.grid_sample(images, grid, padding_mode="reflection", align_corners=False).clamp(0.0, 1.0)


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
    config = evaluate.EvaluateConfig(
        pipeline=["unused"], evaluators=args.evaluators, data=args.data, protocol=args.protocol, n=args.n,
        crop_size=min(64, args.image_size), work_dir=args.work_dir, output_dir=args.work_dir,
    )  # fmt: skip
    evaluators = load_evaluators(config.evaluators)
    rows = {}
    for group, pairs in evaluate.build_pair_sets(config, evaluators, args.image_size).items():
        candidates = {
            "input copy": pairs.inputs,
            "input rotated by +d_az": rotate(pairs.inputs, pairs.d_az_deg),
            "input rotated by -d_az": rotate(pairs.inputs, -pairs.d_az_deg),
        }
        for name, views in candidates.items():
            scores = evaluate.score(views, pairs, evaluators, config, "cpu")
            rows.setdefault(name, {})[group] = scores
            error, se = scores["azimuth_error_deg"], scores["azimuth_error_deg_se"]
            print(f"{group:7s} {name:24s} acc {scores['accuracy']:5.1f} %  az {error:5.1f} ± {se:.1f} deg")
    Path(args.out).write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
