"""The parts of a zero-1-to-3 fine-tuning run around its training step (:mod:`sar_zero123.training.step`):
which modules train and in which dtype, their EMA copies, the optimizer, the logged scalars, the loop and
the export of the finished pipeline.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
from diffusers.training_utils import EMAModel
from torch.utils.data import DataLoader, Dataset

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.domain import naming_write_errors
from sar_zero123.model.conditioning import PoseProjection
from sar_zero123.model.orientation import estimator_weights_digest
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.proxy import DEFAULT_PROXY
from sar_zero123.model.sampler import EXPORTED_SAMPLER
from sar_zero123.model.spatial_pose import takes_proxy
from sar_zero123.progress import progress_bar
from sar_zero123.runs.checkpoints import (
    check_finite_state,
    check_finite_step,
    resumable_batches,
    save_checkpoint,
)
from sar_zero123.runs.launch import all_out_of_time
from sar_zero123.runs.manifest import write_manifest
from sar_zero123.training.losses import LossOutput
from sar_zero123.training.step import (
    MAX_GRAD_NORM,
    ImageEmbedder,
    compute_losses,
    micro_batch_generator,
    timestep_bucket_losses,
)
from sar_zero123.training.validation import VALIDATION_GUIDANCE_SCALE, run_validation

logger = logging.getLogger(__name__)

__all__ = [
    "FinetuneInputs",
    "FinetuneTrainer",
    "ema_models",
    "export_finetuned",
    "finetuning_modules",
    "finetuning_optimizer",
    "mixed_precision_dtype",
    "step_logs",
    "train_finetune_steps",
    "training_image_size",
]


def mixed_precision_dtype(mixed_precision: str) -> torch.dtype:
    """The dtype of frozen modules under accelerate's ``mixed_precision`` (``"no"``: float32)."""
    return {"fp16": torch.float16, "bf16": torch.bfloat16}.get(mixed_precision, torch.float32)


def training_image_size(pipe: SARZero123Pipeline, image_size: int | None = None) -> int:
    """The chip side a run trains at: ``image_size``, or the size the model was built for.

    Raises:
        ValueError: If it is not a multiple of ``pipe.size_multiple`` (VAE factor x UNet downsampling).
    """
    image_size = image_size if image_size is not None else pipe.default_image_size
    if image_size % pipe.size_multiple:
        raise ValueError(f"image_size must be a multiple of {pipe.size_multiple}, got {image_size}")
    return image_size


def finetuning_modules(
    pipe: SARZero123Pipeline,
    *,
    device: torch.device | str,
    weight_dtype: torch.dtype,
    train_image_encoder: bool = False,
    gradient_checkpointing: bool = False,
) -> tuple[AutoencoderKL, ImageEmbedder, UNet2DConditionModel, PoseProjection]:
    """``pipe``'s modules set up for fine-tuning (in place): frozen ones cast, trained ones in float32.

    zero-1-to-3 keeps the CLIP tower frozen; ``train_image_encoder`` trains it too, for models built from
    scratch whose tower is random.

    Args:
        weight_dtype: dtype of the frozen modules (:func:`mixed_precision_dtype`).

    Returns:
        ``(vae, image_embedder, unet, pose_projection)``, ``pipe``'s own modules: the VAE frozen on
        ``device``, the tower in an :class:`ImageEmbedder`, the UNet and pose projection (and an azimuth
        estimator) in float32 train mode, left where they are for ``accelerate.prepare``.
    """
    vae = pipe.vae.to(device, dtype=weight_dtype).eval().requires_grad_(False)
    if train_image_encoder:
        image_embedder = ImageEmbedder(pipe.image_encoder.to(device, dtype=torch.float32))
        image_embedder.train().requires_grad_(True)
    else:
        image_embedder = ImageEmbedder(
            pipe.image_encoder.to(device, dtype=weight_dtype).eval().requires_grad_(False)
        )
    unet, pose_projection = pipe.unet.train(), pipe.pose_projection.train()
    unet.requires_grad_(True)
    pose_projection.requires_grad_(True)
    if pipe.azimuth_estimator is not None:  # trained like the pose projection (sar_zero123.model.orientation)
        pipe.azimuth_estimator.train().requires_grad_(True)
    if gradient_checkpointing:
        unet.enable_gradient_checkpointing()
    return vae, image_embedder, unet, pose_projection


