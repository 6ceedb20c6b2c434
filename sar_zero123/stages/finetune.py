"""The fine-tune stage: a zero-1-to-3 style SAR novel-view model trained with
``L_simple + pfm_weight * L_PFM`` (Eq. 21); ``pfm_weight = 0`` is plain zero-1-to-3 fine-tuning.

The CLIP image tower is frozen as in zero-1-to-3; a built ``size`` starts from a random tower, which
``train_image_encoder`` trains with the UNet. Resuming reaches bitwise the weights of an uninterrupted run:
data order, pairs and every draw are functions of the seed and the step (``runs.checkpoints``).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from accelerate import Accelerator
from diffusers import DDPMScheduler
from diffusers.optimization import get_scheduler
from torch.utils.data import DataLoader

from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import (
    MixedPairs,
    ViewPairDataset,
    check_protocol,
    subsample_objects,
    train_validation_pairs,
)
from sar_zero123.data.corpus_proxies import corpus_proxies_have_oracle, load_corpus_proxies
from sar_zero123.evaluation.evaluators import load_evaluators
from sar_zero123.model.build import load_sar_zero123, record_trained_pose_ranges
from sar_zero123.model.conditioning import SPATIAL_POSE_MODES, vae_signature
from sar_zero123.model.input_tokens import enable_input_tokens, uses_input_tokens
from sar_zero123.model.reference_attention import enable_reference_attention, uses_reference
from sar_zero123.model.spatial_pose import (
    proxy_condition_views,
    proxy_form,
    takes_proxy,
    use_proxy_geometry,
    widen_for_proxy,
)
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.runs.checkpoints import (
    RESUME_MAY_DIFFER,
    check_resume_config,
    check_resume_state,
    check_resume_steps,
    end_run,
    read_run_state,
    resolve_resume_checkpoint,
    resume_step,
)
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run, weights_identity
from sar_zero123.runs.launch import check_global_batch, check_replicas_agree, start_run, tracker_hparams
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.sim.corpus import CORPUS_OPTIONS_FILE, VALIDATION_CLASS
from sar_zero123.training.finetuning import (
    FinetuneInputs,
    FinetuneTrainer,
    ema_models,
    export_finetuned,
    finetuning_modules,
    finetuning_optimizer,
    mixed_precision_dtype,
    train_finetune_steps,
    training_image_size,
)
from sar_zero123.training.latent_cache import (
    CachedViewPairs,
    ChipLatentCache,
    collate_pairs,
    load_chip_images,
)
from sar_zero123.training.losses import TRAINED_PREDICTION_TYPES, LossSettings, check_prediction_type
from sar_zero123.training.pfm import load_pfm_encoder
from sar_zero123.training.step import MAX_GRAD_NORM
from sar_zero123.training.validation import VALIDATION_GUIDANCE_SCALE

logger = logging.getLogger(__name__)

__all__ = ["FinetuneConfig", "check_lr_scheduler", "run_finetune"]

#: AdamW's weight decay (torch's default).
ADAM_WEIGHT_DECAY = 1e-2
#: Schedulers whose learning rate does not depend on the step count: their runs may be extended.
CONSTANT_LR_SCHEDULERS = ("constant", "constant_with_warmup")


def check_lr_scheduler(name: str) -> None:
    """Refuse a schedule diffusers' ``get_scheduler`` does not know (``piecewise_constant`` has no field)."""
    from diffusers.optimization import SchedulerType

    names = [item.value for item in SchedulerType if item is not SchedulerType.PIECEWISE_CONSTANT]
    if name not in names:
        raise ValueError(f"lr_scheduler must be one of {names}, got {name!r}")


