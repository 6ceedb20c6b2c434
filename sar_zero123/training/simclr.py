"""The SimCLR training loop (Eq. 17-18 co-domain views, NT-Xent) over chips held on the device."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from torch import nn

from sar_zero123.augment import simclr_views
from sar_zero123.data import DecibelScaling
from sar_zero123.encoder import nt_xent_loss
from sar_zero123.progress import progress_bar
from sar_zero123.runs.checkpoints import check_finite_step, save_checkpoint
from sar_zero123.runs.launch import all_out_of_time

logger = logging.getLogger(__name__)

__all__ = ["NT_XENT_TEMPERATURE", "SimCLRChips", "SimCLRLoopStats", "simclr_throughput", "train_simclr_steps"]

#: NT-Xent's temperature (SimCLR's, the paper's).
NT_XENT_TEMPERATURE = 0.5


@dataclass
class SimCLRChips:
    """The train magnitudes on the device, their dB scaling and the run's length in steps."""

    magnitude: torch.Tensor
    scaling: DecibelScaling
    steps_per_epoch: int
    max_steps: int


@dataclass
class SimCLRLoopStats:
    """What the training loop measured: the last step and loss, and the time spent augmenting."""

    step: int
    loss: float
    augment_seconds: float
    step_seconds: float
    timed_images: int


def train_simclr_steps(
    config: Any,
    accelerator: Accelerator,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    chips: SimCLRChips,
    step: int,
) -> SimCLRLoopStats:
    """Steps ``step`` to ``chips.max_steps`` of a ``PretrainSimCLRConfig``.

    Each step's batch and augmentation draw depend only on (seed, step), so a resumed run continues the same
    sequence without stored generator states. With ``config.max_train_minutes`` every process stops at the
    first step past that time.
    """
    augmentation = config.augmentation()
    local_batch = config.global_batch_size // accelerator.num_processes
    rank = accelerator.process_index
    aug_generator = torch.Generator(device=accelerator.device)
    order_generator = torch.Generator()
    order, order_epoch = None, -1
    stats = SimCLRLoopStats(step, float("nan"), 0.0, 0.0, 0)
    minutes = getattr(config, "max_train_minutes", None)
    deadline = None if minutes is None else time.monotonic() + 60.0 * minutes
    model.train()
    progress = progress_bar(
        total=chips.max_steps, initial=step, desc="simclr", disable=not accelerator.is_local_main_process
    )
    while step < chips.max_steps:
        epoch, position = divmod(step, chips.steps_per_epoch)
        if epoch != order_epoch:
            order_generator.manual_seed(config.seed * 1_000_003 + epoch)
            order, order_epoch = torch.randperm(chips.magnitude.shape[0], generator=order_generator), epoch
        start = position * config.global_batch_size + rank * local_batch
        index = order[start : start + local_batch].to(accelerator.device)
        step_start = time.perf_counter()
        aug_generator.manual_seed((config.seed * 1_000_003 + step) * 64 + rank)
        chip_batch = chips.magnitude[index]
        view1, view2 = simclr_views(chip_batch, augmentation, chips.scaling, generator=aug_generator)
        views = torch.cat([view1, view2])  # (2B, 1, S, S): one pass, BatchNorm sees both views
        _synchronize(accelerator.device)
        augmented = time.perf_counter()
        z1, z2 = model(views).chunk(2)
        loss = nt_xent_loss(
            z1, z2, temperature=NT_XENT_TEMPERATURE, gather_distributed=config.gather_negatives
        ).mean()
        optimizer.zero_grad(set_to_none=True)
        accelerator.backward(loss)
        optimizer.step()
        scheduler.step()
        # the mean over processes (also synchronises, so the step time below is complete)
        stats.loss = accelerator.reduce(loss.detach(), reduction="mean").item()
        check_finite_step(step + 1, loss=stats.loss)  # reduced: every process stops together
        finished = time.perf_counter()
        if step > 0 or chips.max_steps == 1:  # the first step pays one-off warm-up costs
            stats.augment_seconds += augmented - step_start
            stats.step_seconds += finished - step_start
            stats.timed_images += config.global_batch_size
        step += 1
        progress.update(1)
        progress.set_postfix(loss=f"{stats.loss:.4f}")
        if step % config.logging_steps == 0 or step == chips.max_steps:
            accelerator.log({"train/loss": stats.loss, "train/lr": scheduler.get_last_lr()[0],
                             **simclr_throughput(stats)}, step=step)  # fmt: skip
        if step % config.checkpointing_steps == 0 and step < chips.max_steps:
            save_checkpoint(
                accelerator, Path(config.output_dir), step, config.checkpoints_total_limit, {"epoch": epoch},
                config=config,
            )  # fmt: skip
        if deadline is not None and all_out_of_time(accelerator, deadline):
            logger.info("max_train_minutes reached at step %d of %d", step, chips.max_steps)
            break
    progress.close()
    stats.step = step
    return stats


def simclr_throughput(stats: SimCLRLoopStats) -> dict[str, float]:
    """Images per second and the share of step time spent augmenting (0 before any timed step)."""
    seconds = stats.step_seconds
    return {
        "train/images_per_second": stats.timed_images / seconds if seconds > 0 else 0.0,
        "train/augment_fraction": stats.augment_seconds / seconds if seconds > 0 else 0.0,
    }


def _synchronize(device: torch.device) -> None:
    """Waits for queued device work so the augmentation time is measured, not just its launch."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
