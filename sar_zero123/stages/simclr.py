"""The SimCLR stage: the SAR encoder pretrained with co-domain augmentations (paper Sec. III, Table I).

``train/pretrain_simclr.py`` parses its flags into :class:`PretrainSimCLRConfig` and calls
:func:`run_simclr`.

Defaults are the paper's: ResNet-18 (CIFAR stem), 128x128 chips, batch 256, SGD momentum 0.9,
lr 0.06, weight decay 5e-4, cosine annealing, 500 epochs, preset `speckle+monotonic` with sigma 10,
lambda1 = lambda2 = 1 and Q = 512, projection head 512-512-128, NT-Xent temperature 0.5.

The train split's magnitudes are held in memory on the training device and augmented there, batched
(:func:`sar_zero123.augment.simclr_views`), so file reading never stalls the accelerator. Writes
``<output_dir>/encoder`` (``SAREncoder.save_pretrained``), ``decibel_scaling.json`` (dB bounds),
``config.json``, ``metrics.json`` (final loss, throughput, share of step time spent augmenting),
TensorBoard logs under ``<output_dir>/logs``, resumable ``checkpoint-<step>`` folders and ``run.json``
(:mod:`sar_zero123.runs.folder`). The cosine schedule depends on the step count, so a resumed run
keeps it.

Under multi-process launch each process holds global_batch_size / num_processes chips of every global batch.
By default (``gather_negatives``) NT-Xent contrasts every anchor with the projections of all processes,
so the objective and its gradients are those of one process holding the whole batch of 256, as in
SimCLR; ``gather_negatives=False`` contrasts within each process's sub-batch only (fewer negatives, no
communication). BatchNorm statistics stay per process.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from torch import nn
from torch.utils.data import DataLoader

from sar_zero123.augment import PRESETS, AugmentationPreset
from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import SCALING_FILE, ChipDataset, DecibelScaling, prepare_splits
from sar_zero123.data.selection import select_chips
from sar_zero123.domain import MAX_IMAGE_SIZE
from sar_zero123.encoder import ProjectionHead, SAREncoder, SAREncoderConfig
from sar_zero123.runs.checkpoints import (
    RESUME_MAY_DIFFER,
    check_finite_state,
    check_resume_config,
    end_run,
    resolve_resume_checkpoint,
    resume_step,
)
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run
from sar_zero123.runs.launch import start_run, tracker_hparams
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.training.simclr import NT_XENT_TEMPERATURE, SimCLRChips, SimCLRLoopStats, train_simclr_steps

logger = logging.getLogger(__name__)

__all__ = ["PretrainSimCLRConfig", "load_train_magnitudes", "run_simclr", "select_chips"]

#: SGD's momentum and weight decay (the paper's).
SGD_MOMENTUM = 0.9
SGD_WEIGHT_DECAY = 5e-4


@dataclass
class PretrainSimCLRConfig:
    """SimCLR pretraining of the SAR encoder (ResNet-18) with co-domain augmentations."""

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "work_dir", "max_train_chips", "cifar_stem", "depths", "hidden_sizes", "embedding_size",
        "gather_negatives", "mixed_precision", "checkpointing_steps", "checkpoints_total_limit",
        "logging_steps", "report_to", "num_workers", "resume_from_checkpoint",
    )  # fmt: skip
    #: Settings removed as constants (no recipe, page or measured run set another value): a config or run
    #: folder holding the old default reads as before; another value is refused with the reason.
    REMOVED_FIELDS = {
        "speckle_lambda1": RemovedField(1.0, "lambda1 of Eq. (18) is the paper's 1 (the preset's own)"),
        "speckle_lambda2": RemovedField(1.0, "lambda2 of Eq. (18) is the paper's 1 (the preset's own)"),
        "speckle_mode": RemovedField("pixel", "the speckle is Eq. (17)'s, per pixel"),
        "monotonic_gamma": RemovedField(0.0, "the monotonic map has no random gamma (Algorithm 1)"),
        "in_channels": RemovedField(1, "the encoder reads one channel, the SAR magnitude"),
        "projection_hidden_dim": RemovedField(512, "the projection head is SimCLR's 512-512-128"),
        "projection_dim": RemovedField(128, "the projection head is SimCLR's 512-512-128"),
        "chip_crop_size": RemovedField(None, "chips larger than image_size are centre-cropped to it (their "
                                       "pixel spacing kept)"),
        "temperature": RemovedField(0.5, f"NT-Xent's temperature is SimCLR's {NT_XENT_TEMPERATURE}"),
        "momentum": RemovedField(0.9, f"SGD's momentum is {SGD_MOMENTUM}"),
        "weight_decay": RemovedField(5e-4, f"SGD's weight decay is {SGD_WEIGHT_DECAY:g}"),
        "channels_last": RemovedField(False, "channels-last memory changed nothing measured; convolutions "
                                      "run in the default memory format"),
    }  # fmt: skip

    output_dir: str = "runs/simclr"  # run folder: encoder/, checkpoints, logs, config.json, metrics.json
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
    protocol: str = "extended"  # split protocol of the data; only the "train" split is used
    work_dir: str | None = None  # where the simulated dataset is cached (default: output_dir)
    max_train_chips: int | None = None  # use a seeded random subset of N train chips (quick runs); None = all
    image_size: int = 128  # chip side in pixels (paper: 128)
    preset: str = "speckle+monotonic"  # augmentation preset (Table I row)
    speckle_sigma: float = 10.0  # Rayleigh sigma of Eq. (17), for presets with speckle
    monotonic_q: int = 512  # lookup levels Q of Algorithm 1 and of the level-mode speckle table
    cifar_stem: bool = True  # 3x3 stride-1 stem without max-pool (reference setting)
    depths: tuple[int, ...] = (2, 2, 2, 2)  # ResNet-18 blocks per stage
    hidden_sizes: tuple[int, ...] = (64, 128, 256, 512)  # ResNet-18 stage widths
    embedding_size: int = 64  # stem width
    gather_negatives: bool = True  # multi-process: negatives from the whole global batch, not the sub-batch
    global_batch_size: int = 256  # chips per step over all processes, split evenly (two views each)
    epochs: int = 500  # passes over the train split
    max_train_steps: int | None = None  # stop after this many steps (overrides epochs when smaller)
    # stop at the first step after this many minutes of training (None: no limit); the cosine schedule is
    # still the steps', so a run stopped by the clock ends before its learning rate reaches 0
    max_train_minutes: float | None = None
    learning_rate: float = 0.06  # SGD peak learning rate (cosine annealing to 0)
    mixed_precision: str = "no"  # accelerate mixed precision: "no", "fp16" or "bf16"
    checkpointing_steps: int = 500  # save a resumable checkpoint every this many steps
    checkpoints_total_limit: int | None = 2  # keep at most this many checkpoints
    resume_from_checkpoint: str | None = None  # "latest", a checkpoint folder, or None
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over
    logging_steps: int = 10  # log loss, learning rate and throughput every this many steps
    report_to: str | None = "tensorboard"  # accelerate tracker ("tensorboard"); None disables logging
    num_workers: int = 0  # DataLoader workers for reading the chips once
    seed: int = 0  # seeds the split, the initialisation, the batch order and the augmentations

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        if self.global_batch_size < 2:  # NT-Xent of a lone pair has no negative: loss 0, no gradient
            raise ValueError(
                f"global_batch_size must be >= 2 (NT-Xent needs negatives), got {self.global_batch_size}"
            )
        check_minimum(self, "image_size", minimum=1, maximum=MAX_IMAGE_SIZE)
        check_minimum(self, "epochs", "checkpointing_steps", "logging_steps", minimum=1)
        optional_counts = ("max_train_steps", "max_train_chips", "checkpoints_total_limit")
        check_minimum(self, *optional_counts, minimum=1, optional=True)
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        check_minimum(self, "max_train_minutes", minimum=0, strict=True, optional=True)
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")
        if self.report_to not in ("tensorboard", "none", None):
            raise ValueError(f"report_to must be 'tensorboard' or None, got {self.report_to!r}")
        if self.restart and self.resume_from_checkpoint is not None:
            raise ValueError("restart: starts over; it cannot be combined with resume_from_checkpoint")
        # the augmentation and encoder options validate themselves; fail here, before any work
        self.augmentation()
        self.encoder_config()

    def augmentation(self) -> AugmentationPreset:
        """The preset with this config's co-domain parameters on the stages the preset enables."""
        preset = PRESETS[self.preset]
        overrides: dict[str, Any] = {}
        if preset.speckle_sigma > 0:
            # Eq. (17) per pixel with lambda1 = lambda2 = 1 for every preset, the paper's
            overrides.update(speckle_sigma=self.speckle_sigma, speckle_lambda1=1.0, speckle_lambda2=1.0,
                             speckle_mode="pixel", speckle_q=self.monotonic_q)  # fmt: skip
        if preset.monotonic_q > 0:
            overrides.update(monotonic_q=self.monotonic_q, monotonic_gamma=0.0)
        return dataclasses.replace(preset, **overrides)

    def encoder_config(self) -> SAREncoderConfig:
        """Architecture of the encoder being trained."""
        return SAREncoderConfig(
            image_size=self.image_size,
            in_channels=1,
            cifar_stem=self.cifar_stem,
            depths=self.depths,
            hidden_sizes=self.hidden_sizes,
            embedding_size=self.embedding_size,
        )