@dataclass
class FinetuneConfig(LossSettings):
    """Fine-tune a SAR zero-1-to-3 model with Projected Feature Matching.

    The loss fields are :class:`~sar_zero123.training.losses.LossSettings`'s, inherited.
    """

    ADVANCED_FIELDS = (
        "estimate_input_azimuth", "input_code_dim", "rehearsal_max_chips",
        "input_depression", "pose_lr_multiplier", "lr_scheduler", "lr_warmup_steps",
        "gradient_accumulation_steps", "mixed_precision", "gradient_checkpointing",
        "train_image_encoder", "use_ema", "ema_decay", "prediction_type", "checkpointing_steps",
        "logging_steps", "checkpoints_total_limit", "validation_steps", "num_validation_images",
        "validation_inference_steps", "num_workers", "report_to", "save_pipeline",
        "cache_latents", "cache_on_device", "resume_from_checkpoint",
    )  # fmt: skip

    output_dir: str = "runs/finetune_pfm"  # run folder: checkpoints, logs, validation grids, final pipeline
    pretrained: str | None = None  # pipeline folder or zero-1-to-3 checkpoint; None: build `size`
    # built when pretrained is None
    size: Literal["tiny", "micro", "compact", "small", "medium", "zero123"] = "small"
    image_size: int | None = None  # chip side in pixels; None uses the model's own
    # built sizes: an AzimuthEstimator's reading of the input's azimuth, turned by d_az, enters the UNet
    estimate_input_azimuth: bool = False
    input_code_dim: int = 16  # with estimate_input_azimuth: size of the estimator's code of the input view
    vae: str | None = None  # AutoencoderKL folder (train/train_vae.py) replacing the pipeline's VAE
    encoder: str | None = None  # frozen SAREncoder folder; required when pfm_weight > 0
    data: str | None = None  # dataset folder with index.csv; None simulates the built-in dataset
    protocol: str = "extended"  # split protocol: extended, soc or ood-<CLASS> (e.g. ood-T72)
    scaling: Literal["unit", "mstar_raw", "fit"] = "unit"  # dB bounds: unit magnitude, raw MSTAR, or fitted
    same_depression: bool = True  # pair only chips at one depression; False also across (d_el != 0)
    # a prior corpus whose pairs are mixed into training, so the fine-tune keeps the prior's; None: task only
    rehearsal_data: str | None = None
    rehearsal_fraction: float = 0.25  # with rehearsal_data: share of the training pairs drawn from it
    rehearsal_max_chips: int | None = 4096  # rehearsal: whole vehicles up to this many chips; None: all
    # built sizes: the pose's 4th entry is the input chip's absolute depression (Stable Zero123's convention)
    input_depression: bool = False
    # built sizes: the UNet also takes the input latent turned by d_az ("rotated_input"); None: zero-1-to-3's
    spatial_pose: str | None = None
    proxies: str | None = None  # spatial_pose 'proxy': folder of data's proxies (None: data itself)
    # every self-attention also attends to the input's features (a reference pass; added with zero gates)
    reference_attention: bool = False
    # every cross-attention also attends to the input's latent, a token per place (added with zero gates)
    input_tokens: bool = False
    # a proxy model reads each proxy as its shadow, ground and lit masks, not the simulator's intensities
    proxy_geometry: bool = False
    pfm_projection_dim: int | None = None  # paper-comparable PFM: frozen random 512->k projection (paper: 10)
    learning_rate: float = 1e-4  # AdamW learning rate of the UNet
    pose_lr_multiplier: float = 10.0  # pose projection learning rate = this x learning_rate
    lr_scheduler: str = "constant"  # diffusers scheduler name (constant, constant_with_warmup, cosine, ...)
    lr_warmup_steps: int = 0  # warm-up optimisation steps
    train_batch_size: int = 4  # pairs per process per micro-batch
    gradient_accumulation_steps: int = 1  # micro-batches per optimisation step
    max_train_steps: int = 1000  # optimisation steps
    # stop after this many minutes of steps: checkpoint, export, leave the run for --resume
    max_train_minutes: float | None = None
    mixed_precision: Literal["no", "fp16", "bf16"] = "no"  # frozen VAE/encoders are cast to this dtype
    gradient_checkpointing: bool = False  # checkpoint UNet activations
    train_image_encoder: bool = False  # train the CLIP image tower too: use it when training from scratch
    use_ema: bool = True  # EMA of the UNet (+ trained image tower): in checkpoints, validation, export
    ema_decay: float = 0.9999  # EMA decay
    prediction_type: Literal["epsilon", "v_prediction"] | None = None  # built sizes only (None: epsilon)
    checkpointing_steps: int = 500  # save a resumable checkpoint every this many steps
    # log and check finite the losses every this many steps (each a host-device synchronisation)
    logging_steps: int = 10
    checkpoints_total_limit: int | None = None  # keep at most this many checkpoints
    resume_from_checkpoint: str | None = None  # 'latest' or a checkpoint folder
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over
    validation_steps: int = 500  # validation grid and losses every this many steps (0: never)
    num_validation_images: int = 4  # validation pairs (rows of the grid)
    validation_inference_steps: int = 20  # DDIM steps for validation samples
    num_workers: int = 0  # DataLoader workers
    report_to: str | None = "tensorboard"  # accelerate tracker; None disables logging
    seed: int = 0  # seed of initialisation, data order and every random draw
    save_pipeline: bool = True  # save_pretrained the final SARZero123Pipeline into output_dir/pipeline
    evaluators: str | None = None  # train_evaluators.py folder: validation also checks pose following
    cache_latents: bool = True  # encode every training chip once with the frozen VAE (and frozen CLIP tower)
    # keep that cache on the training device and draw batches there (num_workers unused)
    cache_on_device: bool = False

    REMOVED_FIELDS = {
        "pfm_start_step": RemovedField(0, "PFM switched on after a stretch of L_simple alone kept the seen "
                                       "class less often than PFM from the first step; PFM applies in "
                                       "every step"),
        "pfm_stop_step": RemovedField(None, "PFM switched off early damaged the seen classes as much as "
                                      "PFM throughout; PFM applies in every step"),
        "pfm_monotonic_q": RemovedField(0, "random monotonic maps before PFM's encoder changed nothing "
                                        "measurable; PFM compares the images as Eq. 20 does"),
        "adam_weight_decay": RemovedField(1e-2, f"AdamW's weight decay is {ADAM_WEIGHT_DECAY:g}"),
        "pose_in_time_embedding": RemovedField(
            False, "the pose in the UNet's timestep embedding alone made no model built from scratch "
            "follow the pose; estimate_input_azimuth does"
        ),
        "max_d_az_deg": RemovedField(None, "every pair of views of one object trains, whatever its |d_az|"),
        "guidance_scale": RemovedField(3.0, "validation samples are guided at "
                                       f"{VALIDATION_GUIDANCE_SCALE} (the sampling commands set their own)"),
        "max_grad_norm": RemovedField(1.0, f"gradients are clipped to a norm of {MAX_GRAD_NORM}"),
        "pfm_features": RemovedField("pooled", "unit-length and all-stage (LPIPS-style) features beat "
                                     "neither Eq. 20's pooled feature nor lambda = 0 on seen accuracy"),
        "pfm_snr_gamma": RemovedField(None, "PFM weighted by SNR gave no unseen gain over Eq. 21's equal "
                                      "weight"),
        "lora_rank": RemovedField(None, "a low-rank update kept the prior no better than a lower "
                                  "learning_rate does, at more cost; every UNet weight trains"),
        "lora_alpha": RemovedField(None, "LoRA's scale; LoRA was removed with lora_rank"),
        "lora_modules": RemovedField("all", "LoRA's layer set; LoRA was removed with lora_rank"),
        "pfm_balance": RemovedField("none", "rescaling PFM to L_simple's gradient cost nothing and gained "
                                    "nothing; PFM is weighted by Eq. 21's fixed lambda (pfm_weight)"),
        "timestep_sampling": RemovedField("uniform", "logit-normal timesteps did not make the model follow "
                                          "the pose more; t is drawn uniformly, as in the paper"),
        "timestep_logit_mean": RemovedField(0.0, "with timestep_sampling only; t is drawn uniformly"),
        "timestep_logit_std": RemovedField(1.0, "with timestep_sampling only; t is drawn uniformly"),
        "pfm_crop_size": RemovedField(None, "PFM on a centre crop's latent window gave gradients unlike the "
                                      "full image's (the VAE's attention sees only the window); PFM decodes "
                                      "the whole latent"),
    }  # fmt: skip

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.pfm_weight > 0 and self.encoder is None:
            raise ValueError("encoder: a frozen SAREncoder folder is required when pfm_weight > 0")
        if self.cache_on_device and not self.cache_latents:
            raise ValueError("cache_on_device: keeps the cached encodings on the device; needs cache_latents")
        check_protocol(self.protocol)
        check_minimum(self, "learning_rate", "pose_lr_multiplier", minimum=0, strict=True)
        check_minimum(self, "lr_warmup_steps", "validation_steps", "num_workers", minimum=0)
        check_lr_scheduler(self.lr_scheduler)
        counts = ("train_batch_size", "gradient_accumulation_steps", "max_train_steps", "checkpointing_steps",
                  "logging_steps", "num_validation_images", "validation_inference_steps")  # fmt: skip
        check_minimum(self, *counts, minimum=1)
        check_minimum(self, "pfm_projection_dim", "checkpoints_total_limit", minimum=1, optional=True)
        check_minimum(self, "image_size", minimum=8, optional=True)
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        check_minimum(self, "max_train_minutes", minimum=0, strict=True, optional=True)
        if not 0.0 <= self.rehearsal_fraction < 1.0:
            raise ValueError(f"rehearsal_fraction must lie in [0, 1), got {self.rehearsal_fraction}")
        if self.rehearsal_max_chips is not None and self.rehearsal_max_chips < 2:
            raise ValueError(f"rehearsal_max_chips must be None or >= 2, got {self.rehearsal_max_chips}")
        if self.spatial_pose not in SPATIAL_POSE_MODES:
            raise ValueError(f"spatial_pose must be one of {SPATIAL_POSE_MODES}, got {self.spatial_pose!r}")
        if self.proxy_geometry and self.pretrained is None and self.spatial_pose != "proxy":
            raise ValueError(
                "proxy_geometry: only a spatial_pose='proxy' model reads a proxy; got a model built with "
                f"spatial_pose={self.spatial_pose!r}"
            )
        if self.spatial_pose not in (None, "proxy") and self.pretrained is not None:
            raise ValueError(
                "spatial_pose: only for a model built from scratch (--size), or 'proxy' (a 'rotated_input' "
                "pipeline widened to take the simulator proxy); a pretrained pipeline keeps its condition "
                "input (pose_projection.config.spatial_pose)"
            )
        if self.spatial_pose == "proxy":
            for name, ok, expected in (
                ("cache_latents", self.cache_latents, "True (the proxies are cached with the chips)"),
                ("validation_steps", self.validation_steps == 0, "0 (validation pairs carry no proxies)"),
                (
                    "rehearsal_data",
                    self.rehearsal_data is None,
                    "None (a rehearsal corpus carries no proxies)",
                ),
            ):
                if not ok:
                    raise ValueError(
                        f"{name}: spatial_pose='proxy' needs {expected}, got {getattr(self, name)!r}"
                    )
        if self.input_depression and self.pretrained is not None:
            raise ValueError(
                "input_depression: only for a model built from scratch (--size); a pretrained pipeline keeps "
                "its pose convention (pose_projection.config.input_depression)"
            )
        if self.prediction_type is not None:
            check_prediction_type(self.prediction_type, TRAINED_PREDICTION_TYPES)
        if self.prediction_type is not None and self.pretrained is not None:
            raise ValueError(
                "prediction_type: only for a model built from scratch (--size); a pretrained checkpoint "
                "keeps the prediction type it was trained with"
            )
        if self.restart and self.resume_from_checkpoint is not None:
            raise ValueError("restart: starts over; it cannot be combined with resume_from_checkpoint")

    def loss_settings(self) -> LossSettings:
        """The settings of the training step's loss."""
        names = [item.name for item in dataclasses.fields(LossSettings)]
        return LossSettings(**{name: getattr(self, name) for name in names})

    def extendable_fields(self) -> tuple[str, ...]:
        """Fields a resumed run may change: ``max_train_steps`` when the learning rate ignores the steps."""
        return ("max_train_steps",) if self.lr_scheduler in CONSTANT_LR_SCHEDULERS else ()


