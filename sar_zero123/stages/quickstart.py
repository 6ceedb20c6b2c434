"""The quickstart: every stage of the method end to end, as the README's main command runs it.

:func:`plan_stages` builds the typed config of every stage from its recipe section
(:class:`~sar_zero123.stages.presets.Recipe`: the section's values merged onto the stage config's defaults,
plus what the quickstart sets itself: paths, seed, the shared settings) before anything runs, so a setting a
stage refuses fails first, naming the stage. :func:`run_quickstart` then applies the run-folder rule to the
run's folder (its record holds the quickstart's settings and the recipe's values), runs each stage (each
under its own rule, continued with ``resume``) and writes ``report.md`` from what the stages left on disk
(:mod:`sar_zero123.stages.report`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sar_zero123.config.json_io import config_to_dict, save_config, write_json_atomic
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.conditioning import downsampling_factor
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.runs.folder import (
    field_defaults,
    finish_run,
    read_run_record,
    run_differences,
)
from sar_zero123.runs.stage import open_stage_folder
from sar_zero123.sim.targets import TARGET_CLASSES
from sar_zero123.stages.corpus import CORPUS_FOLDER, run_corpus
from sar_zero123.stages.evaluate import EVALUATE_MAY_DIFFER, EvaluateConfig, run_evaluate
from sar_zero123.stages.evaluators import run_evaluators
from sar_zero123.stages.finetune import run_finetune
from sar_zero123.stages.presets import (
    RECIPE_SECTIONS,
    QuickstartConfig,
    Recipe,
    SharedSettings,
    refuse_old_record,
)
from sar_zero123.stages.proxies import PROXIES_FOLDER, ProxiesConfig, run_proxies
from sar_zero123.stages.report import write_report
from sar_zero123.stages.simclr import run_simclr
from sar_zero123.stages.simulate import SimulateConfig, run_simulate
from sar_zero123.stages.vae import run_vae

logger = logging.getLogger(__name__)

__all__ = ["StagePlan", "plan_stages", "run_quickstart"]

#: The evaluation's speed/error sweep, run once, in the azimuth evaluation.
SPEED_SWEEP = ("steps", "schedulers", "speed_n")
#: The resolved recipe a run folder holds (each section's values the recipe sets).
RECIPE_FILE = "recipe.json"
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


def _build(stage: str, section: str, recipe: Recipe, without: Sequence[str] = (), **plumbing: Any) -> Any:
    """The config of one stage: its recipe section's values (but those ``without`` names) and ``plumbing``
    (what the quickstart sets), with a refusal naming the quickstart stage whose config refused them."""
    try:
        return RECIPE_SECTIONS[section](**recipe.stage_values(section, without, **plumbing))
    except (ValueError, TypeError) as error:
        raise ValueError(
            f"the {stage} stage refuses this recipe (check --recipe and --set {section}.FIELD): {error}"
        ) from error


def _protocol(config: QuickstartConfig, recipe: Recipe) -> str:
    return config.protocol or f"ood-{recipe.value('simulate', 'classes')[-1]}"


def _takes_proxy(prior: str | None) -> bool:
    """Whether the prior's UNet takes the simulator proxy (``spatial_pose="proxy"``)."""
    if prior is None:
        return False
    config = resolve_pretrained(prior) / "pose_projection" / "config.json"
    return config.is_file() and json.loads(config.read_text()).get("spatial_pose") == "proxy"


def _check_image_size(shared: SharedSettings, model_size: str) -> None:
    """The chips fit the prior's VAE and UNet (or ``base.size``'s): checked before any stage, since the
    fine-tunes would refuse them only after SimCLR and the VAE."""
    if shared.prior is not None:
        folder = resolve_pretrained(shared.prior)
        widths = [json.loads((folder / part / "config.json").read_text())["block_out_channels"]
                  for part in ("vae", "unet")]  # fmt: skip
        source = f"the prior {shared.prior!r}"
    else:
        spec = SAR_ZERO123_SIZES[model_size]
        widths = [spec["vae"]["block_out_channels"], spec["unet"]["block_out_channels"]]
        source = f"base.size {model_size!r}"
    multiple = downsampling_factor(widths[0]) * downsampling_factor(widths[1])
    if shared.image_size % multiple:
        raise ValueError(
            f"shared.image_size must be a multiple of {multiple} for {source} (VAE x UNet downsampling), "
            f"got {shared.image_size}"
        )