def ema_models(
    accelerator: Accelerator,
    unet: UNet2DConditionModel,
    image_embedder: ImageEmbedder | None = None,
    *,
    decay: float,
) -> list[tuple[EMAModel, torch.nn.Module]]:
    """EMA copies of the UNet and of a trained CLIP tower, registered for the accelerator's checkpoints.

    The tower is averaged over the same steps as the EMA UNet it conditions. Pass the UNet itself, not the
    prepared wrapper (its parameters are the same tensors).

    Returns:
        ``(ema, module)`` pairs, UNet first (the checkpoint file order).
    """
    ema_unet = EMAModel(
        unet.parameters(), decay=decay, model_cls=UNet2DConditionModel, model_config=unet.config
    )
    pairs = [(ema_unet, unet)]
    if image_embedder is not None:
        pairs.append((EMAModel(image_embedder.parameters(), decay=decay), image_embedder))
    for ema, _ in pairs:
        ema.to(accelerator.device)
        accelerator.register_for_checkpointing(ema)
    return pairs


def finetuning_optimizer(
    unet: torch.nn.Module,
    pose_projection: torch.nn.Module,
    image_embedder: torch.nn.Module | None = None,
    *,
    learning_rate: float,
    pose_lr_multiplier: float = 10.0,
    weight_decay: float = 1e-2,
    azimuth_estimator: torch.nn.Module | None = None,
) -> torch.optim.AdamW:
    """AdamW over zero-1-to-3's parameter groups: the pose projection at ``pose_lr_multiplier`` times
    ``learning_rate`` (zero-1-to-3: 10x), everything else trained at ``learning_rate``; frozen parameters
    are left out. Fused: one kernel per step, far faster than torch's default loop on a CPU too.
    """

    def trained(module: torch.nn.Module) -> list[torch.nn.Parameter]:
        return [parameter for parameter in module.parameters() if parameter.requires_grad]

    param_groups = [
        {"params": trained(unet), "lr": learning_rate},
        {"params": trained(pose_projection), "lr": learning_rate * pose_lr_multiplier},
    ]
    if image_embedder is not None:
        param_groups.append({"params": trained(image_embedder), "lr": learning_rate})
    if azimuth_estimator is not None:
        param_groups.append({"params": trained(azimuth_estimator), "lr": learning_rate})
    return torch.optim.AdamW(param_groups, weight_decay=weight_decay, fused=True)


def step_logs(
    accelerator: Accelerator, losses: LossOutput, learning_rate: float, num_train_timesteps: int
) -> dict[str, float]:
    """The scalars of one optimisation step, means over every process's samples (call it on all).

    Returns:
        ``train/loss``, ``train/loss_simple``, ``train/loss_pfm``, ``lr`` and ``train/loss_simple_<quarter>``.
    """
    denoising = accelerator.gather(losses.denoising.detach())
    logs = {
        "train/loss": accelerator.gather(losses.loss.detach()).mean().item(),
        "train/loss_simple": denoising.mean().item(),
        "train/loss_pfm": accelerator.gather(losses.pfm.detach()).mean().item(),
        "lr": learning_rate,
    }
    if losses.azimuth is not None:
        logs["train/loss_azimuth"] = accelerator.gather(losses.azimuth.detach()).mean().item()
    buckets = timestep_bucket_losses(denoising, accelerator.gather(losses.timesteps), num_train_timesteps)
    logs.update({f"train/loss_simple_{name}": value for name, value in buckets.items()})
    return logs