def _lineage(config: FinetuneConfig) -> dict[str, str] | None:
    """The ``pretrained`` start's name and weight digests (``None`` for a model built from scratch)."""
    if config.pretrained is None:
        return None
    start = resolve_pretrained(config.pretrained)
    return {"start": str(config.pretrained), "start_weights": weights_identity(start)}


def run_finetune(config: FinetuneConfig) -> Path:
    """Fine-tune (or continue, or extend) a run in ``config.output_dir``; returns the run folder.

    Raises:
        ValueError: Before any work, for a folder the run-folder rule refuses, a checkpoint written with
            other settings, or a data split smaller than one optimisation step.
        FileNotFoundError: For a missing model, encoder, VAE, data or rehearsal corpus folder.
        FloatingPointError: If training diverges (nothing non-finite is saved or exported).
    """
    timer = StageTimer()
    output_dir = Path(config.output_dir)
    # checked here, not in the config: a quickstart plans its fine-tunes before its corpus stage writes it
    rehearsal = config.rehearsal_data
    if rehearsal is not None and not (Path(rehearsal) / CORPUS_OPTIONS_FILE).is_file():
        raise FileNotFoundError(
            f"rehearsal_data: expected a prior corpus folder (with {CORPUS_OPTIONS_FILE}, written by "
            f"write_prior_corpus), got {config.rehearsal_data}"
        )
    # 1. the checkpoint to continue from, compared with this run (reads only), then the run-folder rule
    resume_path = resolve_resume_checkpoint(output_dir, config.resume_from_checkpoint)
    check_resume_state(resume_path, "train_image_encoder", config.train_image_encoder, default=False)
    extendable = config.extendable_fields()
    check_resume_config(resume_path, config, may_differ=("restart", *extendable))
    check_resume_steps(resume_path, config.max_train_steps)
    folder = open_stage_folder(
        output_dir, "finetune", config, data={"data": data_identity(config.data)},
        resume=config.resume_from_checkpoint is not None, restart=config.restart,
        may_differ=(*RESUME_MAY_DIFFER, "restart"), may_extend=extendable,
    )  # fmt: skip
    if folder.finished:
        logger.info("%s: this fine-tune is finished; nothing to do", output_dir)
        return output_dir
    accelerator = start_run(
        output_dir,
        seed=config.seed,
        mixed_precision=config.mixed_precision,
        report_to=config.report_to,
        gradient_accumulation_steps=config.gradient_accumulation_steps,
    )
    # 2. inputs, modules, optimiser and data, every input checked before the first step
    with withdrawn_if_setup_fails(folder):
        inputs = _load_inputs(config, accelerator)
        trainer = _prepare_training(config, accelerator, inputs, resume_path)
    # 3. training, then the exported pipeline and the record
    global_step = train_finetune_steps(config, accelerator, inputs, trainer)
    outputs = _export(config, accelerator, inputs, trainer, global_step)
    if accelerator.is_main_process and global_step >= config.max_train_steps:  # else stopped by the clock
        finish_run(folder, outputs, seconds=timer.seconds, results={"final_step": global_step})
    accelerator.wait_for_everyone()
    trainer = None  # no data-parallel wrapper may outlive the process group
    end_run(accelerator)
    return output_dir