def load_train_magnitudes(config: PretrainSimCLRConfig, work_dir: Path) -> torch.Tensor:
    """Reads the train split's chips once as magnitudes. Shape: (N, 1, S, S), values in [0, 1].

    Raises:
        ValueError: If the magnitudes leave [0, 1] (e.g. raw MSTAR files: convert them to an image folder).
    """
    splits = prepare_splits(config.data, config.protocol, work_dir, seed=config.seed)
    records = select_chips(splits["train"], config.max_train_chips, config.seed)
    dataset = ChipDataset(
        records, size=config.image_size, return_magnitude=True
    )
    loader = DataLoader(dataset, batch_size=256, shuffle=False, num_workers=config.num_workers)
    magnitude = torch.cat([batch["magnitude"] for batch in loader])
    if magnitude.min() < 0 or magnitude.max() > 1:
        raise ValueError(
            f"data: train magnitudes must lie in [0, 1] for the co-domain augmentations, got "
            f"[{magnitude.min().item():.3g}, {magnitude.max().item():.3g}]"
        )
    return magnitude


def run_simclr(config: PretrainSimCLRConfig) -> Path:
    """Pretrain (or continue) the SAR encoder in ``config.output_dir``; returns the run folder.

    The encoder lands in ``output_dir/encoder`` and the run's figures in ``metrics.json``; ``run.json`` is
    marked finished once both exist. A finished run continued with the same settings does no work.

    Raises:
        ValueError: Before any work, for a folder holding another run, a run of these settings without
            ``resume_from_checkpoint`` or ``restart``, a checkpoint written with other settings, or a global
            batch the train split or the processes cannot fill.
        FloatingPointError: If training diverges (no encoder is saved).
    """
    timer = StageTimer()
    output_dir = Path(config.output_dir)
    # 1. the checkpoint to continue from (batch_size: its name in older checkpoints), then the run-folder rule
    resume = resolve_resume_checkpoint(output_dir, config.resume_from_checkpoint)
    check_resume_config(resume, config, may_differ=("restart",), renamed={"batch_size": "global_batch_size"})
    folder = open_stage_folder(
        output_dir, "simclr", config, data={"data": data_identity(config.data)},
        resume=config.resume_from_checkpoint is not None, restart=config.restart,
        may_differ=(*RESUME_MAY_DIFFER, "restart"),
    )  # fmt: skip
    if folder.finished:
        logger.info("%s: this SimCLR run is finished; nothing to do", output_dir)
        return output_dir
    accelerator = start_run(
        output_dir, seed=config.seed, mixed_precision=config.mixed_precision, report_to=config.report_to
    )
    # 2. data on the device, model, optimiser, schedule; every input checked before the first step
    with withdrawn_if_setup_fails(folder):
        chips = _load_chips(config, accelerator)
        encoder = SAREncoder(config.encoder_config())
        head = ProjectionHead(encoder.feature_dim, hidden_dim=512, out_dim=128)  # SimCLR's head
        model = nn.Sequential(encoder, head)
        optimizer = torch.optim.SGD(
            model.parameters(), lr=config.learning_rate, momentum=SGD_MOMENTUM, weight_decay=SGD_WEIGHT_DECAY,
        )  # fmt: skip
        # stepped once per optimiser step here (not prepared: there is no prepared dataloader)
        scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=chips.max_steps)
        model, optimizer = accelerator.prepare(model, optimizer)
        accelerator.register_for_checkpointing(scheduler)
        accelerator.init_trackers("simclr", config=tracker_hparams(config))
        start_step = resume_step(accelerator, resume)
    # 3. training, then the encoder, the figures and the record
    stats = train_simclr_steps(config, accelerator, model, optimizer, scheduler, chips, start_step)
    accelerator.wait_for_everyone()
    metrics = _metrics(config, accelerator, chips, stats, start_step)
    if accelerator.is_main_process:
        unwrapped = accelerator.unwrap_model(model)
        check_finite_state({"encoder": unwrapped[0]}, what=str(output_dir / "encoder"))
        unwrapped[0].save_pretrained(output_dir / "encoder")
        write_json_atomic(metrics, output_dir / "metrics.json")
        finish_run(folder, ["encoder/model.safetensors", "metrics.json"], seconds=timer.seconds,
                   results={"final_step": stats.step})  # fmt: skip
    accelerator.wait_for_everyone()  # every process may read metrics.json now
    # no reference to the data-parallel wrapper (or a graph through it) may outlive the process group
    model = None
    end_run(accelerator)
    return output_dir