def export_finetuned(
    directory: str | os.PathLike,
    pipe: SARZero123Pipeline,
    scaling: DecibelScaling,
    ema_pairs: Sequence[tuple[EMAModel, torch.nn.Module]] = (),
    lineage: dict[str, Any] | None = None,
) -> Path:
    """``save_pretrained`` of the fine-tuned pipeline (float32) plus the ``DecibelScaling`` it expects.

    The EMA weights of ``ema_pairs`` are copied into ``pipe``'s modules first and the sampler becomes a
    ``DDIMScheduler``. ``lineage`` (what the
    run started from) goes into ``model_index.json``. Call it on the main process after the last step;
    returns ``directory``.

    Raises:
        FloatingPointError: If a weight is not finite (nothing is written).
    """
    directory = Path(directory)
    for ema, module in ema_pairs:
        ema.copy_to(module.parameters())
    # the proxy settings travel on, in this data's dB scaling; a proxy model also keeps its start's sampler
    proxy = getattr(pipe.config, "proxy", None)
    proxy_model = takes_proxy(pipe.pose_projection)
    if proxy is None and proxy_model:
        proxy = DEFAULT_PROXY
    if proxy is not None:
        proxy = {**proxy, "min_db": float(scaling.min_db), "max_db": float(scaling.max_db)}
    # the measured step count, and a proxy model's whole sampler (its start from the proxy)
    # the estimator's record is rewritten below for the weights exported (the start's no longer holds)
    pipe.pose_projection.register_to_config(trained_estimator=None)
    sampler = {**EXPORTED_SAMPLER, **((getattr(pipe.config, "sampler", None) or {}) if proxy_model else {})}
    export = SARZero123Pipeline(
        **{**pipe.components, "scheduler": DDIMScheduler.from_config(pipe.scheduler.config)},
        sampler=sampler, proxy=proxy, lineage=lineage,
    )  # fmt: skip
    for module in (export.unet, export.image_encoder, export.pose_projection, export.azimuth_estimator):
        if module is not None:
            module.eval()
    if export.azimuth_estimator is not None:  # the estimator the UNet was trained beside, checked at loading
        export.pose_projection.register_to_config(
            trained_estimator=estimator_weights_digest(export.azimuth_estimator)
        )
    check_finite_state(export.components, what=str(directory))
    export.to(torch.float32)
    kept = "the checkpoints are kept and the run is not marked finished; free space and resume to export"
    with naming_write_errors(directory, kept):
        for stale in Path(directory).glob(".*.tmp"):  # a half-written file of an export killed before
            stale.unlink()
        export.save_pretrained(directory)
        write_json_atomic(scaling.to_dict(), directory / SCALING_FILE)
        write_manifest(directory)  # sealed again, the scaling included
    return directory


@dataclass
class FinetuneInputs:
    """What a fine-tune reads: the model it starts from, the PFM encoder, the data, a pose regressor."""

    pipe: SARZero123Pipeline
    image_size: int
    encoder: torch.nn.Module | None
    train_dataset: Dataset
    validation_dataset: Dataset
    scaling: DecibelScaling
    regressor: torch.nn.Module | None
    rehearsal_dataset: Dataset | None = None


@dataclass
class FinetuneTrainer:
    """The prepared training state of a fine-tune (data-parallel wrappers where accelerate made them)."""

    trained_modules: list[torch.nn.Module]
    unet: torch.nn.Module
    pose_projection: torch.nn.Module
    image_encoder: torch.nn.Module
    azimuth_estimator: torch.nn.Module | None
    image_embedder: torch.nn.Module
    ema_pairs: list
    optimizer: Any
    lr_scheduler: Any
    train_dataloader: DataLoader
    train_dataset: Dataset
    validation_batch: dict
    loss_kwargs: dict[str, Any]
    global_step: int


