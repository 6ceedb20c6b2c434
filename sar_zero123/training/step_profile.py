"""One training step of a pipeline's prior, as two calls to profile: the forward and backward, and the
optimiser's step. A small model's step on a GPU is bound by the host's kernel launches, so
:func:`count_operators` counts the ``aten::`` calls.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from diffusers import DDPMScheduler
from torch.profiler import ProfilerActivity, profile

from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.training.finetuning import finetuning_optimizer
from sar_zero123.training.latent_cache import ChipLatentCache
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import ImageEmbedder, compute_losses, micro_batch_generator

__all__ = ["count_operators", "prior_training_step"]


def prior_training_step(
    pipeline: str | Path,
    *,
    batch_size: int,
    device: str | torch.device = "cpu",
    bf16: bool = False,
    compile_mode: str | None = None,
    loop_optimizer: bool = False,
    seed: int = 0,
) -> tuple[Callable[[], None], Callable[[], None], torch.optim.Optimizer]:
    """The training step of a pipeline's prior (lambda = 0, the fine-tune's optimiser) on random chips.

    Args:
        pipeline: A saved pipeline folder.
        bf16: Autocast the forward and backward to bfloat16.
        compile_mode: ``torch.compile`` the UNet with this mode (None: eager).
        loop_optimizer: torch's for-loop AdamW instead of the fine-tune's fused one.

    Returns:
        ``(forward_backward, optimizer_step, optimizer)``: each ``forward_backward`` draws its own micro-batch
        generator and accumulates gradients; ``optimizer_step`` steps and zeroes them.
    """
    device = torch.device(device)
    pipe = SARZero123Pipeline.from_pretrained(pipeline).to(device)
    generator = torch.Generator().manual_seed(seed)
    size = pipe.vae.config.sample_size
    images = torch.randn(batch_size, 1, size, size, generator=generator).to(device)
    cache = ChipLatentCache.encode(images, pipe.vae, pipe.image_encoder)
    angles = (torch.rand(batch_size, generator=generator, dtype=torch.float64) - 0.5) * 300.0
    cache = cache.to(device)
    batch = {
        "input": images, "target": images, "d_az_deg": angles, "d_el_deg": torch.zeros_like(angles),
        "input_depression_deg": torch.full_like(angles, 17.0), "input_azimuth_deg": torch.zeros_like(angles),
        "input_latent_mean": cache.latent_mean, "target_latent_mean": cache.latent_mean,
        "target_latent_logvar": cache.latent_logvar, "input_image_embeds": cache.image_embeds,
    }  # fmt: skip
    unet = torch.compile(pipe.unet, mode=compile_mode) if compile_mode else pipe.unet
    optimizer = finetuning_optimizer(
        pipe.unet, pipe.pose_projection, azimuth_estimator=pipe.azimuth_estimator, learning_rate=1e-4
    )  # the fine-tune's and the prior's optimiser
    if loop_optimizer:
        for group in optimizer.param_groups:
            group.update(fused=False, foreach=False)
    kwargs: dict[str, Any] = {
        "unet": unet, "pose_projection": pipe.pose_projection, "vae": pipe.vae,
        "image_encoder": ImageEmbedder(pipe.image_encoder), "encoder": None,
        "noise_scheduler": DDPMScheduler.from_config(pipe.scheduler.config),
        "loss_settings": LossSettings(pfm_weight=0.0),  # a prior's loss: lambda = 0
        "azimuth_estimator": pipe.azimuth_estimator,
    }  # fmt: skip
    step_index = itertools.count()

    def forward_backward() -> None:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            losses = compute_losses(
                batch, generator=micro_batch_generator(seed, next(step_index), 0), **kwargs
            )
        losses.loss.mean().backward()

    def optimizer_step() -> None:
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    return forward_backward, optimizer_step, optimizer


def count_operators(function: Callable[[], Any]) -> int:
    """``aten::`` operator calls of one call of ``function`` (``torch.profiler`` on the CPU's side)."""
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        function()
    return sum(event.count for event in prof.key_averages() if event.key.startswith("aten::"))
