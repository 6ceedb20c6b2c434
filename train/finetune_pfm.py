"""Fine-tune a zero-1-to-3 style SAR novel-view model with Projected Feature Matching (Eq. 21).

    accelerate launch train/finetune_pfm.py --encoder runs/simclr/encoder --pfm_weight 4 \\
        [--config finetune.yaml] [--data /path/to/mstar --protocol extended] [--flag value ...]

Training follows zero-1-to-3: the UNet sees ``[x_t, condition latent]`` (the condition latent is the
unscaled VAE posterior mode of the input view, only the target latent is scaled) and cross-attends to
``PoseProjection([CLIP image embedding, pose])``; AdamW with the pose projection at 10x the learning rate;
classifier-free-guidance dropout of 5% image embedding, 5% both, 5% condition latent. The loss is
``L_simple + pfm_weight * L_PFM`` (:func:`sar_zero123.losses.total_loss`); ``--pfm_weight 0`` is plain
zero-1-to-3 fine-tuning.

The CLIP image tower is frozen, as in zero-1-to-3, which is right on top of a pretrained tower. The
named ``--size`` models start from a *random* tower, whose embedding would stay a random projection of
the input chip; ``--train_image_encoder`` trains it with the UNet (float32 master weights, same learning
rate, in the EMA, the checkpoints and the exported pipeline).

Determinism and resuming: the data order comes from accelerate's seedable sampler (a function of the seed
and the epoch), the view pairs from ``ViewPairDataset.set_epoch`` and every random draw of a micro-batch
(noise, timesteps, VAE posterior sample, CFG dropout, PFM subset) from a generator seeded by
``(seed, micro-batch index, process index)``. A resumed run therefore needs no RNG state beyond the
checkpoint's step and reaches bitwise the weights of an uninterrupted run.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import PIL.Image
import torch
from accelerate import Accelerator
from diffusers import DDIMScheduler, DDPMScheduler, UNet2DConditionModel
from diffusers.optimization import get_scheduler
from diffusers.training_utils import EMAModel
from torch.utils.data import DataLoader
from tqdm.auto import tqdm

from sar_zero123.config import parse_config, save_config, write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling, check_protocol, train_validation_pairs
from sar_zero123.evaluators import Evaluators, load_evaluators
from sar_zero123.losses import DEFAULT_PFM_MIN_SNR, load_pfm_encoder
from sar_zero123.models import load_sar_zero123
from sar_zero123.pipeline import SARZero123Pipeline
from sar_zero123.run_state import (
    check_finite_state,
    check_finite_step,
    check_resume_config,
    end_run,
    load_checkpoint,
    read_run_state,
    resolve_resume_checkpoint,
    save_checkpoint,
)
from sar_zero123.runs import check_replicas_agree, start_run, tracker_hparams
from sar_zero123.training import (
    CachedViewPairs,
    ChipLatentCache,
    ImageEmbedder,
    compute_losses,
    load_chip_images,
    micro_batch_generator,
    timestep_bucket_losses,
)
from sar_zero123.validation import ema_weights, validate_pairs

logger = logging.getLogger(__name__)



@dataclass
class FinetuneConfig:
    """Fine-tune a SAR zero-1-to-3 model with Projected Feature Matching."""

    output_dir: str = "runs/finetune_pfm"  # run folder: checkpoints, logs, validation grids, final pipeline
    pretrained: str | None = None  # pipeline folder or zero-1-to-3 checkpoint; None: build `size`
    size: Literal["tiny", "micro", "compact", "small", "zero123"] = "small"  # built when pretrained is None
    image_size: int | None = None  # chip side in pixels; None uses the model's own
    pose_in_time_embedding: bool = False  # built sizes: the pose also enters the UNet's timestep embedding
    # built sizes: an AzimuthEstimator reads the input's azimuth, turned by d_az it enters the time embedding
    estimate_input_azimuth: bool = False
    azimuth_loss_weight: float = 1.0  # weight of the estimator's loss on the input chip's known azimuth
    input_code_dim: int = 16  # with estimate_input_azimuth: size of the estimator's code of the input view
    vae: str | None = None  # AutoencoderKL folder (train/train_vae.py) replacing the pipeline's VAE
    encoder: str | None = None  # frozen SAREncoder folder; required when pfm_weight > 0
    data: str | None = None  # dataset folder with index.csv; None simulates the built-in dataset
    protocol: str = "extended"  # split protocol: extended, soc or ood-<CLASS> (e.g. ood-T72)
    scaling: Literal["unit", "mstar_raw", "fit"] = "unit"  # dB bounds: unit magnitude, raw MSTAR, or fitted
    max_d_az_deg: float | None = None  # largest |d_az| of a training pair in degrees; None: any
    pfm_weight: float = 4.0  # lambda of Eq. (21); 0 = plain zero-1-to-3 fine-tuning
    pfm_min_snr: float = DEFAULT_PFM_MIN_SNR  # PFM only where SNR(t) >= this (0 = every timestep)
    pfm_fraction: float = 1.0  # fraction of the eligible batch on which PFM is computed
    pfm_crop_size: int | None = None  # centre crop in pixels for PFM (decodes only that latent window)
    pfm_projection_dim: int | None = None  # paper-comparable PFM: frozen random 512->k projection (paper: 10)
    learning_rate: float = 1e-4  # AdamW learning rate of the UNet
    pose_lr_multiplier: float = 10.0  # pose projection learning rate = this x learning_rate
    adam_weight_decay: float = 1e-2  # AdamW weight decay
    lr_scheduler: str = "constant"  # diffusers scheduler name (constant, constant_with_warmup, cosine, ...)
    lr_warmup_steps: int = 0  # warm-up optimisation steps
    train_batch_size: int = 4  # pairs per process per micro-batch
    gradient_accumulation_steps: int = 1  # micro-batches per optimisation step
    max_train_steps: int = 1000  # optimisation steps
    max_grad_norm: float = 1.0  # gradient clipping norm (all trained parameters together)
    mixed_precision: Literal["no", "fp16", "bf16"] = "no"  # frozen VAE/encoders are cast to this dtype
    gradient_checkpointing: bool = False  # checkpoint UNet activations
    train_image_encoder: bool = False  # train the CLIP image tower too: use it when training from scratch
    use_ema: bool = True  # EMA of the UNet (+ trained image tower): in checkpoints, validation, export
    ema_decay: float = 0.9999  # EMA decay
    drop_image_prob: float = 0.05  # CFG dropout: image embedding only (pose kept)
    drop_both_prob: float = 0.05  # CFG dropout: projected token and condition latent (the sampling null)
    drop_latent_prob: float = 0.05  # CFG dropout: condition latent only
    timestep_sampling: Literal["uniform", "logit_normal"] = "uniform"  # training t density (uniform: paper)
    timestep_logit_mean: float = 0.0  # logit_normal: mean of logit(t / T); > 0 favours high noise
    timestep_logit_std: float = 1.0  # logit_normal: standard deviation of logit(t / T)
    snr_gamma: float | None = None  # Min-SNR-gamma weighting of L_simple (e.g. 5); None: the paper's L_simple
    prediction_type: Literal["epsilon", "v_prediction"] | None = None  # built sizes only (None: epsilon)
    checkpointing_steps: int = 500  # save a resumable checkpoint every this many steps
    checkpoints_total_limit: int | None = None  # keep at most this many checkpoints
    resume_from_checkpoint: str | None = None  # 'latest' or a checkpoint folder
    validation_steps: int = 500  # validation grid and losses every this many steps (0: never)
    num_validation_images: int = 4  # validation pairs (rows of the grid)
    validation_inference_steps: int = 20  # DDIM steps for validation samples
    guidance_scale: float = 3.0  # CFG scale for validation samples
    num_workers: int = 0  # DataLoader workers
    report_to: str | None = "tensorboard"  # accelerate tracker; None disables logging
    seed: int = 0  # seed of initialisation, data order and every random draw
    save_pipeline: bool = True  # save_pretrained the final SARZero123Pipeline into output_dir/pipeline
    evaluators: str | None = None  # train_evaluators.py folder: validation also checks pose following
    cache_latents: bool = True  # encode every training chip once with the frozen VAE (and frozen CLIP tower)

    def __post_init__(self) -> None:
        if not self.pfm_weight >= 0:
            raise ValueError(f"pfm_weight must be >= 0, got {self.pfm_weight}")
        if self.pfm_weight > 0 and self.encoder is None:
            raise ValueError("encoder: a frozen SAREncoder folder is required when pfm_weight > 0")
        if self.pfm_min_snr < 0:
            raise ValueError(f"pfm_min_snr must be >= 0, got {self.pfm_min_snr}")
        if not 0 < self.pfm_fraction <= 1:
            raise ValueError(f"pfm_fraction must be in (0, 1], got {self.pfm_fraction}")
        if self.pfm_projection_dim is not None and self.pfm_projection_dim < 1:
            raise ValueError(f"pfm_projection_dim must be >= 1 or None, got {self.pfm_projection_dim}")
        if self.pfm_crop_size is not None and self.pfm_crop_size < 1:
            raise ValueError(f"pfm_crop_size must be >= 1 or None, got {self.pfm_crop_size}")
        check_protocol(self.protocol)
        for name in ("learning_rate", "pose_lr_multiplier", "max_grad_norm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in (
            "train_batch_size",
            "gradient_accumulation_steps",
            "max_train_steps",
            "checkpointing_steps",
            "num_validation_images",
            "validation_inference_steps",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("lr_warmup_steps", "validation_steps", "num_workers"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.checkpoints_total_limit is not None and self.checkpoints_total_limit < 1:
            raise ValueError(
                f"checkpoints_total_limit must be >= 1 or None, got {self.checkpoints_total_limit}"
            )
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        probs = (self.drop_image_prob, self.drop_both_prob, self.drop_latent_prob)
        if min(probs) < 0 or sum(probs) > 1:
            raise ValueError(
                f"drop_image_prob, drop_both_prob, drop_latent_prob must be >= 0 with sum <= 1, got {probs}"
            )
        if self.prediction_type is not None and self.pretrained is not None:
            raise ValueError(
                "prediction_type: only for a model built from scratch (--size); a pretrained checkpoint "
                "keeps the prediction type it was trained with"
            )
        if self.snr_gamma is not None and not self.snr_gamma > 0:
            raise ValueError(f"snr_gamma must be > 0 or None, got {self.snr_gamma}")
        if self.image_size is not None and self.image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {self.image_size}")


# ----------------------------------------------------------------------------------------- building
def resolve_image_size(config: FinetuneConfig, pipe: SARZero123Pipeline) -> int:
    """Chip side for training; must be a multiple of the pipeline's total downsampling.

    Raises:
        ValueError: If it is not.
    """
    image_size = config.image_size if config.image_size is not None else pipe.default_image_size
    if image_size % pipe.size_multiple:
        raise ValueError(f"image_size must be a multiple of {pipe.size_multiple}, got {image_size}")
    return image_size


def export_pipeline(pipe: SARZero123Pipeline, scaling: DecibelScaling, directory: Path) -> Path:
    """``save_pretrained`` of the complete pipeline (float32) plus the ``DecibelScaling`` it expects."""
    check_finite_state(pipe.components, what=str(directory))
    pipe.to(torch.float32)
    pipe.save_pretrained(directory)
    write_json_atomic(scaling.to_dict(), directory / SCALING_FILE)
    return directory


# ------------------------------------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> Path:
    """Run a fine-tune; returns the run folder."""
    config = parse_config(FinetuneConfig, argv)
    output_dir = Path(config.output_dir)
    accelerator = start_run(
        output_dir,
        seed=config.seed,
        mixed_precision=config.mixed_precision,
        report_to=config.report_to,
        gradient_accumulation_steps=config.gradient_accumulation_steps,
    )

    # 1. check every input before any training step
    resume_path = resolve_resume_checkpoint(output_dir, config.resume_from_checkpoint)
    if resume_path is not None:  # the checkpoint's module list must match this run's
        written_with = bool(read_run_state(resume_path).get("train_image_encoder", False))
        if written_with != config.train_image_encoder:
            raise ValueError(
                f"resume_from_checkpoint: {str(resume_path)!r} was written with "
                f"train_image_encoder={written_with}; resume it with the same setting"
            )
    # the LR schedule of a constant scheduler does not depend on the step count: such runs may be extended
    extendable = ("max_train_steps",) if config.lr_scheduler in ("constant", "constant_with_warmup") else ()
    check_resume_config(resume_path, config, may_differ=("guidance_scale", *extendable))
    pipe = load_sar_zero123(
        config.pretrained,
        size=config.size,
        image_size=config.image_size,
        seed=config.seed,
        pose_in_time_embedding=config.pose_in_time_embedding,
        estimate_input_azimuth=config.estimate_input_azimuth,
        input_code_dim=config.input_code_dim,
        prediction_type=config.prediction_type,
        vae=config.vae,
    )
    image_size = resolve_image_size(config, pipe)
    encoder = None
    if config.pfm_weight > 0:
        encoder = load_pfm_encoder(
            config.encoder, image_size=image_size, projection_dim=config.pfm_projection_dim, seed=config.seed
        )
    train_dataset, validation_dataset, scaling = train_validation_pairs(
        config.data,
        config.protocol,
        output_dir / "data",
        image_size=image_size,
        scaling=config.scaling,
        max_d_az_deg=config.max_d_az_deg,
        num_validation_pairs=config.num_validation_images,
        seed=config.seed,
    )
    evaluators = None
    if config.evaluators is not None and config.validation_steps:
        evaluators = load_evaluators(config.evaluators)  # pose following reads only the regressor
    if len(train_dataset) < config.train_batch_size * accelerator.num_processes:
        raise ValueError(
            f"data: {len(train_dataset)} training pairs, fewer than one global batch of "
            f"{config.train_batch_size * accelerator.num_processes}"
        )
    if config.pfm_crop_size is not None:
        factor = pipe.vae_scale_factor
        if config.pfm_crop_size > image_size or (image_size - config.pfm_crop_size) % (2 * factor):
            raise ValueError(
                f"pfm_crop_size must be <= {image_size} with image_size - pfm_crop_size a "
                f"multiple of {2 * factor}, got {config.pfm_crop_size}"
            )
    if accelerator.is_main_process:
        output_dir.mkdir(parents=True, exist_ok=True)
        save_config(config, output_dir)
        if encoder is not None and config.pfm_projection_dim is not None:
            encoder.save_projection(output_dir)

    # 2. frozen parts in the weight dtype, trainable parts in float32
    weight_dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}.get(
        accelerator.mixed_precision, torch.float32
    )
    vae = pipe.vae.to(accelerator.device, dtype=weight_dtype).eval().requires_grad_(False)
    if config.train_image_encoder:
        image_encoder = ImageEmbedder(pipe.image_encoder.to(accelerator.device, dtype=torch.float32))
        image_encoder.train().requires_grad_(True)
    else:
        image_encoder = ImageEmbedder(
            pipe.image_encoder.to(accelerator.device, dtype=weight_dtype).eval().requires_grad_(False)
        )
    if encoder is not None:
        encoder = encoder.to(accelerator.device, dtype=weight_dtype)
    if config.cache_latents:  # the VAE (and a frozen tower) never change: encode each chip once
        frozen_tower = None if config.train_image_encoder else image_encoder.image_encoder
        cache = ChipLatentCache.encode(load_chip_images(train_dataset), vae, frozen_tower)
        train_dataset = CachedViewPairs(train_dataset, cache)
    unet, pose_projection = pipe.unet.train(), pipe.pose_projection.train()
    unet.requires_grad_(True)
    pose_projection.requires_grad_(True)
    azimuth_estimator = pipe.azimuth_estimator
    if azimuth_estimator is not None:
        azimuth_estimator.train().requires_grad_(True)
    if config.gradient_checkpointing:
        unet.enable_gradient_checkpointing()
    noise_scheduler = DDPMScheduler.from_config(pipe.scheduler.config)
    ema_unet = None
    if config.use_ema:
        ema_unet = EMAModel(
            unet.parameters(),
            decay=config.ema_decay,
            model_cls=UNet2DConditionModel,
            model_config=unet.config,
        )
        ema_unet.to(accelerator.device)
        accelerator.register_for_checkpointing(ema_unet)
    ema_image_encoder = None
    if config.use_ema and config.train_image_encoder:
        # the exported UNet is the EMA one; its conditioning tower must be averaged over the same steps
        ema_image_encoder = EMAModel(image_encoder.parameters(), decay=config.ema_decay)
        ema_image_encoder.to(accelerator.device)
        accelerator.register_for_checkpointing(ema_image_encoder)

    # 3. optimiser: the pose projection at pose_lr_multiplier x the learning rate, the image tower (if
    #    trained) at the learning rate
    param_groups = [
        {"params": list(unet.parameters()), "lr": config.learning_rate},
        {
            "params": list(pose_projection.parameters()),
            "lr": config.learning_rate * config.pose_lr_multiplier,
        },
    ]
    if config.train_image_encoder:
        param_groups.append({"params": list(image_encoder.parameters()), "lr": config.learning_rate})
    if azimuth_estimator is not None:
        param_groups.append({"params": list(azimuth_estimator.parameters()), "lr": config.learning_rate})
    optimizer = torch.optim.AdamW(param_groups, weight_decay=config.adam_weight_decay)
    lr_scheduler = get_scheduler(
        config.lr_scheduler,
        optimizer,
        num_warmup_steps=config.lr_warmup_steps * accelerator.num_processes,
        num_training_steps=config.max_train_steps * accelerator.num_processes,
    )
    train_dataloader = DataLoader(
        train_dataset,
        batch_size=config.train_batch_size,
        shuffle=True,
        drop_last=True,
        num_workers=config.num_workers,
    )
    unet, pose_projection, optimizer, train_dataloader, lr_scheduler = accelerator.prepare(
        unet, pose_projection, optimizer, train_dataloader, lr_scheduler
    )
    # prepared after the others so that the checkpoints of a frozen-tower run keep their file names
    trained_modules = [unet, pose_projection]
    if config.train_image_encoder:
        image_encoder = accelerator.prepare(image_encoder)
        trained_modules.append(image_encoder)
    if azimuth_estimator is not None:
        azimuth_estimator = accelerator.prepare(azimuth_estimator)
        trained_modules.append(azimuth_estimator)
    if len(train_dataloader) == 0:
        raise ValueError("data: the training split yields no full batch on each process")
    validation_batch = next(iter(DataLoader(validation_dataset, batch_size=config.num_validation_images)))

    # 4. resume
    global_step = 0
    if resume_path is not None:
        state = load_checkpoint(accelerator, resume_path)
        global_step = int(state["step"])
        logger.info("resumed from %s at step %d", resume_path, global_step)
    accelerator.init_trackers("finetune_pfm", config=tracker_hparams(config))

    # 5. training loop
    batches_per_epoch = len(train_dataloader)
    batch_index = global_step * config.gradient_accumulation_steps
    trainable = [parameter for module in trained_modules for parameter in module.parameters()]
    progress = tqdm(
        total=config.max_train_steps,
        initial=global_step,
        desc="steps",
        disable=not accelerator.is_local_main_process,
    )
    frozen_modules = dict(
        vae=vae,
        encoder=encoder,
        noise_scheduler=noise_scheduler,
        pfm_weight=config.pfm_weight,
        pfm_min_snr=config.pfm_min_snr,
        pfm_fraction=config.pfm_fraction,
        pfm_crop_size=config.pfm_crop_size,
        drop_image_prob=config.drop_image_prob,
        drop_both_prob=config.drop_both_prob,
        drop_latent_prob=config.drop_latent_prob,
        timestep_sampling=config.timestep_sampling,
        timestep_logit_mean=config.timestep_logit_mean,
        timestep_logit_std=config.timestep_logit_std,
        snr_gamma=config.snr_gamma,
        azimuth_loss_weight=config.azimuth_loss_weight,
    )
    while global_step < config.max_train_steps:
        epoch, offset = divmod(batch_index, batches_per_epoch)
        train_dataset.set_epoch(epoch)
        train_dataloader.set_epoch(epoch)
        loader = accelerator.skip_first_batches(train_dataloader, offset) if offset else train_dataloader
        for batch in loader:
            with accelerator.accumulate(*trained_modules):
                generator = micro_batch_generator(config.seed, batch_index, accelerator.process_index)
                losses = compute_losses(
                    batch,
                    unet=unet,
                    pose_projection=pose_projection,
                    image_encoder=image_encoder,
                    azimuth_estimator=azimuth_estimator,
                    generator=generator,
                    **frozen_modules,
                )
                loss = losses.loss.mean()
                accelerator.backward(loss)
                if accelerator.sync_gradients:
                    accelerator.clip_grad_norm_(trainable, config.max_grad_norm)
                optimizer.step()
                lr_scheduler.step()
                optimizer.zero_grad(set_to_none=True)
            batch_index += 1
            if not accelerator.sync_gradients:
                continue
            global_step += 1
            if ema_unet is not None:
                ema_unet.step(unet.parameters())
            if ema_image_encoder is not None:
                ema_image_encoder.step(image_encoder.parameters())
            progress.update(1)
            logs = {
                "train/loss": accelerator.gather(losses.loss.detach()).mean().item(),
                "train/loss_simple": accelerator.gather(losses.denoising.detach()).mean().item(),
                "train/loss_pfm": accelerator.gather(losses.pfm.detach()).mean().item(),
                **(
                    {"train/loss_azimuth": accelerator.gather(losses.azimuth.detach()).mean().item()}
                    if losses.azimuth is not None
                    else {}
                ),
                "lr": lr_scheduler.get_last_lr()[0],
            }
            buckets = timestep_bucket_losses(
                accelerator.gather(losses.denoising.detach()),
                accelerator.gather(losses.timesteps),
                noise_scheduler.config.num_train_timesteps,
            )
            logs.update({f"train/loss_simple_{name}": value for name, value in buckets.items()})
            progress.set_postfix(loss=f"{logs['train/loss']:.4f}")
            accelerator.log(logs, step=global_step)
            check_finite_step(global_step, loss=logs["train/loss"])  # gathered: every process stops
            if global_step % config.checkpointing_steps == 0 or global_step == config.max_train_steps:
                save_checkpoint(
                    accelerator,
                    output_dir,
                    global_step,
                    config.checkpoints_total_limit,
                    extra_state={
                        "epoch": epoch,
                        "batch_index": batch_index,
                        "train_image_encoder": config.train_image_encoder,
                    },
                    config=config,
                )
            if config.validation_steps and global_step % config.validation_steps == 0:
                if accelerator.is_main_process:
                    ema_pairs = [
                        (ema_unet, accelerator.unwrap_model(unet)),
                        (ema_image_encoder, accelerator.unwrap_model(image_encoder)),
                    ]
                    validate(
                        accelerator,
                        pipe,
                        image_encoder,
                        ema_pairs,
                        validation_batch,
                        frozen_modules,
                        config,
                        global_step,
                        evaluators,
                    )
                accelerator.wait_for_everyone()
            if global_step >= config.max_train_steps:
                break
    progress.close()

    # 6. replica check, then export the complete pipeline (EMA weights in the UNet and a trained tower)
    accelerator.wait_for_everyone()
    trained = [accelerator.unwrap_model(module) for module in trained_modules]
    digests = check_replicas_agree(accelerator, trained)
    if accelerator.is_main_process:
        write_json_atomic(
            {"global_step": global_step, "image_size": image_size, "replica_weight_digests": digests},
            output_dir / "train_state.json",
        )
    if accelerator.is_main_process and config.save_pipeline:
        final_unet = trained[0]
        if ema_unet is not None:
            ema_unet.copy_to(final_unet.parameters())
        final_image_encoder = accelerator.unwrap_model(image_encoder).image_encoder
        if ema_image_encoder is not None:
            ema_image_encoder.copy_to(final_image_encoder.parameters())
        export = SARZero123Pipeline(
            vae=vae,
            image_encoder=final_image_encoder.eval(),
            unet=final_unet.eval(),
            scheduler=DDIMScheduler.from_config(pipe.scheduler.config),
            pose_projection=trained[1].eval(),
            feature_extractor=pipe.feature_extractor,
            azimuth_estimator=None if azimuth_estimator is None else trained[-1].eval(),
        )
        export_pipeline(export, scaling, output_dir / "pipeline")
    accelerator.wait_for_everyone()
    # no reference to a data-parallel wrapper (or a graph through one) may outlive the process group
    unet = pose_projection = image_encoder = azimuth_estimator = trained_modules = losses = loss = None
    end_run(accelerator)
    return output_dir


def validate(
    accelerator: Accelerator,
    pipe: SARZero123Pipeline,
    image_encoder,
    ema_pairs: list,
    batch: dict,
    loss_kwargs: dict,
    config: FinetuneConfig,
    step: int,
    evaluators: Evaluators | None = None,
) -> Path:
    """Validation with EMA weights swapped in: ``validation/step-<step>.png``, logs, ``metrics.jsonl``."""
    with ema_weights(ema_pairs):
        logs, grid = validate_pairs(
            batch,
            pipe=pipe,
            image_embedder=accelerator.unwrap_model(image_encoder),
            loss_kwargs=loss_kwargs,
            seed=config.seed,
            num_inference_steps=config.validation_inference_steps,
            guidance_scale=config.guidance_scale,
            regressor=None if evaluators is None else evaluators.regressor,
        )
    path = Path(config.output_dir) / "validation" / f"step-{step:06d}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    PIL.Image.fromarray(grid).save(path)
    if config.report_to == "tensorboard":
        accelerator.get_tracker("tensorboard").log_images(
            {"validation/input_generated_target": grid[None, ..., None]}, step=step, dataformats="NHWC"
        )
    accelerator.log(logs, step=step)
    logger.info("validation step %d: %s", step, json.dumps(logs))
    with open(path.parent / "metrics.jsonl", "a") as stream:
        stream.write(json.dumps({"step": step, **logs}) + "\n")
    return path


if __name__ == "__main__":
    main()