def _training_stages(config: QuickstartConfig, recipe: Recipe, out: Path) -> list[StagePlan]:
    """SimCLR; the VAE and base model without a prior; the rehearsal corpus; one fine-tune per lambda."""
    shared = recipe.shared
    data = str(out / "data" if config.data is None else Path(config.data))
    common = {"data": data, "seed": config.seed, "image_size": shared.image_size,
              "protocol": _protocol(config, recipe), "mixed_precision": shared.mixed_precision,
              "checkpointing_steps": shared.checkpointing_steps, "checkpoints_total_limit": 2,
              "resume_from_checkpoint": "latest", "report_to": "none"}  # fmt: skip
    simclr_dir = out / "simclr"
    plans = [StagePlan("simclr", _build("simclr", "simclr", recipe, **common, output_dir=str(simclr_dir)),
                       run_simclr)]  # fmt: skip
    vae_dir = out / "vae" / "vae"
    model_size = recipe.value("base", "size")
    if shared.prior is None:  # the VAE of the base model's size
        shape = SAR_ZERO123_SIZES[model_size]["vae"]
        plans.append(StagePlan("vae", _build(
            "vae", "vae", recipe, **common, output_dir=str(out / "vae"),
            layers_per_block=shape["layers_per_block"], latent_channels=shape["latent_channels"],
        ), run_vae))  # fmt: skip

    proxies_dir = out / "proxies"
    if _takes_proxy(shared.prior):  # each training chip's simulator proxies, the fine-tunes' condition
        plans.append(StagePlan("proxies", ProxiesConfig(
            data=data, output_dir=str(proxies_dir), image_size=shared.image_size,
        ), run_proxies))  # fmt: skip

    rehearsal_dir = out / "rehearsal"
    if shared.rehearsal:
        plans.append(StagePlan("rehearsal corpus", _build(
            "rehearsal corpus", "corpus", recipe, output_dir=str(rehearsal_dir), size=shared.image_size,
            seed=config.seed,
        ), run_corpus))  # fmt: skip

    def finetune(name: str, section: str, run_dir: Path, weight: float, pretrained: str | None) -> StagePlan:
        plumbing: dict[str, Any] = {**common, "output_dir": str(run_dir), "pfm_weight": weight,
                                    "encoder": str(simclr_dir / "encoder")}  # fmt: skip
        if shared.rehearsal:  # (a prior's fine-tunes) the whole rendered corpus, no subsample
            plumbing.update(rehearsal_data=str(rehearsal_dir / CORPUS_FOLDER), rehearsal_max_chips=None)
        if shared.prior is None:
            plumbing["vae"] = str(vae_dir)
        if _takes_proxy(shared.prior):
            plumbing["proxies"] = str(proxies_dir / PROXIES_FOLDER)
        if pretrained is not None:
            plumbing["pretrained"] = pretrained
        return StagePlan(name, _build(name, section, recipe, **plumbing), run_finetune)

    if shared.prior is None:
        plans.append(finetune("base model", "base", out / "base", 0.0, None))
        base = str(out / "base" / "pipeline")
    else:  # the paper's regime: every fine-tune starts from one pretrained multi-view prior
        base = str(resolve_pretrained(shared.prior))
    for weight in config.lambdas:
        name = f"finetune lambda={weight:g}"
        plans.append(finetune(name, "finetune", out / f"finetune_lambda{weight:g}", weight, base))
    return plans


