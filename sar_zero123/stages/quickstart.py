"""The quickstart: every stage of the method end to end, as the README's main command runs it.

:func:`plan_stages` builds the typed config of every stage from a :class:`~sar_zero123.stages.presets.Preset`
before anything runs, so a setting a stage refuses fails first, named in the preset's terms.
:func:`run_quickstart` then applies the run-folder rule to the run's folder (its record holds the
quickstart's settings and the preset's values), runs each stage (each under its own rule, continued with
``resume``) and writes ``report.md`` from what the stages left on disk (:mod:`sar_zero123.stages.report`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sar_zero123.config import config_to_dict, save_config, write_json_atomic
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.runs.folder import (
    field_defaults,
    finish_run,
    read_run_record,
    run_differences,
)
from sar_zero123.runs.stage import open_stage_folder
from sar_zero123.stages.corpus import CORPUS_FOLDER, CorpusConfig, run_corpus
from sar_zero123.stages.evaluate import EVALUATE_MAY_DIFFER, EvaluateConfig, run_evaluate
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig, run_evaluators
from sar_zero123.stages.finetune import FinetuneConfig, run_finetune
from sar_zero123.stages.presets import Preset, QuickstartConfig
from sar_zero123.stages.proxies import PROXIES_FOLDER, ProxiesConfig, run_proxies
from sar_zero123.stages.report import write_report
from sar_zero123.stages.simclr import PretrainSimCLRConfig, run_simclr
from sar_zero123.stages.simulate import SimulateConfig, run_simulate
from sar_zero123.stages.vae import TrainVAEConfig, run_vae

logger = logging.getLogger(__name__)

__all__ = ["StagePlan", "plan_stages", "run_quickstart"]

#: Fields of an evaluation that a run with more ``--lambdas`` changes: the evaluation is then redone.
_PIPELINE_FIELDS = ("pipeline", "pipeline_names", "lambdas")


@dataclass(frozen=True)
class StagePlan:
    """One stage of a quickstart: its name in the report, its typed config and its stage function."""

    name: str
    config: Any
    run: Callable[[Any], Any]

    @property
    def folder(self) -> Path:
        config = self.config
        return Path(config.out if isinstance(config, SimulateConfig) else config.output_dir)


def _build(stage: str, cls: type, **values: Any) -> Any:
    """``cls(**values)``, with a refusal naming the quickstart stage whose config refused the preset."""
    try:
        return cls(**values)
    except (ValueError, TypeError) as error:
        raise ValueError(
            f"the {stage} stage refuses this recipe (check --recipe and --set): {error}"
        ) from error


def _protocol(config: QuickstartConfig, preset: Preset) -> str:
    return config.protocol or f"ood-{preset.classes[-1]}"


def _takes_proxy(prior: str | None) -> bool:
    """Whether the prior's UNet takes the simulator proxy (``spatial_pose="proxy"``)."""
    if prior is None:
        return False
    config = resolve_pretrained(prior) / "pose_projection" / "config.json"
    return config.is_file() and json.loads(config.read_text()).get("spatial_pose") == "proxy"


