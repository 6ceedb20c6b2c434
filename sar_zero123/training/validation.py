"""Validation of a fine-tuning run: what the model generates for fixed pairs, and whether it uses its
conditioning.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import PIL.Image
import torch
from accelerate import Accelerator
from diffusers import DDIMScheduler
from diffusers.training_utils import EMAModel

from sar_zero123.evaluation.scoring import pose_following
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.training.step import ImageEmbedder, compute_losses, conditioning_sensitivity

__all__ = ["VALIDATION_GUIDANCE_SCALE", "ema_weights", "make_grid", "run_validation", "validate_pairs"]

#: The classifier-free guidance weight of a fine-tune's validation samples.
VALIDATION_GUIDANCE_SCALE = 3.0

logger = logging.getLogger(__name__)


def make_grid(inputs: torch.Tensor, generated: torch.Tensor, targets: torch.Tensor) -> np.ndarray:
    """Rows of ``input | generated | target`` as an 8-bit image.

    Shape:
        each ``(N, 1, S, S)`` in [0, 1] -> ``(N * S, 3 * S)`` uint8.
    """
    rows = torch.cat([inputs, generated, targets], dim=-1)[:, 0]  # (N, S, 3S)
    grid = rows.reshape(-1, rows.shape[-1]).clamp(0, 1)
    return (grid.float().cpu().numpy() * 255).round().astype(np.uint8)


@contextmanager
def ema_weights(pairs: Sequence[tuple[EMAModel | None, torch.nn.Module]]) -> Iterator[None]:
    """Inside the block each module holds its EMA weights (``None`` EMAs skipped); afterwards, even on an
    exception, its own.
    """
    swapped = [(ema, module) for ema, module in pairs if ema is not None]
    for ema, module in swapped:
        ema.store(module.parameters())
        ema.copy_to(module.parameters())
    try:
        yield
    finally:
        for ema, module in swapped:
            ema.restore(module.parameters())


@torch.no_grad()
def validate_pairs(
    batch: dict[str, Any],
    *,
    pipe: SARZero123Pipeline,
    image_embedder: ImageEmbedder,
    loss_kwargs: dict[str, Any],
    seed: int,
    num_inference_steps: int,
    guidance_scale: float,
    regressor: torch.nn.Module | None = None,
) -> tuple[dict[str, float], np.ndarray]:
    """Losses, samples and conditioning checks of one validation batch, the modules in eval mode.

    1. the losses without CFG dropout; 2. DDIM samples of every pair from ``seed``; 3. the prediction change
    under a 180 deg turn and an input swap and, with ``regressor``, the regressed azimuth of views generated
    for several d_az against the requested one (``pose_following``).

    Args:
        pipe: The pipeline being trained (unwrapped modules); its scheduler is replaced by DDIM for sampling.
        loss_kwargs: The frozen parts and loss settings of ``compute_losses``.
        regressor: An azimuth regressor for the pose-following check.

    Returns:
        ``(logs, grid)``: ``validation/...`` scalars and the ``input | generated | target`` rows.
    """
    modules = [pipe.unet, pipe.pose_projection, image_embedder]
    if pipe.azimuth_estimator is not None:
        modules.append(pipe.azimuth_estimator)
    modes = [module.training for module in modules]
    for module in modules:
        module.eval()
    try:
        # 1. losses
        losses = compute_losses(
            batch,
            unet=pipe.unet,
            pose_projection=pipe.pose_projection,
            image_encoder=image_embedder,
            generator=torch.Generator().manual_seed(seed),
            apply_dropout=False,
            azimuth_estimator=pipe.azimuth_estimator,
            **loss_kwargs,
        )
        logs = {
            "validation/loss_simple": losses.denoising.mean().item(),
            "validation/loss_pfm": losses.pfm.mean().item(),
            **({} if losses.azimuth is None else {"validation/loss_azimuth": losses.azimuth.mean().item()}),
        }
        # 2. samples (not `from_pipe`, which casts every module to one dtype)
        sampler = SARZero123Pipeline(
            **{**pipe.components, "scheduler": DDIMScheduler.from_config(pipe.scheduler.config)}
        )
        sampler.set_progress_bar_config(disable=True)
        takes_depression = getattr(pipe.pose_projection.config, "input_depression", False)
        generated = sampler(
            batch["input"].to(sampler.device, torch.float32),
            d_az=batch["d_az_deg"],
            d_el=batch["d_el_deg"],
            input_depression_deg=batch["input_depression_deg"] if takes_depression else None,
            num_inference_steps=num_inference_steps,
            guidance_scale=guidance_scale,
            generator=torch.Generator().manual_seed(seed),
            output_type="pt",
        ).images
        grid = make_grid(batch["input"], generated.cpu(), batch["target"])
        # 3. conditioning checks
        sensitivity = conditioning_sensitivity(
            batch,
            unet=pipe.unet,
            pose_projection=pipe.pose_projection,
            vae=loss_kwargs["vae"],
            image_encoder=image_embedder,
            noise_scheduler=loss_kwargs["noise_scheduler"],
            seed=seed,
            azimuth_estimator=pipe.azimuth_estimator,
        )
        logs.update({f"validation/sensitivity_{name}": value for name, value in sensitivity.items()})
        if regressor is not None:
            following = pose_following(
                sampler,
                batch["input"][:1].float(),
                float(batch["input_azimuth_deg"][0]),
                regressor,
                num_inference_steps=num_inference_steps,
                guidance_scale=guidance_scale,
                seed=seed,
                input_depression_deg=float(batch["input_depression_deg"][0]) if takes_depression else None,
            )
            logs["validation/pose_following_error_deg"] = following["mean_error_deg"]
            logs["validation/pose_following_floor_deg"] = following["floor_deg"]
        return logs, grid
    finally:
        for module, mode in zip(modules, modes):
            module.train(mode)


def run_validation(
    accelerator: Accelerator,
    directory: str | os.PathLike,
    step: int,
    batch: dict[str, Any],
    *,
    ema_pairs: Sequence[tuple[EMAModel | None, torch.nn.Module]] = (),
    **kwargs: Any,
) -> dict[str, float]:
    """One validation of a training run with the EMA weights swapped in; call it on the main process.

    Writes ``directory/step-<step>.png``, appends ``{"step": step, **logs}`` to ``directory/metrics.jsonl``
    and logs to the run's trackers. ``kwargs`` go to :func:`validate_pairs`. Returns the logged scalars.
    """
    with ema_weights(ema_pairs):
        logs, grid = validate_pairs(batch, **kwargs)
    path = Path(directory) / f"step-{step:06d}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    PIL.Image.fromarray(grid).save(path)
    if any(tracker.name == "tensorboard" for tracker in accelerator.trackers):
        accelerator.get_tracker("tensorboard").log_images(
            {"validation/input_generated_target": grid[None, ..., None]}, step=step, dataformats="NHWC"
        )
    accelerator.log(logs, step=step)
    logger.info("validation step %d: %s", step, json.dumps(logs))
    with open(path.parent / "metrics.jsonl", "a") as stream:
        stream.write(json.dumps({"step": step, **logs}) + "\n")
    return logs