def _load_chips(config: PretrainSimCLRConfig, accelerator: Accelerator) -> SimCLRChips:
    """The train magnitudes on the device, checked against the global batch; writes ``config.json`` and
    ``decibel_scaling.json``."""
    output_dir = Path(config.output_dir)
    work_dir = Path(config.work_dir) if config.work_dir is not None else output_dir
    with accelerator.main_process_first():  # the main process simulates the dataset once
        magnitude = load_train_magnitudes(config, work_dir).to(accelerator.device)
    num_chips = magnitude.shape[0]
    if num_chips < config.global_batch_size:
        raise ValueError(f"global_batch_size {config.global_batch_size} exceeds the {num_chips} train chips")
    if config.global_batch_size % accelerator.num_processes != 0:
        raise ValueError(f"global_batch_size must be divisible by the {accelerator.num_processes} processes")
    if not config.gather_negatives and config.global_batch_size // accelerator.num_processes < 2:
        raise ValueError(
            f"global_batch_size {config.global_batch_size} over {accelerator.num_processes} processes leaves "
            "fewer than 2 chips per process; NT-Xent without --gather_negatives needs 2"
        )
    scaling = DecibelScaling.for_unit_magnitude()
    if accelerator.is_main_process:
        save_config(config, output_dir)
        write_json_atomic(scaling.to_dict(), output_dir / SCALING_FILE)
    steps_per_epoch = num_chips // config.global_batch_size  # drop the incomplete last batch, as SimCLR does
    max_steps = config.epochs * steps_per_epoch
    if config.max_train_steps is not None:
        max_steps = min(max_steps, config.max_train_steps)
    return SimCLRChips(magnitude, scaling, steps_per_epoch, max_steps)


def _metrics(
    config: PretrainSimCLRConfig,
    accelerator: Accelerator,
    chips: SimCLRChips,
    stats: SimCLRLoopStats,
    start_step: int,
) -> dict[str, Any]:
    """The figures of ``metrics.json``: final loss, steps, throughput and the collapse loss log(2N - 1)."""
    gathered = config.gather_negatives and accelerator.num_processes > 1
    local_batch = config.global_batch_size // accelerator.num_processes
    negatives_batch = config.global_batch_size if gathered else local_batch
    seconds = stats.step_seconds
    return {
        "final_loss": stats.loss,
        "steps": stats.step,
        "start_step": start_step,
        "epochs": stats.step / chips.steps_per_epoch,
        "train_chips": chips.magnitude.shape[0],
        "images_per_second": stats.timed_images / seconds if seconds > 0 else None,
        "augment_fraction": stats.augment_seconds / seconds if seconds > 0 else None,
        "device": str(accelerator.device),
        "num_processes": accelerator.num_processes,
        "collapse_loss": math.log(2 * negatives_batch - 1),
    }