def _training_stages(config: QuickstartConfig, preset: Preset, out: Path) -> list[StagePlan]:
    """SimCLR; the VAE and base model without a prior; the rehearsal corpus; one fine-tune per lambda."""
    data = str(out / "data" if config.data is None else Path(config.data))
    protocol = _protocol(config, preset)
    common = {"data": data, "seed": config.seed, "image_size": preset.image_size, "protocol": protocol,
              "mixed_precision": preset.mixed_precision,
              "checkpointing_steps": preset.checkpointing_steps, "checkpoints_total_limit": 2,
              "resume_from_checkpoint": "latest", "report_to": "none"}  # fmt: skip
    simclr_dir = out / "simclr"
    plans = [StagePlan("simclr", _build(
        "simclr", PretrainSimCLRConfig, **common, output_dir=str(simclr_dir), preset="speckle+monotonic",
        cifar_stem=preset.encoder_cifar_stem, depths=list(preset.encoder_depths),
        hidden_sizes=list(preset.encoder_widths), embedding_size=preset.encoder_widths[0],
        global_batch_size=preset.simclr_batch_size, max_train_steps=preset.simclr_steps, epochs=10_000,
    ), run_simclr)]  # fmt: skip
    vae_dir = out / "vae" / "vae"
    if preset.prior is None:
        shape = SAR_ZERO123_SIZES[preset.model_size]["vae"]
        plans.append(StagePlan("vae", _build(
            "vae", TrainVAEConfig, **common, output_dir=str(out / "vae"),
            block_out_channels=list(preset.vae_widths), layers_per_block=shape["layers_per_block"],
            latent_channels=shape["latent_channels"], norm_num_groups=preset.vae_norm_groups,
            train_batch_size=preset.vae_batch_size, max_train_steps=preset.vae_steps, learning_rate=1e-3,
            num_eval_images=16,
        ), run_vae))  # fmt: skip

    if preset.prior is not None and preset.vae_decoder_steps:  # the prior's decoder adapted to these chips
        vae_dir = out / "vae_decoder" / "vae"
        plans.append(StagePlan("vae decoder", _build(
            "vae decoder", TrainVAEConfig, **common, output_dir=str(out / "vae_decoder"),
            pretrained=preset.prior, train_encoder=False, feature_loss_weight=preset.vae_feature_loss_weight,
            feature_encoder=str(simclr_dir / "encoder") if preset.vae_feature_loss_weight else None,
            train_batch_size=preset.vae_batch_size, max_train_steps=preset.vae_decoder_steps,
            learning_rate=1e-4, num_eval_images=16,
        ), run_vae))  # fmt: skip

    proxies_dir = out / "proxies"
    if _takes_proxy(preset.prior):  # each training chip's simulator proxies, the fine-tunes' condition
        plans.append(StagePlan("proxies", _build(
            "proxies", ProxiesConfig, data=data, output_dir=str(proxies_dir), image_size=preset.image_size,
        ), run_proxies))  # fmt: skip

    rehearsal_dir = out / "rehearsal"
    if preset.rehearsal_vehicles:
        plans.append(StagePlan("rehearsal corpus", _build(
            "rehearsal corpus", CorpusConfig, output_dir=str(rehearsal_dir),
            num_vehicles=preset.rehearsal_vehicles, num_validation_vehicles=1, size=preset.image_size,
            seed=config.seed,
        ), run_corpus))  # fmt: skip

    def finetune(name: str, run_dir: Path, steps: int, weight: float, pretrained: str | None) -> StagePlan:
        values: dict[str, Any] = {
            **common, "output_dir": str(run_dir), "pfm_weight": weight, "pfm_fraction": preset.pfm_fraction,
            "encoder": str(simclr_dir / "encoder"), "train_batch_size": preset.finetune_batch_size,
            "max_train_steps": steps, "learning_rate": preset.finetune_learning_rate,
            "lr_scheduler": preset.lr_scheduler, "lr_warmup_steps": preset.lr_warmup_steps,
            "use_ema": preset.ema_decay is not None, "train_image_encoder": preset.train_image_encoder,
            "timestep_sampling": preset.timestep_sampling, "timestep_logit_mean": preset.timestep_logit_mean,
            "validation_steps": 0, "snr_gamma": preset.snr_gamma,
            "pfm_projection_dim": preset.pfm_projection_dim, "pfm_balance": preset.pfm_balance,
            "pfm_min_snr": preset.pfm_min_snr, "lora_rank": preset.finetune_lora_rank,
        }  # fmt: skip
        if preset.ema_decay is not None:
            values["ema_decay"] = preset.ema_decay
        if preset.rehearsal_vehicles:  # (a prior's fine-tunes) the whole rendered corpus, no subsample
            values.update(rehearsal_data=str(rehearsal_dir / CORPUS_FOLDER), rehearsal_max_chips=None,
                          rehearsal_fraction=preset.rehearsal_fraction)  # fmt: skip
        if preset.prior is None or preset.vae_decoder_steps:
            values["vae"] = str(vae_dir)
        if _takes_proxy(preset.prior):
            values["proxies"] = str(proxies_dir / PROXIES_FOLDER)
        if pretrained is None:
            values.update(size=preset.model_size, estimate_input_azimuth=preset.estimate_input_azimuth,
                          prediction_type=preset.prediction_type)  # fmt: skip
        else:
            values["pretrained"] = pretrained
        return StagePlan(name, _build(name, FinetuneConfig, **values), run_finetune)

    if preset.prior is None:
        plans.append(finetune("base model", out / "base", preset.base_steps, 0.0, None))
        base = str(out / "base" / "pipeline")
    else:  # the paper's regime: every fine-tune starts from one pretrained multi-view prior
        base = str(resolve_pretrained(preset.prior))
    for weight in config.lambdas:
        name = f"lambda={weight:g}"
        plans.append(finetune(f"finetune {name}", out / f"finetune_lambda{weight:g}", preset.finetune_steps,
                              weight, base))  # fmt: skip
    return plans