def _load_inputs(config: FinetuneConfig, accelerator: Accelerator) -> FinetuneInputs:
    """The model, the PFM encoder and the data, checked against each other; writes ``config.json``."""
    output_dir = Path(config.output_dir)
    pipe = load_sar_zero123(
        config.pretrained,
        size=config.size,
        image_size=config.image_size,
        seed=config.seed,
        estimate_input_azimuth=config.estimate_input_azimuth,
        input_code_dim=config.input_code_dim,
        prediction_type=config.prediction_type,
        vae=config.vae,
        input_depression=config.input_depression,
        spatial_pose=None if config.pretrained is not None else config.spatial_pose,
    )
    if config.spatial_pose == "proxy" and not takes_proxy(pipe.pose_projection):
        widen_for_proxy(pipe.unet, pipe.pose_projection)  # a warm start: zero weights on the proxy pair
    if config.reference_attention and not uses_reference(pipe.pose_projection):
        enable_reference_attention(pipe.unet, pipe.pose_projection)  # a warm start: every gate zero
    if config.input_tokens and not uses_input_tokens(pipe.pose_projection):
        enable_input_tokens(pipe.unet, pipe.pose_projection, pipe.vae.config.latent_channels)
    if config.proxy_geometry and proxy_form(pipe.pose_projection) != "geometry":
        use_proxy_geometry(pipe.pose_projection)  # the proxy's masks replace its render from now on
    image_size = training_image_size(pipe, config.image_size)
    encoder = None
    if config.pfm_weight > 0:
        encoder = load_pfm_encoder(
            config.encoder,
            image_size=image_size,
            projection_dim=config.pfm_projection_dim,
            seed=config.seed,
        )
    train_dataset, validation_dataset, scaling = train_validation_pairs(
        config.data,
        config.protocol,
        output_dir / "data",
        image_size=image_size,
        scaling=config.scaling,
        num_validation_pairs=config.num_validation_images,
        seed=config.seed,
        same_depression=config.same_depression,
    )
    record_trained_pose_ranges(pipe.pose_projection, train_dataset)
    pipe.pose_projection.register_to_config(trained_vae=vae_signature(pipe.vae.config))  # refused if swapped
    pipe.pose_projection.register_to_config(trained_estimator=None)  # the estimator trains: recorded anew
    rehearsal = None
    if config.rehearsal_data is not None and config.rehearsal_fraction > 0:
        rehearsal, _, _ = train_validation_pairs(
            config.rehearsal_data, f"ood-{VALIDATION_CLASS}", output_dir / "rehearsal", image_size=image_size,
            scaling="unit", seed=config.seed, same_depression=False,
        )  # fmt: skip
        if config.rehearsal_max_chips is not None and len(rehearsal.records) > config.rehearsal_max_chips:
            rehearsal = ViewPairDataset(
                subsample_objects(rehearsal.records, config.rehearsal_max_chips, seed=config.seed),
                size=image_size, scaling=rehearsal.scaling, same_depression=False, seed=config.seed,
            )  # fmt: skip
        record_trained_pose_ranges(pipe.pose_projection, rehearsal)  # the union: both kinds of pairs
    regressor = None  # validation's pose-following check
    if config.evaluators is not None and config.validation_steps:
        regressor = load_evaluators(config.evaluators).regressor
    check_global_batch(len(train_dataset), config.train_batch_size, accelerator.num_processes, what="pairs",
                       gradient_accumulation_steps=config.gradient_accumulation_steps)  # fmt: skip
    if accelerator.is_main_process:
        save_config(config, output_dir)
        if encoder is not None and config.pfm_projection_dim is not None:
            encoder.save_projection(output_dir)
    return FinetuneInputs(
        pipe, image_size, encoder, train_dataset, validation_dataset, scaling, regressor, rehearsal
    )