def plan_stages(config: QuickstartConfig) -> list[StagePlan]:
    """Every stage of the run with its typed config, in order; builds (and so validates) all of them.

    Raises:
        ValueError: Naming the stage that refuses a setting of the recipe (or its ``--set`` items).
    """
    recipe = config.resolved_recipe()
    shared = recipe.shared
    _check_image_size(shared, recipe.value("base", "size"))
    out = Path(config.output_dir)
    data = out / "data" if config.data is None else Path(config.data)
    depression_data = out / "data_depression"
    with_depressions = config.data is None and bool(shared.depression_targets_deg)
    plans: list[StagePlan] = []
    if config.data is None:  # 15 and 17 deg as MSTAR; views at other depressions for the depression table
        classes = recipe.value("simulate", "classes")
        if len(classes) < 2 or len(set(classes)) != len(classes):  # the last one is held out
            raise ValueError(
                f"simulate.classes must name at least two distinct classes, got {classes!r}; expected names "
                f"from {list(TARGET_CLASSES)}"
            )
        simulated = [("simulate", data, [15.0, 17.0])]
        if with_depressions:
            depressions = sorted({17.0, *shared.depression_targets_deg})
            simulated.append(("simulate depressions", depression_data, depressions))
        for name, folder, depressions in simulated:
            plans.append(StagePlan(name, _build(
                name, "simulate", recipe, out=str(folder), depressions_deg=depressions,
                size=shared.image_size, seed=config.seed, resume=True,
            ), run_simulate))  # fmt: skip
    plans += _training_stages(config, recipe, out)
    pipelines = {
        plan.name[len("finetune ") :]: str(Path(plan.config.output_dir) / "pipeline")
        for plan in plans
        if plan.name.startswith("finetune ")
    }
    simclr_dir = out / "simclr"
    evaluator_dir = out / "evaluators"
    plans.append(StagePlan("evaluators", _build(
        "evaluators", "evaluators", recipe, output_dir=str(evaluator_dir), data=str(data),
        depression_data=str(depression_data) if with_depressions else None, seed=config.seed,
        image_size=shared.image_size, mixed_precision=shared.mixed_precision,
        simclr_encoders=[str(simclr_dir)], resume=True,
    ), run_evaluators))  # fmt: skip
    evaluation = {
        "pipeline": list(pipelines.values()), "pipeline_names": list(pipelines),
        "lambdas": list(config.lambdas), "evaluators": str(evaluator_dir),
        "protocol": _protocol(config, recipe), "crop_size": min(64, shared.image_size), "seed": config.seed,
        "resume": True,
    }  # fmt: skip
    plans.append(StagePlan("evaluate", _build(
        "evaluate", "evaluate", recipe, **evaluation, data=str(data), output_dir=str(out / "eval"),
    ), run_evaluate))  # fmt: skip
    if with_depressions:  # depression requests from 17 deg inputs, same evaluators
        plans.append(StagePlan("evaluate depressions", _build(
            "evaluate depressions", "evaluate", recipe, without=SPEED_SWEEP, **evaluation,
            data=str(depression_data), output_dir=str(out / "eval_depression"), same_depression=False,
            input_depression_deg=17.0, target_depressions_deg=list(shared.depression_targets_deg),
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
        ValueError: For a recipe a stage refuses (before any work), or a folder holding other work (one
            of the old recipe fields: naming the field and its replacement).
    """
    recipe = config.resolved_recipe()
    plans = plan_stages(config)  # every stage's config checked before any work
    out = Path(config.output_dir)
    gone = refuse_old_record(read_run_record(out) if out.is_dir() else None, f"output_dir: {str(out)!r}")
    # the recipe's values one by one, so that a refusal names the field that differs
    record = {**config_to_dict(config), **{f"recipe.{k}": v for k, v in recipe.flat().items()}}
    folder = open_stage_folder(
        out, "quickstart", record, data=None if config.data is None else config.data, resume=config.resume,
        # the recipe's name and the --set items may differ: the recipe.* values they give are compared
        restart=config.restart, may_differ=("output_dir", "resume", "restart", "recipe", "set",
                                            *QuickstartConfig.REMOVED_FIELDS, *gone),
        may_extend=("lambdas",), resume_hint="--resume",
    )  # fmt: skip
    report = out / "report.md"
    if folder.status == "new":
        save_config(config, out)
        write_json_atomic(recipe.to_dict(), out / RECIPE_FILE)
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
    protocol = _protocol(config, recipe)
    held_out = protocol[len("ood-") :] if protocol.startswith("ood-") else None
    report = write_report(out, recipe, config, held_out, timings)
    total = sum(t["seconds"] for t in timings.values())
    finish_run(folder, ["report.md"], seconds=total - float(folder.record.get("seconds", 0.0)))
    return report