def plan_stages(config: QuickstartConfig) -> list[StagePlan]:
    """Every stage of the run with its typed config, in order; builds (and so validates) all of them.

    Raises:
        ValueError: Naming the stage that refuses a setting of the preset (or its overrides).
    """
    preset = config.preset()
    out = Path(config.output_dir)
    data = out / "data" if config.data is None else Path(config.data)
    depression_data = out / "data_depression"
    with_depressions = config.data is None and bool(preset.depression_targets_deg)
    plans: list[StagePlan] = []
    if config.data is None:  # 15 and 17 deg as MSTAR; views at other depressions for the depression table
        simulated = [("simulate", data, [15.0, 17.0])]
        if with_depressions:
            depressions = sorted({17.0, *preset.depression_targets_deg})
            simulated.append(("simulate depressions", depression_data, depressions))
        for name, folder, depressions in simulated:
            plans.append(StagePlan(name, _build(
                name, SimulateConfig, out=str(folder), classes=list(preset.classes),
                instances=preset.instances, azimuth_step_deg=preset.azimuth_step_deg,
                depressions_deg=depressions, size=preset.image_size, seed=config.seed, resume=True,
            ), run_simulate))  # fmt: skip
    plans += _training_stages(config, preset, out)
    pipelines = {
        plan.name[len("finetune ") :]: str(Path(plan.config.output_dir) / "pipeline")
        for plan in plans
        if plan.name.startswith("finetune ")
    }
    simclr_dir = out / "simclr"
    evaluator_dir = out / "evaluators"
    plans.append(StagePlan("evaluators", _build(
        "evaluators", TrainEvaluatorsConfig, output_dir=str(evaluator_dir), data=str(data),
        depression_data=str(depression_data) if with_depressions else None, seed=config.seed,
        image_size=preset.image_size, mixed_precision=preset.mixed_precision,
        cifar_stem=preset.encoder_cifar_stem, depths=list(preset.encoder_depths),
        hidden_sizes=list(preset.encoder_widths), epochs=preset.evaluator_epochs,
        probe_epochs=preset.evaluator_epochs, learning_rate=preset.evaluator_learning_rate,
        train_batch_size=32, simclr_encoders=[str(simclr_dir)], resume=True,
    ), run_evaluators))  # fmt: skip
    evaluation = {
        "pipeline": list(pipelines.values()), "pipeline_names": list(pipelines),
        "lambdas": list(config.lambdas), "evaluators": str(evaluator_dir),
        "protocol": _protocol(config, preset), "n": preset.eval_n, "num_inference_steps": preset.eval_steps,
        "guidance_scale": 3.0, "heading_guidance_scale": preset.eval_heading_guidance_scale,
        "depression_guidance_scale": preset.eval_depression_guidance_scale,
        "strength": preset.eval_strength, "start_from": preset.eval_start_from,
        "crop_size": min(64, preset.image_size),
        "eval_batch_size": 8, "seed": config.seed, "resume": True, "speckle_looks": preset.eval_speckle_looks,
    }  # fmt: skip
    plans.append(StagePlan("evaluate", _build(
        "evaluate", EvaluateConfig, **evaluation, data=str(data), output_dir=str(out / "eval"),
        steps=list(preset.speed_steps), schedulers=list(preset.schedulers), speed_n=preset.speed_n,
    ), run_evaluate))  # fmt: skip
    if with_depressions:  # depression requests from 17 deg inputs, same evaluators
        plans.append(StagePlan("evaluate depressions", _build(
            "evaluate depressions", EvaluateConfig, **evaluation, data=str(depression_data),
            output_dir=str(out / "eval_depression"), same_depression=False, input_depression_deg=17.0,
            target_depressions_deg=list(preset.depression_targets_deg),
            outside_trained_range=True,  # a from-scratch model never saw d_el != 0: score it anyway
        ), run_evaluate))  # fmt: skip
    return plans


