"""How many operators one training step of a prior launches, and how long the step takes.

    python benchmarks/step_operators.py --pipeline sar-zero123/sim-prior-rotated --batch_size 64 \\
        --out OUT.json

On a GPU every operator is at least one kernel launch, a few microseconds of host time whatever the batch:
a step that launches thousands of operators is bound by the host when the model is small. The script
counts the ``aten::`` operator calls of one forward and backward (:func:`~sar_zero123.training.step.
compute_losses` on a batch of cached encodings, as a prior's training step runs it) and of one step of the
fine-tune's optimiser (:func:`~sar_zero123.training.finetuning.finetuning_optimizer`), with
``torch.profiler``, then times ``--steps`` whole steps.
``--compile`` times the same step with the UNet compiled (``torch.compile``, inductor), the first step
(the compilation) apart. It writes the counts and times as JSON.
"""

from __future__ import annotations

import argparse
import itertools
import time
from collections.abc import Sequence
from typing import Any

import torch
from diffusers import DDPMScheduler
from torch.profiler import ProfilerActivity, profile

from sar_zero123 import resolve_pretrained
from sar_zero123.config import write_json_atomic
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.training.finetuning import finetuning_optimizer
from sar_zero123.training.latent_cache import ChipLatentCache
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import ImageEmbedder, compute_losses, micro_batch_generator


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", default="sar-zero123/sim-prior-rotated", help="bundled name or folder")
    parser.add_argument("--batch_size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=5, help="timed steps after one warm-up step")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--bf16", action="store_true", help="autocast the step to bfloat16 (a GPU run's)")
    parser.add_argument("--compile", default=None, choices=["default", "reduce-overhead", "max-autotune"])
    parser.add_argument(
        "--loop_optimizer",
        action="store_true",
        help="torch's default for-loop AdamW instead of the fine-tune's fused one",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file of the counts and times")
    return parser.parse_args(argv)


def training_step(args: argparse.Namespace) -> tuple[Any, Any, torch.optim.Optimizer]:
    """``(forward_backward, optimizer_step, optimizer)`` of the pipeline's training step on one batch."""
    device = torch.device(args.device)
    pipe = SARZero123Pipeline.from_pretrained(resolve_pretrained(args.pipeline)).to(device)
    generator = torch.Generator().manual_seed(args.seed)
    size = pipe.vae.config.sample_size
    images = torch.randn(args.batch_size, 1, size, size, generator=generator).to(device)
    cache = ChipLatentCache.encode(images, pipe.vae, pipe.image_encoder)
    angles = (torch.rand(args.batch_size, generator=generator, dtype=torch.float64) - 0.5) * 300.0
    cache = cache.to(device)
    batch = {
        "input": images, "target": images, "d_az_deg": angles, "d_el_deg": torch.zeros_like(angles),
        "input_depression_deg": torch.full_like(angles, 17.0), "input_azimuth_deg": torch.zeros_like(angles),
        "input_latent_mean": cache.latent_mean, "target_latent_mean": cache.latent_mean,
        "target_latent_logvar": cache.latent_logvar, "input_image_embeds": cache.image_embeds,
    }  # fmt: skip
    unet = torch.compile(pipe.unet, mode=args.compile) if args.compile else pipe.unet
    optimizer = finetuning_optimizer(
        pipe.unet, pipe.pose_projection, azimuth_estimator=pipe.azimuth_estimator, learning_rate=1e-4
    )  # the fine-tune's and the prior's optimiser
    if args.loop_optimizer:
        for group in optimizer.param_groups:
            group.update(fused=False, foreach=False)
    kwargs = {"unet": unet, "pose_projection": pipe.pose_projection, "vae": pipe.vae,
              "image_encoder": ImageEmbedder(pipe.image_encoder), "encoder": None,
              "noise_scheduler": DDPMScheduler.from_config(pipe.scheduler.config),
              "loss_settings": LossSettings(pfm_weight=0.0),  # a prior's loss: lambda = 0
              "azimuth_estimator": pipe.azimuth_estimator}  # fmt: skip
    step_index = itertools.count()

    def forward_backward() -> None:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.bf16):
            losses = compute_losses(
                batch, generator=micro_batch_generator(args.seed, next(step_index), 0), **kwargs
            )
        losses.loss.mean().backward()

    def optimizer_step() -> None:
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    return forward_backward, optimizer_step, optimizer


def count_operators(function: Any) -> int:
    """``aten::`` operator calls of one call of ``function``."""
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        function()
    return sum(event.count for event in prof.key_averages() if event.key.startswith("aten::"))


def synchronize(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    forward_backward, optimizer_step, _ = training_step(args)
    start = time.perf_counter()
    forward_backward()  # the warm-up (and, with --compile, the compilation)
    optimizer_step()
    synchronize(args.device)
    first = time.perf_counter() - start
    counts = {
        "forward_backward": count_operators(forward_backward),
        "optimizer": count_operators(optimizer_step),
    }
    synchronize(args.device)
    start = time.perf_counter()
    for _ in range(args.steps):
        forward_backward()
        optimizer_step()
    synchronize(args.device)
    seconds = (time.perf_counter() - start) / args.steps
    device = torch.cuda.get_device_name() if torch.device(args.device).type == "cuda" else "cpu"
    result = {
        "settings": vars(args), "device": f"{device}, torch {torch.__version__}",
        "operators_per_step": counts, "first_step_seconds": first, "step_seconds": seconds,
        "steps_per_second": 1.0 / seconds, "pairs_per_second": args.batch_size / seconds,
    }  # fmt: skip
    print(result)
    if args.out:
        write_json_atomic(result, args.out)
    return result


if __name__ == "__main__":
    main()
