"""Starting a training run under ``accelerate``, the same way in every script, and the launch's checks:
a multi-process launch that is not distributed, a split smaller than a global batch, and replicas whose
weights disagree at the end."""

from __future__ import annotations

import hashlib
import logging
import os
import time
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from accelerate.utils import (
    DataLoaderConfiguration,
    GradientAccumulationPlugin,
    ProjectConfiguration,
    set_seed,
)

from sar_zero123.config.json_io import config_to_dict

__all__ = [
    "all_out_of_time",
    "check_device",
    "check_distributed_launch",
    "check_global_batch",
    "check_replicas_agree",
    "start_run",
    "tracker_hparams",
    "weights_digest",
]

logger = logging.getLogger(__name__)


def check_device(device: str, field: str = "device") -> torch.device:
    """The torch device ``device`` names, checked before any model loads: one this machine has and can compute
    on (not ``meta``; not ``cuda`` without a CUDA device).

    Raises:
        ValueError: Naming ``field``, for text that is no device or a device this machine lacks.
    """
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"{field}: {device!r} is not a torch device (cpu, cuda, cuda:1, mps, ...)") from None
    available = {
        "cpu": 1,
        "cuda": torch.cuda.device_count(),
        "mps": int(torch.backends.mps.is_available()),
        "xpu": torch.xpu.device_count() if hasattr(torch, "xpu") and torch.xpu.is_available() else 0,
    }
    if parsed.type not in available:
        raise ValueError(f"{field}: {device!r} cannot compute here; expected one of {sorted(available)}")
    count = available[parsed.type]
    if count == 0 or (parsed.index is not None and parsed.index >= count):
        raise ValueError(
            f"{field}: {device!r}, but this machine has {count} {parsed.type} device(s); use cpu or one of "
            "those it has"
        )
    return parsed


def start_run(
    output_dir: str | os.PathLike | None,
    *,
    seed: int,
    mixed_precision: str = "no",
    report_to: str | None = None,
    gradient_accumulation_steps: int = 1,
    seedable_sampler: bool = True,
) -> Accelerator:
    """The run's ``Accelerator``, after checking the launch; logging set up and every RNG seeded.

    Args:
        output_dir: The run folder; trackers log under ``output_dir/logs``. ``None``: no tracker folder.
        report_to: An accelerate tracker; ``None`` or ``"none"``: no tracker.
        gradient_accumulation_steps: Micro-batches per step; the loader's end does not end a cycle, so a
            resumed run keeps the cycles of an uninterrupted one.
        seedable_sampler: Make a prepared loader's order a function of the seed and the epoch, which a resume
            continues exactly; ``False`` keeps the loader's own generator.

    Raises:
        RuntimeError: From :func:`check_distributed_launch`.
    """
    log_with = None if report_to in (None, "none") else report_to
    project_config = None
    if output_dir is not None:
        project_config = ProjectConfiguration(
            project_dir=str(output_dir), logging_dir=str(Path(output_dir) / "logs")
        )
    accelerator = Accelerator(
        mixed_precision=mixed_precision,
        gradient_accumulation_plugin=GradientAccumulationPlugin(
            num_steps=gradient_accumulation_steps, sync_with_dataloader=False
        ),
        dataloader_config=DataLoaderConfiguration(use_seedable_sampler=seedable_sampler),
        log_with=log_with,
        project_config=project_config,
    )
    logging.basicConfig(
        level=logging.INFO if accelerator.is_main_process else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    check_distributed_launch(accelerator)
    set_seed(seed)
    return accelerator


def check_distributed_launch(accelerator: Accelerator) -> None:
    """Refuse a multi-process launch that accelerate did not turn into a distributed run.

    Without GPUs, ``accelerate launch --multi_gpu`` starts processes that each believe they are alone (and
    overwrite each other's checkpoints) unless ``ACCELERATE_USE_CPU=true`` selects gloo.

    Raises:
        RuntimeError: If ``WORLD_SIZE > 1`` but accelerate runs a single process.
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size > 1 and accelerator.num_processes == 1:
        raise RuntimeError(
            f"WORLD_SIZE={world_size} but accelerate started a non-distributed run; on CPU launch with "
            "ACCELERATE_USE_CPU=true accelerate launch --multi_gpu --num_processes N ..."
        )


def check_global_batch(
    num_examples: int,
    batch_size: int,
    num_processes: int,
    what: str = "examples",
    gradient_accumulation_steps: int = 1,
) -> None:
    """Refuse a training split smaller than one optimisation step's examples.

    A ``drop_last`` loader yields ``num_examples // (batch_size x processes)`` micro-batches per epoch: none
    for a split below one global batch, and fewer than one step when ``gradient_accumulation_steps`` exceeds
    them.

    Raises:
        ValueError: ``"data: <N> training <what>, fewer than a global batch of <batch_size x processes>"``,
            or naming ``gradient_accumulation_steps`` and its bound.
    """
    global_batch = batch_size * num_processes
    if num_examples < global_batch:
        raise ValueError(f"data: {num_examples} training {what}, fewer than a global batch of {global_batch}")
    per_epoch = num_examples // global_batch
    if gradient_accumulation_steps > per_epoch:
        raise ValueError(
            f"gradient_accumulation_steps must be <= {per_epoch} for {num_examples} training {what} in "
            f"global batches of {global_batch} (one optimisation step may take at most one epoch's "
            f"{per_epoch} micro-batches), got {gradient_accumulation_steps}"
        )


def tracker_hparams(config: Any) -> dict[str, int | float | str | bool]:
    """Every field of a config dataclass as a tracker hyperparameter; ``None``, lists and paths become
    ``str``."""
    return {
        name: value if isinstance(value, (int, float, str, bool)) else str(value)
        for name, value in config_to_dict(config).items()
    }


def weights_digest(modules: list[torch.nn.Module]) -> torch.Tensor:
    """A 63-bit digest of the exact bytes of every parameter, to compare data-parallel replicas.

    Shape:
        ``(1,)`` int64.
    """
    digest = hashlib.sha256()
    for module in modules:
        for name, parameter in module.named_parameters():
            digest.update(name.encode())
            digest.update(parameter.detach().cpu().contiguous().view(torch.uint8).numpy().tobytes())
    return torch.tensor([int.from_bytes(digest.digest()[:8], "little") >> 1], dtype=torch.int64)


def check_replicas_agree(accelerator: Accelerator, modules: list[torch.nn.Module]) -> list[int]:
    """Gather every process's :func:`weights_digest` of its unwrapped trained modules; call it on every
    process.

    Data-parallel replicas apply the same averaged gradients, so their weights must end bitwise equal.

    Returns:
        The digests, one per process in process order.

    Raises:
        RuntimeError: If the digests differ (the message lists them).
    """
    digests = accelerator.gather(weights_digest(modules).to(accelerator.device)).tolist()
    if len(set(digests)) != 1:
        raise RuntimeError(f"data-parallel replicas diverged: weight digests {digests}")
    return digests


def all_out_of_time(accelerator: Accelerator, deadline: float) -> bool:
    """Whether any process has passed ``deadline``, agreed through a reduction so all stop at the same
    step."""
    if accelerator.num_processes == 1:
        return time.monotonic() >= deadline
    late = torch.tensor([float(time.monotonic() >= deadline)], device=accelerator.device)
    return bool(accelerator.reduce(late, reduction="sum").item() > 0)
