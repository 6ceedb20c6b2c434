"""The prior stage: the multi-view SAR prior pretrained on procedural simulated vehicles (the bundled prior).

Three resumable stages in ``output_dir``:

1. the corpus (:func:`sar_zero123.sim.corpus.write_prior_corpus`): procedural vehicles at random azimuths
   and depressions; the named simulator classes are never in it (they are the prior's unseen vehicles);
2. a VAE on the corpus, in ``vae/`` (skipped when ``vae`` or ``init`` gives one);
3. the UNet with its pose path (lambda = 0), in ``base/``: pairs across depressions, the input's absolute
   depression in the pose (Stable Zero123's fourth slot), the estimated-azimuth path, v prediction with
   Min-SNR weighting. Its pipeline, ``base/pipeline``, is the prior.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import train_validation_pairs
from sar_zero123.data.corpus_proxies import PROXIES_RECORD, write_corpus_proxies
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.conditioning import downsampling_factor
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run, read_run_record
from sar_zero123.runs.stage import launch_state, open_stage_folder
from sar_zero123.sim.corpus import CORPUS_OPTIONS_FILE, VALIDATION_CLASS, write_prior_corpus
from sar_zero123.stages.finetune import (
    CONSTANT_LR_SCHEDULERS,
    FinetuneConfig,
    check_lr_scheduler,
    run_finetune,
)
from sar_zero123.stages.vae import TrainVAEConfig, run_vae
from sar_zero123.training.losses import LossSettings

logger = logging.getLogger(__name__)

__all__ = [
    "PriorConfig",
    "check_corpus_pairs",
    "init_folder",
    "prior_base_config",
    "prior_proxies_folder",
    "prior_vae_config",
    "prior_vae_folder",
    "run_prior",
]

#: The corpus's uniform depression draw (deg), and the share of its views at MSTAR's 15/17 deg instead.
CORPUS_DEPRESSION_RANGE_DEG = (10.0, 60.0)
CORPUS_MSTAR_FRACTION = 0.25
#: "proxy": the simulator bank fitted to each corpus vehicle, and the best-fitting ones kept per vehicle.
PROXY_BANK_VEHICLES = 250
PROXY_CANDIDATES = 2
#: GroupNorm groups of the prior's VAE (each of vae_widths a multiple of it).
VAE_NORM_GROUPS = 8


@dataclass
class PriorConfig:
    """Corpus, VAE and UNet of the multi-view prior (defaults: the bundled prior's recipe)."""

    ADVANCED_FIELDS = (
        "num_validation_vehicles", "corpus_workers", "proxy_oracle_prob", "proxy_runner_up_prob",
        "vae_widths", "vae_steps", "vae_batch_size", "lr_scheduler", "lr_warmup_steps", "input_depression",
        "prediction_type", "snr_gamma", "checkpointing_steps", "mixed_precision",
    )  # fmt: skip
    REMOVED_FIELDS = {
        "depression_range_deg": RemovedField([10.0, 60.0], "the corpus's depressions are drawn in "
                                             f"{CORPUS_DEPRESSION_RANGE_DEG} deg"),
        "mstar_fraction": RemovedField(0.25, f"a share of {CORPUS_MSTAR_FRACTION} of the corpus views lie at "
                                       "MSTAR's 15/17 deg"),
        "proxy_bank_vehicles": RemovedField(250, f"the proxy bank holds {PROXY_BANK_VEHICLES} vehicles"),
        "vae_norm_groups": RemovedField(8, f"the VAE's GroupNorm has {VAE_NORM_GROUPS} groups"),
        "proxy_candidates": RemovedField(2, f"{PROXY_CANDIDATES} best-fitting bank vehicles are kept per "
                                         "corpus vehicle"),
    }  # fmt: skip

    output_dir: str = "runs/prior"  # run folder: corpus/, vae/, base/ (its pipeline/ is the prior)
    corpus: str | None = None  # an existing corpus folder to train on; None writes output_dir/corpus
    num_vehicles: int = 2000  # procedural vehicles in the corpus (validation ones included)
    views_per_vehicle: int = 24  # chips per vehicle
    num_validation_vehicles: int = 32  # vehicles held out as class PROCVAL (validation pairs)
    image_size: int = 64  # chip side in pixels
    corpus_workers: int = 2  # processes rendering the corpus
    model_size: str = "micro"  # build_sar_zero123 size of the UNet
    # the UNet also takes the input latent turned by d_az ("rotated_input"), or also the proxies ("proxy")
    spatial_pose: str | None = None
    proxy_oracle_prob: float = LossSettings.proxy_oracle_prob  # "proxy": pairs given the vehicle itself
    proxy_runner_up_prob: float = LossSettings.proxy_runner_up_prob  # "proxy": pairs given the runner-up fit
    reference_attention: bool = False  # the UNet's self-attentions also attend to the input's own features
    input_tokens: bool = False  # the UNet's cross-attentions also attend to the input's latent, by place
    proxy_geometry: bool = False  # "proxy": the UNet reads each proxy as shadow, ground and lit masks
    vae: str | None = None  # an AutoencoderKL folder to use (e.g. the bundled prior's vae/); None trains one
    init: str | None = None  # a prior (name or folder) to continue with its own VAE (warm start)
    vae_widths: list[int] = field(default_factory=lambda: [16, 32, 64])  # VAE block widths (16x16 latents)
    vae_steps: int = 3000  # VAE optimisation steps
    vae_batch_size: int = 8  # chips per VAE step
    base_steps: int = 25000  # UNet optimisation steps (a constant lr_scheduler: a re-run may extend them)
    train_batch_size: int = 16  # pairs per UNet step
    learning_rate: float = 1e-3  # AdamW (peak) learning rate of the UNet
    lr_scheduler: str = "constant"  # diffusers LR schedule of the UNet stage (e.g. cosine: decays to 0)
    lr_warmup_steps: int = 0  # its warm-up optimisation steps
    input_depression: bool = True  # the pose's 4th entry is the input's absolute depression
    prediction_type: str = "v_prediction"  # the UNet's training target
    snr_gamma: float | None = 5.0  # Min-SNR-gamma weighting of L_simple
    checkpointing_steps: int = 1000  # resumable checkpoint interval of the VAE and UNet stages
    mixed_precision: str = "no"  # accelerate mixed precision of both training stages ("bf16" on GPUs)
    seed: int = 0  # seed of the corpus and of every stage
    resume: bool = True  # continue a run in output_dir with these settings (default); --no-resume refuses it
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over

    def __post_init__(self) -> None:
        check_minimum(self, "num_vehicles", "views_per_vehicle", minimum=2)
        check_minimum(
            self,
            "num_validation_vehicles",
            "corpus_workers",
            "vae_steps",
            "vae_batch_size",
            "base_steps",
            "train_batch_size",
            "checkpointing_steps",
            minimum=1,
        )
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        check_minimum(self, "lr_warmup_steps", minimum=0)
        check_lr_scheduler(self.lr_scheduler)
        if self.num_validation_vehicles >= self.num_vehicles:
            raise ValueError(
                f"num_validation_vehicles must be below num_vehicles ({self.num_vehicles}): the others are "
                f"the training vehicles, got {self.num_validation_vehicles}"
            )
        if self.model_size not in SAR_ZERO123_SIZES:
            raise ValueError(
                f"model_size must be one of {sorted(SAR_ZERO123_SIZES)}, got {self.model_size!r}"
            )
        LossSettings(proxy_oracle_prob=self.proxy_oracle_prob, proxy_runner_up_prob=self.proxy_runner_up_prob)
        if self.proxy_geometry and self.init is None and self.spatial_pose != "proxy":
            raise ValueError(
                "proxy_geometry: only a spatial_pose='proxy' prior reads a proxy (--spatial_pose proxy), got "
                f"spatial_pose={self.spatial_pose!r}"
            )
        if self.init is not None:
            defaults = {item.name: item.default for item in dataclasses.fields(PriorConfig)}
            kept = ("model_size", "prediction_type", "input_depression")  # image_size sizes the corpus
            ignored = [name for name in kept if getattr(self, name) != defaults[name]]
            ignored += ["spatial_pose"] if self.spatial_pose not in (None, "proxy") else []
            if ignored:
                raise ValueError(
                    f"{', '.join(ignored)}: a warm start (init {self.init}) keeps that pipeline's own "
                    "(spatial_pose may only be 'proxy', which widens a 'rotated_input' init); leave "
                    f"{'it' if len(ignored) == 1 else 'them'} out"
                )
            if self.vae is not None:
                raise ValueError(
                    f"vae: a warm start (init {self.init}) keeps that pipeline's own VAE; leave vae out, got "
                    f"{self.vae}"
                )
            if not (init_folder(self) / "model_index.json").is_file():
                raise FileNotFoundError(
                    f"init: expected a bundled prior's name or a pipeline folder with model_index.json, got "
                    f"{self.init}"
                )
        if self.vae is not None and not (Path(self.vae) / "config.json").is_file():
            raise FileNotFoundError(f"vae: expected an AutoencoderKL folder with config.json, got {self.vae}")
        if self.corpus is not None and not (Path(self.corpus) / "index.csv").is_file():
            raise FileNotFoundError(f"corpus: expected a corpus folder with index.csv, got {self.corpus}")
        if self.corpus is not None and not (Path(self.corpus) / CORPUS_OPTIONS_FILE).is_file():
            raise FileNotFoundError(
                f"corpus: {self.corpus} is not a prior corpus (no {CORPUS_OPTIONS_FILE}, which "
                "write_prior_corpus writes); leave --corpus out to write one into output_dir/corpus"
            )
        # the UNet needs the VAE's downsampling factor: refused before the VAE stage
        needed = downsampling_factor(SAR_ZERO123_SIZES[self.model_size]["vae"]["block_out_channels"])
        widths = self.vae_widths
        if self.init is not None:  # the pipeline's UNet and VAE already agree
            widths = SAR_ZERO123_SIZES[self.model_size]["vae"]["block_out_channels"]
        elif self.vae is not None:
            vae_config = json.loads((Path(self.vae) / "config.json").read_text())
            widths = vae_config.get("block_out_channels", widths)
        if downsampling_factor(widths) != needed:
            source = f"the VAE in {self.vae}" if self.vae is not None else "vae_widths"
            raise ValueError(
                f"model_size {self.model_size!r} needs a VAE that downsamples by {needed} "
                f"({needed.bit_length()} width levels), but {source} {list(widths)} downsamples by "
                f"{downsampling_factor(widths)}"
            )
        most_pairs = (self.num_vehicles - self.num_validation_vehicles) * self.views_per_vehicle
        if self.train_batch_size > most_pairs:
            raise ValueError(
                f"train_batch_size {self.train_batch_size} exceeds the {most_pairs} training chips of the "
                "corpus ((num_vehicles - num_validation_vehicles) x views_per_vehicle), hence its pairs per "
                "epoch"
            )
        # the two training stages' configs validate their own fields, before the corpus
        out = Path(self.output_dir)
        try:
            prior_vae_config(self, out / "corpus")
        except ValueError as error:
            raise ValueError(
                f"the VAE stage (image_size, vae_*, model_size) refuses these settings: {error}"
            ) from None
        try:
            prior_base_config(self, prior_vae_folder(self))
        except ValueError as error:
            raise ValueError(
                "the UNet stage (image_size, model_size, base_steps, train_batch_size, learning_rate, "
                f"prediction_type, snr_gamma) refuses these settings: {error}"
            ) from None


def _stage_settings(config: PriorConfig) -> dict[str, Any]:
    """The settings the VAE and the UNet stages share: seed, split, precision, checkpoints, resume."""
    return {
        "seed": config.seed,
        "image_size": config.image_size,
        "protocol": f"ood-{VALIDATION_CLASS}",
        "mixed_precision": config.mixed_precision,
        "checkpointing_steps": config.checkpointing_steps,
        "checkpoints_total_limit": 2,
        "resume_from_checkpoint": "latest",
        "report_to": "none",
    }


def prior_vae_config(config: PriorConfig, corpus: Path) -> TrainVAEConfig:
    """The VAE stage of the prior: ``model_size``'s latent shape at ``vae_widths``, trained on ``corpus``."""
    vae_shape = SAR_ZERO123_SIZES[config.model_size]["vae"]
    return TrainVAEConfig(
        **_stage_settings(config),
        output_dir=str(Path(config.output_dir) / "vae"),
        data=str(corpus),
        block_out_channels=tuple(config.vae_widths),
        layers_per_block=vae_shape["layers_per_block"],
        latent_channels=vae_shape["latent_channels"],
        norm_num_groups=VAE_NORM_GROUPS,
        train_batch_size=config.vae_batch_size,
        max_train_steps=config.vae_steps,
        learning_rate=1e-3,
        num_eval_images=64,
    )


def init_folder(config: PriorConfig) -> Path:
    """The pipeline folder a warm start (``config.init``) continues from."""
    from sar_zero123.pretrained import resolve_pretrained

    return resolve_pretrained(config.init)


def prior_vae_folder(config: PriorConfig) -> Path:
    """The VAE the UNet stage uses: the warm start's own, the given one, or the VAE stage's."""
    if config.init is not None:
        return init_folder(config) / "vae"
    if config.vae is not None:
        return Path(config.vae)
    return Path(config.output_dir) / "vae" / "vae"


def prior_base_config(config: PriorConfig, vae: Path, corpus: Path | None = None) -> FinetuneConfig:
    """The UNet stage of the prior: lambda = 0 across depressions, with the VAE at ``vae``; from scratch, or
    from ``config.init``'s UNet, pose path and settings (a warm start)."""
    pose = {  # a warm start keeps its pipeline's own pose input, depression input and prediction type
        "spatial_pose": config.spatial_pose,
        "input_depression": config.input_depression,
        "prediction_type": config.prediction_type,
    }
    if config.init is not None:
        spatial_pose = "proxy" if config.spatial_pose == "proxy" else None  # widens the init's UNet
        pose = {**dict.fromkeys(pose), "input_depression": False, "pretrained": str(init_folder(config)),
                "spatial_pose": spatial_pose}  # fmt: skip
    return FinetuneConfig(
        **_stage_settings(config),
        output_dir=str(Path(config.output_dir) / "base"),
        data=None if corpus is None else str(corpus),
        size=config.model_size,
        estimate_input_azimuth=True,
        **pose,
        proxies=None if corpus is None else _proxies_or_none(config, corpus),
        proxy_oracle_prob=config.proxy_oracle_prob,
        proxy_runner_up_prob=config.proxy_runner_up_prob,
        reference_attention=config.reference_attention,
        input_tokens=config.input_tokens,
        proxy_geometry=config.proxy_geometry,
        same_depression=False,
        snr_gamma=config.snr_gamma,
        pfm_weight=0.0,
        vae=str(vae),
        train_batch_size=config.train_batch_size,
        max_train_steps=config.base_steps,
        learning_rate=config.learning_rate,
        lr_scheduler=config.lr_scheduler,
        lr_warmup_steps=config.lr_warmup_steps,
        use_ema=False,
        validation_steps=0,
    )


def run_prior(config: PriorConfig) -> Path:
    """Run (or continue, or extend) the three stages; returns ``output_dir/base/pipeline``.

    Under ``accelerate launch`` the main process writes the corpus and the records; the training stages share
    the work.

    Raises:
        ValueError: Before any work, for a folder holding another run or this run with other settings.
    """
    timer = StageTimer()
    state = launch_state()
    out = Path(config.output_dir)
    pipeline = out / "base" / "pipeline"
    folder = open_stage_folder(
        out, "prior", config, data={"corpus": data_identity(config.corpus)},
        resume=config.resume and not config.restart, restart=config.restart, resume_hint="--resume",
        may_differ=("output_dir", "resume", "restart", "corpus_workers", "checkpointing_steps"),
        may_extend=("base_steps",) if config.lr_scheduler in CONSTANT_LR_SCHEDULERS else (),
    )  # fmt: skip
    if folder.finished:
        logger.info("%s: this prior is finished; nothing to do", out)
        return pipeline
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    if state.is_main_process:
        save_config(config, out)
    timings_path = out / "timings.json"
    timings: dict[str, float] = json.loads(timings_path.read_text()) if timings_path.is_file() else {}

    # 1. corpus (its index is written last)
    corpus = Path(config.corpus) if config.corpus is not None else out / "corpus"
    with state.main_process_first():  # the others then find its index and skip the stage
        _stage("corpus", (corpus / "index.csv").is_file(), timings, lambda: _write_corpus(config, corpus))
    if config.spatial_pose == "proxy":
        with state.main_process_first():
            proxies = prior_proxies_folder(config, corpus)
            proxies_done = (proxies / PROXIES_RECORD).is_file()
            _stage("proxies", proxies_done, timings, lambda: _write_proxies(config, corpus, proxies))
    # the UNet's batch against the corpus's training pairs, before the VAE stage's minutes
    check_corpus_pairs(config, corpus, num_processes=state.num_processes)
    # 2. VAE, then 3. the UNet and its pose path across depressions (each done once its record is finished)
    vae_config = prior_vae_config(config, corpus)
    vae = prior_vae_folder(config)
    vae_done = config.vae is not None or config.init is not None or _finished(vae_config.output_dir)
    _stage("vae", vae_done, timings, lambda: run_vae(vae_config))
    base_config = prior_base_config(config, vae, corpus)
    base_done = _finished(base_config.output_dir, min_steps=config.base_steps)  # more steps: resume, export
    _stage("base", base_done, timings, lambda: run_finetune(base_config))
    if state.is_main_process:
        write_json_atomic(timings, timings_path)
        write_json_atomic(dataclasses.asdict(config), out / "prior_config.json")
        finish_run(folder, ["base/pipeline/model_index.json"], seconds=timer.seconds,
                   results={"base_steps": config.base_steps})  # fmt: skip
    state.wait_for_everyone()
    print(f"prior pipeline: {pipeline}")
    return pipeline


def check_corpus_pairs(config: PriorConfig, corpus: Path, num_processes: int = 1) -> int:
    """The number of the UNet stage's training pairs of ``corpus``, checked against one global batch before
    the VAE stage (the validation azimuths are known only once the corpus's poses are).

    Raises:
        ValueError: If the pairs cannot fill one global batch, saying how to reuse the corpus written.
    """
    train, _, _ = train_validation_pairs(
        corpus, f"ood-{VALIDATION_CLASS}", Path(config.output_dir) / "base", image_size=config.image_size,
        seed=config.seed, same_depression=False,
    )  # fmt: skip
    global_batch = config.train_batch_size * num_processes
    if len(train) < global_batch:
        raise ValueError(
            f"train_batch_size: the corpus {str(corpus)!r} gives {len(train)} training pairs (the training "
            f"vehicles' chips outside the validation azimuths), fewer than a global batch of {global_batch}; "
            f"use train_batch_size <= {len(train) // num_processes} or more vehicles or views. The corpus "
            f"is kept: pass --corpus {corpus} with another --output_dir to train on it"
        )
    return len(train)


def _write_corpus(config: PriorConfig, corpus: Path) -> None:
    write_prior_corpus(
        corpus,
        num_vehicles=config.num_vehicles,
        views_per_vehicle=config.views_per_vehicle,
        num_validation_vehicles=config.num_validation_vehicles,
        depression_range_deg=CORPUS_DEPRESSION_RANGE_DEG,
        mstar_fraction=CORPUS_MSTAR_FRACTION,
        size=config.image_size,
        seed=config.seed,
        num_workers=config.corpus_workers,
    )


def prior_proxies_folder(config: PriorConfig, corpus: Path) -> Path:
    """The corpus's own proxies where they match this bank and candidates, else ``output_dir/proxies``."""
    own = corpus / PROXIES_RECORD
    if own.is_file():
        record = json.loads(own.read_text())
        bank = record.get("bank", {})
        if (
            bank.get("num_vehicles") == PROXY_BANK_VEHICLES
            and record.get("candidates") == PROXY_CANDIDATES
            and (record.get("oracle") is True or config.proxy_oracle_prob == 0)
        ):
            return corpus
    return Path(config.output_dir) / "proxies"


def _proxies_or_none(config: PriorConfig, corpus: Path) -> str | None:
    return str(prior_proxies_folder(config, corpus)) if config.spatial_pose == "proxy" else None


def _write_proxies(config: PriorConfig, corpus: Path, out: Path) -> None:
    write_corpus_proxies(
        corpus,
        out,
        num_vehicles=PROXY_BANK_VEHICLES,
        candidates=PROXY_CANDIDATES,
        num_workers=config.corpus_workers,
        oracle=config.proxy_oracle_prob > 0,
    )


def _finished(folder: str | Path, min_steps: int | None = None) -> bool:
    """Whether a stage folder's record says finished (after at least ``min_steps`` steps when given)."""
    record = read_run_record(folder)
    if record is None or not record.get("finished"):
        return False
    return min_steps is None or record["config"]["max_train_steps"] >= min_steps


def _stage(name: str, done: bool, timings: dict[str, float], function: Callable[[], Any]) -> None:
    """Run one stage unless it is done; record its wall time only when it ran."""
    if done:
        logger.info("stage %s: done", name)
        return
    logger.info("stage %s", name)
    begin = time.perf_counter()
    function()
    timings[name] = time.perf_counter() - begin
    logger.info("stage %s took %.1f s", name, timings[name])