def _run_stage(plan: StagePlan) -> bool:
    """Runs one stage (continued under its own run-folder rule); returns whether it had work to do.

    An evaluation whose record differs only in its pipelines (a re-run with more ``--lambdas``) is redone:
    its old folder is moved aside, never deleted.
    """
    before = read_run_record(plan.folder) if plan.folder.is_dir() else None
    had_work = before is None or not before.get("finished")
    logger.info("stage %s%s", plan.name, "" if had_work else ": finished before, checking its record")
    try:
        plan.run(plan.config)
    except ValueError:
        if not isinstance(plan.config, EvaluateConfig) or before is None:
            raise
        fields = config_to_dict(plan.config)
        ignored = (*EVALUATE_MAY_DIFFER, *_PIPELINE_FIELDS)
        differences = run_differences(
            before, "evaluate", fields, before.get("data", {}), ignore=ignored,
            defaults=field_defaults(plan.config),
        )  # fmt: skip
        if differences:
            raise
        logger.info("stage %s: other pipelines than its record; evaluating them all again", plan.name)
        plan.run(dataclasses.replace(plan.config, resume=False, restart=True))
        had_work = True
    after = read_run_record(plan.folder) or {}
    return had_work or after.get("finished_at") != (before or {}).get("finished_at")


def run_quickstart(config: QuickstartConfig) -> Path:
    """Runs (or continues, with ``config.resume``) the whole chain; returns the path of ``report.md``.

    Raises:
        ValueError: For a preset a stage refuses (before any work), or a folder holding other work.
    """
    preset = config.preset()
    plans = plan_stages(config)  # every stage's config checked before any work
    out = Path(config.output_dir)
    # the preset's values one by one, so that a refusal names the field that differs
    record = {**config_to_dict(config), **{f"preset.{k}": v for k, v in dataclasses.asdict(preset).items()}}
    folder = open_stage_folder(
        out, "quickstart", record, data=None if config.data is None else config.data, resume=config.resume,
        # the recipe's name and the --set items may differ: the preset.* values they give are compared
        restart=config.restart, may_differ=("output_dir", "resume", "restart", "recipe", "set",
                                            *QuickstartConfig.REMOVED_FIELDS),
        may_extend=("lambdas",), resume_hint="--resume",
    )  # fmt: skip
    report = out / "report.md"
    if folder.status == "new":
        save_config(config, out)
        write_json_atomic(dataclasses.asdict(preset), out / "preset.json")
    timings: dict[str, dict[str, Any]] = {}
    for plan in plans:  # a finished stage returns at once; one whose outputs are gone is continued
        ran = _run_stage(plan)
        seconds = float((read_run_record(plan.folder) or {}).get("seconds", 0.0))
        timings[plan.name] = {"seconds": seconds, "ran": ran}
    if folder.finished and not any(t["ran"] for t in timings.values()):
        logger.info("%s: every stage was finished; %s is up to date", out, report)
        return report
    save_config(config, out)  # with more --lambdas, the record's and config.json's lambdas grow
    write_json_atomic(timings, out / "timings.json")
    protocol = _protocol(config, preset)
    held_out = protocol[len("ood-") :] if protocol.startswith("ood-") else None
    report = write_report(out, preset, config, held_out, timings)
    total = sum(t["seconds"] for t in timings.values())
    finish_run(folder, ["report.md"], seconds=total - float(folder.record.get("seconds", 0.0)))
    return report