def train_finetune_steps(
    config: Any, accelerator: Accelerator, inputs: FinetuneInputs, trainer: FinetuneTrainer
) -> int:
    """The fine-tune's training loop (``config``: a ``FinetuneConfig``) from ``trainer.global_step`` to
    ``config.max_train_steps``; returns the last step.
    """
    output_dir = Path(config.output_dir)
    global_step = trainer.global_step
    trainable = [parameter for module in trainer.trained_modules for parameter in module.parameters()]
    progress = progress_bar(total=config.max_train_steps, initial=global_step, desc="steps",
                    disable=not accelerator.is_local_main_process)  # fmt: skip
    noise_scheduler = trainer.loss_kwargs["noise_scheduler"]
    accumulation = config.gradient_accumulation_steps  # micro-batch i belongs to step i // accumulation
    first, stop = global_step * accumulation, config.max_train_steps * accumulation
    batches = resumable_batches(
        accelerator, trainer.train_dataloader, first, stop, datasets=[trainer.train_dataset]
    )
    minutes = config.max_train_minutes
    deadline = None if minutes is None else time.monotonic() + 60.0 * minutes
    for batch_index, epoch, batch in batches:
        with accelerator.accumulate(*trainer.trained_modules):
            generator = micro_batch_generator(config.seed, batch_index, accelerator.process_index)
            losses = compute_losses(
                batch,
                unet=trainer.unet,
                pose_projection=trainer.pose_projection,
                image_encoder=trainer.image_encoder,
                azimuth_estimator=trainer.azimuth_estimator,
                generator=generator,
                **trainer.loss_kwargs,
            )
            accelerator.backward(losses.loss.mean())
            if accelerator.sync_gradients:
                accelerator.clip_grad_norm_(trainable, MAX_GRAD_NORM)
            trainer.optimizer.step()
            trainer.lr_scheduler.step()
            trainer.optimizer.zero_grad(set_to_none=True)
        if not accelerator.sync_gradients:
            continue
        global_step += 1
        for ema, module in trainer.ema_pairs:
            ema.step(module.parameters())
        progress.update(1)
        out_of_time = deadline is not None and all_out_of_time(accelerator, deadline)
        last = global_step == config.max_train_steps or out_of_time
        checkpoint = global_step % config.checkpointing_steps == 0 or last
        # the scalars reach the host (a synchronisation that stalls a GPU's queue) every logging_steps, and
        # before every checkpoint: no non-finite weights are saved
        if global_step % config.logging_steps == 0 or checkpoint:
            learning_rate = trainer.lr_scheduler.get_last_lr()[0]
            logs = step_logs(accelerator, losses, learning_rate, noise_scheduler.config.num_train_timesteps)
            progress.set_postfix(loss=f"{logs['train/loss']:.4f}")
            accelerator.log(logs, step=global_step)
            check_finite_step(global_step, loss=logs["train/loss"])  # gathered: every process stops
        if checkpoint:
            extra_state = {"epoch": epoch, "batch_index": batch_index + 1,
                           "train_image_encoder": config.train_image_encoder}  # fmt: skip
            save_checkpoint(accelerator, output_dir, global_step, config.checkpoints_total_limit,
                            extra_state=extra_state, config=config)  # fmt: skip
        if config.validation_steps and global_step % config.validation_steps == 0:
            if accelerator.is_main_process:
                run_validation(
                    accelerator,
                    output_dir / "validation",
                    global_step,
                    trainer.validation_batch,
                    ema_pairs=trainer.ema_pairs,
                    pipe=inputs.pipe,
                    image_embedder=trainer.image_embedder,
                    loss_kwargs=trainer.loss_kwargs,
                    seed=config.seed,
                    num_inference_steps=config.validation_inference_steps,
                    guidance_scale=VALIDATION_GUIDANCE_SCALE,
                    regressor=inputs.regressor,
                )
            accelerator.wait_for_everyone()
        if out_of_time:
            logger.info("max_train_minutes reached at step %d of %d", global_step, config.max_train_steps)
            break
    progress.close()
    return global_step
