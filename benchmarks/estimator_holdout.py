"""Which held-out vehicle can an azimuth estimator trained on the others read? (learning.md, section 6a)

    python benchmarks/estimator_holdout.py --vae RUN/vae/vae --data DATA --held_out TANK APC TRUCK SPG \\
        --training_classes APC TRUCK SPG TANK --out estimator_holdout.json

For each class of `--held_out` (protocol ``ood-<CLASS>``), trains a fresh :class:`AzimuthEstimator` (the
model's pose path, ``sar_zero123.orientation``) alone on the frozen VAE's condition latents of the train split
of the other classes of `--training_classes`, then reports its circular error on the held-out azimuth
intervals of those classes (val) and on every chip of the held-out class (test): mean, median and the
share above 135 deg (front and back confused). Inside a model the estimator trains with the UNet; alone it
takes seconds and shows the same front/back confusion (``ood-SPG``: 61 % of SPG chips above 135 deg in the
quickstart's model, 58-66 % here), so it tells which held-out class a run can hope to turn correctly.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from diffusers import AutoencoderKL

from sar_zero123.conditioning import encode_condition_latents
from sar_zero123.data import SCALING_FILE, DecibelScaling, load_chip, load_index, split_records
from sar_zero123.evaluators import azimuth_error_deg
from sar_zero123.orientation import AzimuthEstimator, azimuth_estimation_loss


def encode_split(records, vae, scaling, size, batch_size=256):
    """Condition latents, azimuths (deg) and classes of `records`."""
    chips = [torch.from_numpy(scaling.normalize(load_chip(r.path, size)))[None] for r in records]
    images = torch.stack(chips)
    with torch.no_grad():
        chunks = images.float().split(batch_size)
        latents = torch.cat([encode_condition_latents(vae, chunk) for chunk in chunks])
    azimuths = torch.tensor([r.azimuth_deg for r in records], dtype=torch.float64)
    return latents, azimuths, [r.target_class for r in records]


def error_summary(estimator, latents, azimuths):
    with torch.no_grad():
        estimate = estimator(latents)
    predicted = torch.rad2deg(torch.atan2(estimate[:, 0], estimate[:, 1])).double() % 360.0
    error = azimuth_error_deg(predicted, azimuths)
    return {
        "chips": len(error),
        "mean_deg": round(error.mean().item(), 2),
        "median_deg": round(error.median().item(), 2),
        "above_135_deg_percent": round((error > 135).double().mean().item() * 100, 2),
    }


def main(argv: list[str] | None = None) -> dict:
    """Runs the benchmark (`argv`: the command-line flags); returns what it writes to `--out`."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae", required=True, help="AutoencoderKL folder of train/train_vae.py")
    parser.add_argument("--data", required=True, help="chip folder with index.csv (every class below)")
    parser.add_argument("--held_out", nargs="+", required=True, help="classes to hold out, one at a time")
    parser.add_argument("--training_classes", nargs="+", required=True,
                        help="classes the estimator may train on (the held-out one is dropped)")  # fmt: skip
    parser.add_argument("--steps", type=int, default=1500, help="AdamW steps of 32 chips")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    vae = AutoencoderKL.from_pretrained(args.vae).eval()
    scaling = DecibelScaling.from_dict(json.loads((Path(args.vae) / SCALING_FILE).read_text()))
    records = load_index(args.data)
    unknown = sorted(set(args.held_out) - {r.target_class for r in records})
    if unknown:
        raise ValueError(f"held_out: no chips of {unknown} in {args.data}")
    result = {"vae": args.vae, "data": args.data, "steps": args.steps, "rows": []}
    for held_out in args.held_out:
        splits = split_records(records, f"ood-{held_out}", seed=0)
        encoded = {name: encode_split(split, vae, scaling, args.image_size) for name, split in splits.items()}
        classes = [c for c in args.training_classes if c != held_out]
        latents, azimuths, labels = encoded["train"]
        keep = torch.tensor([label in classes for label in labels])
        val_latents, val_azimuths, val_labels = encoded["val"]
        val_keep = torch.tensor([label in classes for label in val_labels])
        for seed in args.seeds:
            torch.manual_seed(seed)
            estimator = AzimuthEstimator(latent_channels=latents.shape[1])
            optimizer = torch.optim.AdamW(estimator.parameters(), lr=1e-3)
            train_latents, train_azimuths = latents[keep], azimuths[keep]
            for _ in range(args.steps):
                batch = torch.randint(0, len(train_latents), (32,))
                loss = azimuth_estimation_loss(estimator(train_latents[batch]), train_azimuths[batch]).mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
            row = {
                "held_out": held_out,
                "training_classes": classes,
                "seed": seed,
                "train_chips": int(keep.sum()),
                "val": error_summary(estimator, val_latents[val_keep], val_azimuths[val_keep]),
                "test": error_summary(estimator, *encoded["test"][:2]),
            }
            result["rows"].append(row)
            print(json.dumps(row), flush=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
