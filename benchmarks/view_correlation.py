"""How predictable is a target view from the input? Correlation of two views of one object against |d_az|.

    python benchmarks/view_correlation.py --data runs/quickstart/data --target_class TANK --depression 17 \\
        --image_size 64 --out view_correlation.json

For every pair of chips of one class at one depression: the Pearson correlation of the normalised dB
images, at full resolution and after 4x4 average pooling (the layout a 16x16 latent carries), averaged in
|d_az| bins. A model that follows the pose must beat the input copy, whose similarity to the target is
this curve.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sar_zero123.data import ViewPairDataset, load_index
from sar_zero123.training.latent_cache import load_chip_images

BINS_DEG = ((4, 6), (9, 11), (14, 16), (29, 31), (44, 46), (89, 91), (134, 136), (179, 181))


def correlation_matrix(images: torch.Tensor) -> np.ndarray:
    """Pearson correlation between every two images. Shape: `(N, 1, S, S)` -> `(N, N)`."""
    flat = images.reshape(images.shape[0], -1).double().numpy()
    flat = (flat - flat.mean(1, keepdims=True)) / flat.std(1, keepdims=True)
    return flat @ flat.T / flat.shape[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--target_class", required=True)
    parser.add_argument("--depression", type=float, required=True)
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--out", default="view_correlation.json")
    args = parser.parse_args()
    records = [
        r
        for r in load_index(args.data)
        if r.target_class == args.target_class and abs(r.depression_deg - args.depression) < 1e-6
    ]
    if len(records) < 2:
        raise ValueError(f"data: fewer than two chips of {args.target_class!r} at {args.depression} deg")
    images = load_chip_images(ViewPairDataset(records, size=args.image_size))
    azimuth = np.array([r.azimuth_deg for r in records])
    d_az = np.abs((azimuth[None] - azimuth[:, None] + 180.0) % 360.0 - 180.0)
    matrices = {"full": correlation_matrix(images), "pooled4": correlation_matrix(F.avg_pool2d(images, 4))}
    rows = []
    for low, high in BINS_DEG:
        mask = (d_az >= low) & (d_az <= high)
        if mask.any():
            row = {"d_az_low": low, "d_az_high": high, "pairs": int(mask.sum())}
            row.update({name: float(matrix[mask].mean()) for name, matrix in matrices.items()})
            rows.append(row)
            print(f"|d_az| {low:3d}-{high:3d} deg: corr {row['full']:.3f}, 4x4-pooled {row['pooled4']:.3f}")
    Path(args.out).write_text(json.dumps({"class": args.target_class, "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
