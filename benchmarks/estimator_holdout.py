"""Which held-out vehicle can an azimuth estimator trained on the others read? (learning.md, section 6a)

    python benchmarks/estimator_holdout.py --vae RUN/vae/vae --data DATA --held_out TANK APC TRUCK SPG \\
        --training_classes APC TRUCK SPG TANK --out estimator_holdout.json

For each class of `--held_out` (protocol ``ood-<CLASS>``), trains a fresh :class:`AzimuthEstimator` (the
model's pose path, ``sar_zero123.model.orientation``) alone on the frozen VAE's condition latents of the train
split of the other classes of `--training_classes`, then reports its circular error on the held-out azimuth
intervals of those classes (val) and on every chip of the held-out class (test): mean, median and the
share above 135 deg (front and back confused). Inside a model the estimator trains with the UNet; alone it
takes seconds and shows the same front/back confusion (``ood-SPG``: 61 % of SPG chips above 135 deg in the
quickstart's model, 44-58 % here), so it tells which held-out class a run can hope to turn correctly.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from diffusers import AutoencoderKL

from sar_zero123.data import SCALING_FILE, DecibelScaling, load_index, split_records
from sar_zero123.model.orientation import AzimuthEstimator, azimuth_estimation_loss

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `benchmarks`
from benchmarks.azimuth_estimator_error import encode_chips, error_summary  # noqa: E402


def train_estimator(latents: torch.Tensor, azimuths: torch.Tensor, steps: int, seed: int) -> AzimuthEstimator:
    """A fresh :class:`AzimuthEstimator` fitted alone to `latents` (AdamW 1e-3, `steps` batches of 32)."""
    torch.manual_seed(seed)
    estimator = AzimuthEstimator(latent_channels=latents.shape[1])
    optimizer = torch.optim.AdamW(estimator.parameters(), lr=1e-3)
    for _ in range(steps):
        batch = torch.randint(0, len(latents), (32,))
        loss = azimuth_estimation_loss(estimator(latents[batch]), azimuths[batch]).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return estimator.eval()


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
    unknown = sorted(set(args.held_out + args.training_classes) - {r.target_class for r in records})
    if unknown:
        raise ValueError(f"held_out / training_classes: no chips of {unknown} in {args.data}")
    result = {"vae": args.vae, "data": args.data, "steps": args.steps, "rows": []}
    for held_out in args.held_out:
        classes = [c for c in args.training_classes if c != held_out]
        splits = {  # every chip of the held-out class; only the training classes' chips of train and val
            name: [r for r in split if name == "test" or r.target_class in classes]
            for name, split in split_records(records, f"ood-{held_out}", seed=0).items()
        }
        encoded = {name: encode_chips(split, vae, scaling, args.image_size) for name, split in splits.items()}
        for seed in args.seeds:
            estimator = train_estimator(*encoded["train"], args.steps, seed)
            row = {"held_out": held_out, "training_classes": classes, "seed": seed}
            row["train_chips"] = len(encoded["train"][0])
            with torch.no_grad():
                for name in ("val", "test"):
                    latents, true_deg = encoded[name]
                    row[name] = error_summary(estimator(latents), true_deg)
            result["rows"].append(row)
            print(json.dumps(row), flush=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
