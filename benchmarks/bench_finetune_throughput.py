"""Fine-tuning throughput (pairs/s) per model size and training-step variant, as ratios in one run.

    python benchmarks/bench_finetune_throughput.py --sizes micro compact small --batch_size 16 \\
        --out docs/results/data/finetune_throughput_cpu.json

Each variant runs :func:`sar_zero123.training.step.compute_losses` + backward + AdamW on one fixed batch of
random 64 px chips (lambda = 0, no CFG dropout) and reports the median step time after warm-up:

- ``encode``: the VAE (and CLIP tower) encode both chips of every pair at every step (before caching).
- ``cached``: frozen encodings from :class:`~sar_zero123.training.latent_cache.ChipLatentCache` (the default
  now).
- ``cached+bf16``: cached, the UNet forward under ``torch.autocast("cpu", torch.bfloat16)``.
- ``cached+channels_last``: cached, the UNet in channels-last memory format.
- ``cached+compile``: cached, the UNet wrapped in ``torch.compile`` (inductor; needs a C++ compiler on a
  CPU). Not in the default ``--variants``: its first step compiles for minutes. ``first_step_seconds``
  records that cost beside the median step.

Speed only: the variants compute the same loss (bf16 to rounding), so no error column applies here; the
error side of speed against error is in ``train/evaluate.py``'s sampler sweep.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch
from diffusers import DDPMScheduler

from sar_zero123.model.build import build_sar_zero123
from sar_zero123.training.latent_cache import ChipLatentCache
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import ImageEmbedder, compute_losses

VARIANTS = ("encode", "cached", "cached+bf16", "cached+channels_last", "cached+compile")
DEFAULT_VARIANTS = VARIANTS[:4]  # torch.compile only on request: minutes of compiling per size


def make_batch(images: torch.Tensor, cache: ChipLatentCache | None, batch_size: int) -> dict:
    """Pairs (i, batch_size + i) of the fixed chips, with the cached encodings when given."""
    generator = torch.Generator().manual_seed(0)
    batch = {
        "input": images[:batch_size],
        "target": images[batch_size:],
        "d_az_deg": torch.rand(batch_size, generator=generator) * 360 - 180,
        "d_el_deg": torch.zeros(batch_size),
    }
    if cache is not None:
        batch.update(
            input_latent_mean=cache.latent_mean[:batch_size],
            target_latent_mean=cache.latent_mean[batch_size:],
            target_latent_logvar=cache.latent_logvar[batch_size:],
            input_image_embeds=cache.image_embeds[:batch_size],
        )
    return batch


def time_variant(size: str, variant: str, batch_size: int, steps: int, warmup: int) -> dict:
    """Median seconds per optimisation step of one (size, variant)."""
    pipe = build_sar_zero123(size)
    unet, projection = pipe.unet.train(), pipe.pose_projection.train()
    vae = pipe.vae.eval().requires_grad_(False)
    tower = pipe.image_encoder.eval().requires_grad_(False)
    if variant.endswith("channels_last"):
        unet.to(memory_format=torch.channels_last)
    model = torch.compile(unet) if variant.endswith("compile") else unet
    images = torch.rand(2 * batch_size, 1, 64, 64, generator=torch.Generator().manual_seed(1))
    cache = ChipLatentCache.encode(images, vae, tower) if variant.startswith("cached") else None
    batch = make_batch(images, cache, batch_size)
    optimizer = torch.optim.AdamW(list(unet.parameters()) + list(projection.parameters()), lr=1e-4)
    scheduler = DDPMScheduler.from_config(pipe.scheduler.config)
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=variant.endswith("bf16"))
    times = []
    for step in range(warmup + steps):
        begin = time.perf_counter()
        with autocast:
            losses = compute_losses(
                batch,
                unet=model,
                pose_projection=projection,
                vae=vae,
                image_encoder=ImageEmbedder(tower),
                encoder=None,
                noise_scheduler=scheduler,
                generator=torch.Generator().manual_seed(step),
                loss_settings=LossSettings(
                    pfm_weight=0.0, drop_image_prob=0.0, drop_both_prob=0.0, drop_latent_prob=0.0
                ),
            )
        losses.loss.float().mean().backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        times.append(time.perf_counter() - begin)
    seconds = statistics.median(times[warmup:])
    return {
        "size": size,
        "variant": variant,
        "unet_parameters": sum(p.numel() for p in unet.parameters()),
        "batch_size": batch_size,
        "seconds_per_step": seconds,
        "first_step_seconds": times[0],  # includes torch.compile's compilation for that variant
        "pairs_per_s": batch_size / seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["micro", "compact", "small"])
    parser.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS), choices=VARIANTS)
    parser.add_argument("--batch_size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--out", default="finetune_throughput.json")
    args = parser.parse_args()
    rows = [
        time_variant(size, variant, args.batch_size, args.steps, args.warmup)
        for size in args.sizes
        for variant in args.variants
    ]
    for row in rows:  # ratio against the size's encode-every-step baseline
        base = next((r for r in rows if r["size"] == row["size"] and r["variant"] == "encode"), None)
        row["speedup_vs_encode"] = base["seconds_per_step"] / row["seconds_per_step"] if base else None
        print(
            f"{row['size']:8s} {row['variant']:22s} {row['unet_parameters'] / 1e6:6.2f} M  "
            f"{row['seconds_per_step']:.3f} s/step  {row['pairs_per_s']:6.1f} pairs/s  "
            f"x{row['speedup_vs_encode'] or float('nan'):.2f}"
        )
    result = {
        "device": f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)",
        "torch": torch.__version__,
        "rows": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
