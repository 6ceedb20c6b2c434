"""Scale of the two PFM forms on real MSTAR chips: 512-d features against the authors' random projection.

For real extended-test chips encoded by a VAE, x0 estimates at a few timesteps (a "network" whose epsilon
prediction is the true noise plus an error of RMS ``--eps_error``, as in bench_pfm.py) and a different
chip's latent (chance level) are scored with ``pfm_loss`` twice: with the encoder's 512-d features
(squared L2, ours) and with ``ProjectedFeatureEncoder`` (mean squared error of a seeded random 512->10
projection, the authors' form), for ``--num_seeds`` projection seeds. Reports the ratio 512-d / projected
per sample and seed, and both forms against L_simple of the same error. JSON on stdout (and in ``--out``).

    python benchmarks/pfm_projection_scale.py --vae runs/vae/vae --data /path/to/mstar --out scale.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sar_zero123.data import signed_to_unit  # noqa: E402
from sar_zero123.encoder import SAREncoder, SAREncoderConfig  # noqa: E402
from sar_zero123.model.conditioning import encode_condition_latents  # noqa: E402
from sar_zero123.training.losses import estimate_x0  # noqa: E402
from sar_zero123.training.pfm import encode_target_features, pfm_loss, project_encoder_features  # noqa: E402


def real_chips(data: str, image_size: int, num_images: int) -> torch.Tensor:
    """``num_images`` random extended-test chips as normalised dB, (N, 1, S, S)."""
    from sar_zero123.data import ChipDataset, load_index, split_records

    records = split_records(load_index(data), "extended")["test"]
    rng = np.random.default_rng(0)
    picked = [records[i] for i in rng.choice(len(records), size=num_images, replace=False)]
    return torch.stack([item["image"] for item in ChipDataset(picked, size=image_size)])


def summarise(values: np.ndarray) -> dict:
    return {
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "p05": float(np.percentile(values, 5)),
        "p95": float(np.percentile(values, 95)),
    }


@torch.no_grad()
def measure(args: argparse.Namespace) -> dict:
    from diffusers import AutoencoderKL, DDPMScheduler

    vae = AutoencoderKL.from_pretrained(args.vae).eval().requires_grad_(False)
    image_size = vae.config.sample_size
    images = real_chips(args.data, image_size, args.num_images)
    if args.encoder:
        encoder = SAREncoder.from_pretrained(args.encoder)
    else:
        torch.manual_seed(0)
        encoder = SAREncoder(SAREncoderConfig(image_size=image_size))
    encoder = encoder.eval().requires_grad_(False)
    projected = [project_encoder_features(encoder, 10, seed=seed) for seed in range(args.num_seeds)]
    latents = encode_condition_latents(vae, images) * vae.config.scaling_factor
    scheduler = DDPMScheduler(
        num_train_timesteps=1000, beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012
    )
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(latents.shape, generator=generator)
    error = torch.randn(latents.shape, generator=generator) * args.eps_error
    l_simple = float(error.pow(2).flatten(1).mean(1).mean())
    cases = {"different chip (chance)": latents.roll(1, dims=0)}
    for t in args.timesteps:
        timesteps = torch.full((latents.shape[0],), t, dtype=torch.long)
        x_t = scheduler.add_noise(latents, noise, timesteps)
        cases[f"x0 estimate, t={t}"] = estimate_x0(x_t, noise + error, timesteps, scheduler)
    target_features = encode_target_features(images, encoder).double()
    rows = []
    for name, estimate in cases.items():
        # Decode and encode once; the projections act on the same feature difference.
        decoded = vae.decode(estimate / vae.config.scaling_factor).sample
        features = encode_target_features(signed_to_unit(decoded), encoder).double()
        difference = features - target_features  # (N, D)
        full = difference.pow(2).sum(1)
        if name == "different chip (chance)":  # the shortcut is pfm_loss itself
            reference = pfm_loss(estimate, images, vae, encoder)
            torch.testing.assert_close(full.float(), reference, rtol=1e-4, atol=0)
        # ProjectedFeatureEncoder's distance: mean over the k outputs of (W difference)^2.
        small = torch.stack(
            [(torch.nn.functional.linear(difference, p.weight.double()) ** 2).mean(1) for p in projected]
        )  # (seeds, N)
        ratio = (full[None] / small).numpy().ravel()
        rows.append(
            {
                "case": name,
                "pfm_512_mean": float(full.mean()),
                "pfm_projected_mean": float(small.mean()),
                "ratio_of_means": float(full.mean() / small.mean()),
                "ratio_per_sample_and_seed": summarise(ratio),
                "pfm_512_over_l_simple": float(full.mean()) / l_simple,
                "pfm_projected_over_l_simple": float(small.mean()) / l_simple,
            }
        )
    return {
        "num_images": args.num_images,
        "image_size": image_size,
        "num_projection_seeds": args.num_seeds,
        "eps_error_rms": args.eps_error,
        "l_simple": l_simple,
        "expected_ratio_3D": 3 * encoder.feature_dim,
        "encoder": args.encoder or "random init ResNet-18 (512-d)",
        "vae": str(args.vae),
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae", required=True, help="AutoencoderKL folder")
    parser.add_argument("--data", required=True, help="MSTAR folder with index.csv")
    parser.add_argument("--encoder", help="SAREncoder folder (default: random init ResNet-18)")
    parser.add_argument("--num_images", type=int, default=32)
    parser.add_argument("--num_seeds", type=int, default=10)
    parser.add_argument("--eps_error", type=float, default=0.1)
    parser.add_argument("--timesteps", type=int, nargs="+", default=[500, 900, 999])
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    result = measure(args)
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return result


if __name__ == "__main__":
    main()
