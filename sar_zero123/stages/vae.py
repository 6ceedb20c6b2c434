"""The VAE stage: an ``AutoencoderKL`` sized for SAR chips, for users without a pretrained VAE.

``train/train_vae.py`` parses its flags into :class:`TrainVAEConfig` and calls :func:`run_vae`.

Default: 1-channel 128 px chips -> 32x32x4 latents (three encoder levels, downsampling 4), trained on the
training split with an L1 (or L2) reconstruction loss plus a small KL term; the latent scaling factor is
set to 1 / std of the training latents (how Stable Diffusion's 0.18215 was obtained), and reconstruction
PSNR/SSIM (scikit-image, data range 1) on the test split is written to ``metrics.json``. The model is
saved with ``save_pretrained`` into ``output_dir/vae`` and loads with ``AutoencoderKL.from_pretrained``
(``FinetuneConfig.vae``). The learning rate is constant, so a resumed run may ask for more steps.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from accelerate import Accelerator
from diffusers import AutoencoderKL
from torch.utils.data import DataLoader

from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import (
    SCALING_FILE,
    ChipDataset,
    DecibelScaling,
    check_protocol,
    prepare_splits,
)
from sar_zero123.domain import MAX_IMAGE_SIZE
from sar_zero123.evaluation.reconstruction import evaluate_reconstruction
from sar_zero123.model.conditioning import downsampling_factor
from sar_zero123.model.vae import latent_scaling_factor, new_sar_vae, reconstruct
from sar_zero123.runs.checkpoints import (
    RESUME_MAY_DIFFER,
    check_finite_state,
    check_finite_step,
    check_resume_config,
    check_resume_steps,
    end_run,
    resolve_resume_checkpoint,
    resume_step,
)
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run
from sar_zero123.runs.launch import check_global_batch, start_run, tracker_hparams
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.training.step import MAX_GRAD_NORM
from sar_zero123.training.vae import VAEObjective, train_vae_steps

logger = logging.getLogger(__name__)

__all__ = [
    "TrainVAEConfig",
    "VAEObjective",
    "build_vae",
    "evaluate_reconstruction",
    "latent_scaling_factor",
    "reconstruct",
    "run_vae",
]

#: Weight of the KL term (a per-sample sum over latent elements) beside the L1 pixel loss on [-1, 1] images.
KL_WEIGHT = 1e-6
#: Training batches the latent scaling factor is estimated on.
SCALING_BATCHES = 8
_DECODER_FINE_TUNE = (
    "fine-tuning a pretrained VAE (a prior's decoder alone) measured no gain in accuracy; the stage trains a "
    "new VAE, and a prior's fine-tunes decode with the prior's own"
)


@dataclass
class TrainVAEConfig:
    """Train an AutoencoderKL on SAR chips (normalised dB)."""

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "block_out_channels", "layers_per_block", "latent_channels", "norm_num_groups",
        "mixed_precision", "checkpointing_steps", "checkpoints_total_limit", "num_eval_images", "report_to",
        "resume_from_checkpoint",
    )  # fmt: skip
    #: Settings removed as constants (no recipe, page or measured run set another value): a config or run
    #: folder holding the old default reads as before; another value is refused with the reason.
    REMOVED_FIELDS = {
        "reconstruction_loss": RemovedField("l1", "the pixel loss is L1 on [-1, 1] images"),
        "kl_weight": RemovedField(1e-6, f"the KL term's weight is {KL_WEIGHT:g}"),
        "max_grad_norm": RemovedField(1.0, f"gradients are clipped to a norm of {MAX_GRAD_NORM}"),
        "num_scaling_batches": RemovedField(8, f"the latent scaling factor is estimated on {SCALING_BATCHES} "
                                            "training batches"),
        "pretrained": RemovedField(None, _DECODER_FINE_TUNE),
        "train_encoder": RemovedField(True, _DECODER_FINE_TUNE),
        "feature_loss_weight": RemovedField(0.0, "the SAR feature loss served the decoder fine-tune, which "
                                            "measured no gain; the loss is L1 pixels plus KL"),
        "feature_encoder": RemovedField(None, "the SAR feature loss it fed served the decoder fine-tune, "
                                        "which measured no gain"),
    }  # fmt: skip

    output_dir: str = "runs/vae"  # run folder: checkpoints, logs, metrics.json, vae/
    data: str | None = None  # dataset folder with index.csv; None simulates the built-in dataset
    protocol: str = "extended"  # split protocol: extended, soc or ood-<CLASS>
    scaling: Literal["unit", "mstar_raw", "fit"] = "unit"  # dB bounds: unit magnitude, raw MSTAR, or fitted
    image_size: int = 128  # chip side in pixels
    block_out_channels: tuple[int, ...] = (32, 64, 128)  # encoder widths; n levels downsample by 2**(n-1)
    layers_per_block: int = 2  # ResNet blocks per level
    latent_channels: int = 4  # latent channels (4 for the zero-1-to-3 UNet)
    norm_num_groups: int = 32  # GroupNorm groups (must divide every width)
    learning_rate: float = 1e-4  # AdamW learning rate
    train_batch_size: int = 16  # chips per process per step
    max_train_steps: int = 2000  # optimisation steps
    mixed_precision: Literal["no", "fp16", "bf16"] = "no"  # accelerate mixed precision
    checkpointing_steps: int = 500  # save a resumable checkpoint every this many steps
    checkpoints_total_limit: int | None = 2  # keep at most this many checkpoints
    resume_from_checkpoint: str | None = None  # 'latest' or a checkpoint folder
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over
    num_eval_images: int = 256  # test chips scored for PSNR/SSIM (fewer if the split is smaller)
    report_to: str | None = "tensorboard"  # accelerate tracker; None disables logging
    seed: int = 0  # seed of initialisation, data order and posterior samples

    def __post_init__(self) -> None:
        self.block_out_channels = tuple(int(c) for c in self.block_out_channels)
        if not self.block_out_channels or min(self.block_out_channels) < 1:
            raise ValueError(
                f"block_out_channels must be non-empty and positive, got {self.block_out_channels}"
            )
        if any(c % self.norm_num_groups for c in self.block_out_channels):
            raise ValueError(
                f"norm_num_groups={self.norm_num_groups} must divide every block_out_channels "
                f"{self.block_out_channels}"
            )
        check_minimum(self, "image_size", minimum=1, maximum=MAX_IMAGE_SIZE)
        factor = downsampling_factor(self.block_out_channels)
        if self.image_size < factor or self.image_size % factor:
            raise ValueError(
                f"image_size must be a positive multiple of the downsampling factor {factor}, "
                f"got {self.image_size}"
            )
        check_protocol(self.protocol)
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        check_minimum(
            self,
            "layers_per_block",
            "latent_channels",
            "train_batch_size",
            "max_train_steps",
            "checkpointing_steps",
            "num_eval_images",
            minimum=1,
        )
        check_minimum(self, "checkpoints_total_limit", minimum=1, optional=True)
        if self.restart and self.resume_from_checkpoint is not None:
            raise ValueError("restart: starts over; it cannot be combined with resume_from_checkpoint")


def build_vae(config: TrainVAEConfig) -> AutoencoderKL:
    """A randomly initialised 1-channel ``AutoencoderKL`` of the configured size
    (:func:`~sar_zero123.model.vae.new_sar_vae`)."""
    return new_sar_vae(
        image_size=config.image_size, block_out_channels=config.block_out_channels,
        layers_per_block=config.layers_per_block, latent_channels=config.latent_channels,
        norm_num_groups=config.norm_num_groups,
    )  # fmt: skip


def run_vae(config: TrainVAEConfig) -> Path:
    """Train (or continue, or extend) the VAE in ``config.output_dir``; returns the run folder.

    The model lands in ``output_dir/vae`` with the ``decibel_scaling.json`` it expects; ``run.json`` is
    marked finished once that file exists. A finished run continued with the same settings does no work.

    Raises:
        ValueError: Before any work, for a folder holding another run, a run of these settings without
            ``resume_from_checkpoint`` or ``restart``, a checkpoint written with other settings, or fewer
            training chips than one global batch.
        FloatingPointError: If training diverges (nothing non-finite is saved).
    """
    timer = StageTimer()
    output_dir = Path(config.output_dir)
    # 1. the checkpoint to continue from (constant LR: max_train_steps may grow), then the run-folder rule
    resume_path = resolve_resume_checkpoint(output_dir, config.resume_from_checkpoint)
    check_resume_config(resume_path, config, may_differ=("max_train_steps", "restart"))
    check_resume_steps(resume_path, config.max_train_steps)
    folder = open_stage_folder(
        output_dir, "vae", config, data={"data": data_identity(config.data)},
        resume=config.resume_from_checkpoint is not None, restart=config.restart,
        may_differ=(*RESUME_MAY_DIFFER, "restart"), may_extend=("max_train_steps",),
    )  # fmt: skip
    if folder.finished:
        logger.info("%s: this VAE run is finished; nothing to do", output_dir)
        return output_dir
    accelerator = start_run(
        output_dir, seed=config.seed, mixed_precision=config.mixed_precision, report_to=config.report_to
    )
    # 2. data, model, optimiser, checked before any step
    with withdrawn_if_setup_fails(folder):
        scaling, train_dataset, test_dataset = _load_chips(config, accelerator)
        objective = VAEObjective(build_vae(config).train(), KL_WEIGHT, "l1")
        optimizer = torch.optim.AdamW(objective.parameters(), lr=config.learning_rate)
        train_loader = DataLoader(
            train_dataset, batch_size=config.train_batch_size, shuffle=True, drop_last=True
        )
        objective, optimizer, train_loader = accelerator.prepare(objective, optimizer, train_loader)
        global_step = resume_step(accelerator, resume_path)
        accelerator.init_trackers("train_vae", config=tracker_hparams(config))
    # 3. training, then the model and the record
    global_step = train_vae_steps(config, accelerator, objective, optimizer, train_loader, global_step)
    accelerator.wait_for_everyone()
    if accelerator.is_main_process:
        model = accelerator.unwrap_model(objective).vae.eval()
        _export(config, accelerator, model, train_loader, test_dataset, scaling, global_step)
        finish_run(folder, ["metrics.json", f"vae/{SCALING_FILE}"], seconds=timer.seconds,
                   results={"final_step": global_step})  # fmt: skip
    # no reference to the data-parallel wrapper (or a graph through it) may outlive the process group
    objective = None
    end_run(accelerator)
    return output_dir


def _load_chips(
    config: TrainVAEConfig, accelerator: Accelerator
) -> tuple[DecibelScaling, ChipDataset, ChipDataset]:
    """The dB scaling and the train and test chips (the train split stands in for a missing test split);
    writes ``config.json``."""
    output_dir = Path(config.output_dir)
    splits = prepare_splits(config.data, config.protocol, output_dir / "data", seed=config.seed)
    scaling = DecibelScaling.from_choice(config.scaling, splits["train"])
    train_dataset = ChipDataset(splits["train"], size=config.image_size, scaling=scaling)
    test_dataset = ChipDataset(splits.get("test") or splits["train"], size=config.image_size, scaling=scaling)
    check_global_batch(len(train_dataset), config.train_batch_size, accelerator.num_processes, what="chips")
    if accelerator.is_main_process:
        save_config(config, output_dir)
    return scaling, train_dataset, test_dataset


def _export(
    config: TrainVAEConfig,
    accelerator: Accelerator,
    model: AutoencoderKL,
    train_loader: DataLoader,
    test_dataset: ChipDataset,
    scaling: DecibelScaling,
    global_step: int,
) -> None:
    """The latent scaling factor, test-split PSNR/SSIM and the saved model; on the main process."""
    output_dir = Path(config.output_dir)
    model.register_to_config(scaling_factor=latent_scaling_factor(model, train_loader, SCALING_BATCHES))
    metrics = evaluate_reconstruction(model, test_dataset, config.num_eval_images, config.train_batch_size)
    architecture = {key: model.config[key] for key in (
        "block_out_channels", "layers_per_block", "latent_channels", "norm_num_groups")}  # fmt: skip
    metrics.update(scaling_factor=model.config.scaling_factor, steps=global_step, architecture=architecture)
    check_finite_step(global_step, scaling_factor=model.config.scaling_factor)
    check_finite_state({"vae": model}, what=str(output_dir / "vae"))
    write_json_atomic(metrics, output_dir / "metrics.json")
    model.save_pretrained(output_dir / "vae")
    write_json_atomic(scaling.to_dict(), output_dir / "vae" / SCALING_FILE)
    accelerator.log({"test/psnr_db": metrics["psnr_db"], "test/ssim": metrics["ssim"]}, step=global_step)
    logger.info("test reconstruction: PSNR %.2f dB, SSIM %.4f", metrics["psnr_db"], metrics["ssim"])