def _prepare_training(
    config: FinetuneConfig, accelerator: Accelerator, inputs: FinetuneInputs, resume_path: Path | None
) -> FinetuneTrainer:
    """Modules in their dtypes, EMA copies, the optimiser, the schedule and the data, prepared and resumed."""
    # 1. frozen parts in the weight dtype, trainable parts in float32 (pipe's own modules), EMA copies
    pipe = inputs.pipe
    weight_dtype = mixed_precision_dtype(accelerator.mixed_precision)
    vae, image_embedder, unet, pose_projection = finetuning_modules(
        pipe,
        device=accelerator.device,
        weight_dtype=weight_dtype,
        train_image_encoder=config.train_image_encoder,
        gradient_checkpointing=config.gradient_checkpointing,
    )
    trained_tower = image_embedder if config.train_image_encoder else None
    encoder = inputs.encoder
    if encoder is not None:
        encoder = encoder.to(accelerator.device, dtype=weight_dtype)
    # a resume whose checkpoint already reached max_train_steps only exports: no step needs the cache
    resumed_step = 0 if resume_path is None else int(read_run_state(resume_path)["step"])
    train_dataset, rehearsal = inputs.train_dataset, inputs.rehearsal_dataset
    if config.cache_latents and resumed_step < config.max_train_steps:  # the frozen parts never change
        frozen_tower = None if config.train_image_encoder else image_embedder.image_encoder
        cache_device = accelerator.device if config.cache_on_device else "cpu"
        proxies = None
        if takes_proxy(pipe.pose_projection):  # each chip's proxies at its pose, in the chips' dB scaling
            if config.data is None:
                raise ValueError(
                    "data: spatial_pose='proxy' trains on a corpus folder with its proxies "
                    "(train/pretrain_prior.py writes both), got None (the built-in dataset has none)"
                )
            paths = [record.path for record in train_dataset.records]
            has_oracle = corpus_proxies_have_oracle(config.data, config.proxies)
            if config.proxy_oracle_prob > 0 and not has_oracle:
                raise ValueError(
                    f"proxy_oracle_prob: {config.proxy_oracle_prob} needs proxies written with the oracle "
                    "(sar_zero123.data.corpus_proxies.write_corpus_proxies(oracle=True))"
                )
            magnitudes = load_corpus_proxies(config.data, paths, config.proxies)
            if has_oracle and config.proxy_oracle_prob == 0:  # the fitted candidates only
                magnitudes = magnitudes[:, :-1]
            proxies = train_dataset.scaling.normalize(magnitudes).float()
            flat = proxies.reshape(-1, 1, *proxies.shape[-2:])  # each candidate as the model reads it
            proxies = proxy_condition_views(flat, proxy_form(pipe.pose_projection)).reshape(proxies.shape)
        cache = ChipLatentCache.encode(
            load_chip_images(train_dataset), vae, frozen_tower, proxy_images=proxies
        ).to(cache_device)
        train_dataset = CachedViewPairs(train_dataset, cache)
        if rehearsal is not None:
            rehearsal_cache = ChipLatentCache.encode(load_chip_images(rehearsal), vae, frozen_tower)
            rehearsal = CachedViewPairs(rehearsal, rehearsal_cache.to(cache_device))
    if rehearsal is not None:
        train_dataset = MixedPairs(train_dataset, rehearsal, config.rehearsal_fraction, seed=config.seed)
    noise_scheduler = DDPMScheduler.from_config(pipe.scheduler.config)
    ema_pairs = ema_models(accelerator, unet, trained_tower, decay=config.ema_decay) if config.use_ema else []
    # 2. optimiser (pose projection at pose_lr_multiplier x the learning rate), schedule, data
    optimizer = finetuning_optimizer(
        unet,
        pose_projection,
        trained_tower,
        azimuth_estimator=pipe.azimuth_estimator,
        learning_rate=config.learning_rate,
        pose_lr_multiplier=config.pose_lr_multiplier,
        weight_decay=ADAM_WEIGHT_DECAY,
    )
    lr_scheduler = get_scheduler(
        config.lr_scheduler,
        optimizer,
        num_warmup_steps=config.lr_warmup_steps * accelerator.num_processes,
        num_training_steps=config.max_train_steps * accelerator.num_processes,
    )
    train_dataloader = DataLoader(  # cached pairs arrive stacked (CachedViewPairs.__getitems__)
        train_dataset, config.train_batch_size, shuffle=True, drop_last=True, collate_fn=collate_pairs,
        num_workers=0 if config.cache_latents and config.cache_on_device else config.num_workers,
    )  # fmt: skip
    unet, pose_projection, optimizer, train_dataloader, lr_scheduler = accelerator.prepare(
        unet, pose_projection, optimizer, train_dataloader, lr_scheduler
    )
    # prepared after the others so that the checkpoints of a frozen-tower run keep their file names
    image_encoder = accelerator.prepare(image_embedder) if config.train_image_encoder else image_embedder
    trained_modules = [unet, pose_projection] + ([image_encoder] if config.train_image_encoder else [])
    azimuth_estimator = pipe.azimuth_estimator
    if azimuth_estimator is not None:
        azimuth_estimator = accelerator.prepare(azimuth_estimator)
        trained_modules.append(azimuth_estimator)
    validation_loader = DataLoader(inputs.validation_dataset, batch_size=config.num_validation_images)
    validation_batch = next(iter(validation_loader))
    # 3. resume
    global_step = resume_step(accelerator, resume_path)
    accelerator.init_trackers("finetune_pfm", config=tracker_hparams(config))
    loss_kwargs = {"vae": vae, "encoder": encoder, "noise_scheduler": noise_scheduler,
                   "loss_settings": config.loss_settings()}  # fmt: skip
    return FinetuneTrainer(
        trained_modules, unet, pose_projection, image_encoder, azimuth_estimator, image_embedder, ema_pairs,
        optimizer, lr_scheduler, train_dataloader, train_dataset, validation_batch, loss_kwargs, global_step,
    )  # fmt: skip


def _export(
    config: FinetuneConfig,
    accelerator: Accelerator,
    inputs: FinetuneInputs,
    trainer: FinetuneTrainer,
    global_step: int,
) -> list[str]:
    """Replica check, then the pipeline with EMA weights; returns the outputs relative to the run folder."""
    output_dir = Path(config.output_dir)
    accelerator.wait_for_everyone()
    unwrapped = [accelerator.unwrap_model(module) for module in trainer.trained_modules]
    digests = check_replicas_agree(accelerator, unwrapped)
    outputs = ["train_state.json"]
    if accelerator.is_main_process:
        state = {"global_step": global_step, "image_size": inputs.image_size,
                 "replica_weight_digests": digests}  # fmt: skip
        write_json_atomic(state, output_dir / "train_state.json")
        if config.save_pipeline:
            export_finetuned(output_dir / "pipeline", inputs.pipe, inputs.scaling, trainer.ema_pairs,
                             lineage=_lineage(config))  # fmt: skip
    if config.save_pipeline:
        outputs.append("pipeline/model_index.json")
    return outputs
