"""Runs sized to one device call's wall-clock budget: priors trained for minutes, not steps (their arms,
their start, the corpus that fits), the quickstart's stages under one time limit, and a trained pipeline
packed into parts small enough for the call to return.

The GPU scripts (``benchmarks/gpu_prior.py``, ``benchmarks/gpu_mstar_pfm.py``) parse their flags and call
these; every piece runs on a CPU too, which is how they are tested.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import tarfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.sim.corpus import write_prior_corpus
from sar_zero123.stages.evaluate import EvaluateConfig
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig
from sar_zero123.stages.finetune import FinetuneConfig
from sar_zero123.stages.presets import QuickstartConfig
from sar_zero123.stages.prior import PriorConfig, prior_base_config
from sar_zero123.stages.quickstart import StagePlan, plan_stages
from sar_zero123.stages.simclr import PretrainSimCLRConfig
from sar_zero123.stages.vae import TrainVAEConfig

__all__ = [
    "PART_BYTES", "PRIOR_ARMS", "UNBOUNDED_STEPS", "affordable_vehicles", "arm_config", "arm_label",
    "budgeted_plans", "init_pipeline", "pack_pipeline", "parse_arm", "with_budget",
]  # fmt: skip

logger = logging.getLogger(__name__)

#: The arms' condition inputs (``FinetuneConfig.spatial_pose``); ``<input>@<size>`` trains that input at
#: another ``build_sar_zero123`` size (``rotated_input@micro``: the quickstart's size, one that can ship).
PRIOR_ARMS = {"global": None, "rotated_input": "rotated_input"}
#: The largest part :func:`pack_pipeline` writes: under the 16 MiB a device call may return per file.
PART_BYTES = 15 * 2**20
#: A fine-tune bounded by its minutes has no step count to stop at.
UNBOUNDED_STEPS = 10_000_000


def arm_label(arm: str) -> str:
    """The arm's name in files and folders (letters, digits, ``._-`` only: ``rotated_input-micro``)."""
    return arm.replace("@", "-")


def parse_arm(arm: str, default_size: str) -> tuple[str | None, str]:
    """``(spatial_pose, size)`` of an arm such as ``global``, ``rotated_input`` or ``rotated_input@micro``.

    Raises:
        ValueError: Naming the arm, for an unknown condition input or size.
    """
    name, _, size = arm.partition("@")
    size = size or default_size
    if name not in PRIOR_ARMS or size not in SAR_ZERO123_SIZES:
        raise ValueError(
            f"arms: {arm!r} is not <input>[@<size>] with input one of {list(PRIOR_ARMS)} and size one of "
            f"{sorted(SAR_ZERO123_SIZES)}"
        )
    return PRIOR_ARMS[name], size


def init_pipeline(init: str | None, spatial_pose: str | None, arm: str) -> Path | None:
    """The folder an arm starts from (a bundled name or a folder), or None (``None``/``"none"``: scratch).

    Raises:
        ValueError: Naming the arm, when the pipeline's condition input is not the arm's.
    """
    if init is None or init.lower() == "none":
        return None
    folder = resolve_pretrained(init)
    found = json.loads((folder / "pose_projection" / "config.json").read_text()).get("spatial_pose")
    if found != spatial_pose:
        raise ValueError(
            f"init: {init} takes the condition input {found or 'global'!r}, arm {arm!r} needs "
            f"{spatial_pose or 'global'!r}"
        )
    return folder


def arm_config(
    arm: str, minutes: float, *, size: str, prior: Mapping[str, Any], init: str | None = None, **finetune: Any
) -> FinetuneConfig:
    """One arm's prior, trained for ``minutes`` of steps: the UNet stage
    (:func:`~sar_zero123.stages.prior.prior_base_config`) of ``PriorConfig(**prior)`` with the arm's
    condition input and size (:func:`parse_arm`, ``size`` by default), from ``init``'s weights when given
    (the pipeline keeps its own condition input, size and prediction type), one checkpoint at the prior's
    ``base_steps``, and the ``finetune`` fields replaced.

    Raises:
        ValueError: For an unknown arm, or an ``init`` whose condition input is not the arm's.
    """
    spatial_pose, size = parse_arm(arm, size)
    config = PriorConfig(**prior, model_size=size, spatial_pose=spatial_pose)
    base = prior_base_config(config, Path(str(config.vae)), Path(str(config.corpus)))
    start = init_pipeline(init, spatial_pose, arm)
    if start is not None:
        base = dataclasses.replace(
            base, pretrained=str(start), spatial_pose=None, input_depression=False, prediction_type=None
        )
    return dataclasses.replace(
        base, max_train_minutes=minutes, checkpointing_steps=config.base_steps, checkpoints_total_limit=1,
        **finetune,
    )  # fmt: skip


def affordable_vehicles(
    work: Path, num_vehicles: int, views_per_vehicle: int, minutes: float, workers: int, seed: int
) -> int:
    """``num_vehicles``, or fewer where the render rate of two pilots says they would overrun ``minutes``.

    The pilots render one and then five vehicles per worker into ``work/corpus_pilot`` (removed after); the
    difference of their times is the rate without the process pool's start-up, which one pilot alone would
    count as rendering. A corpus already in ``work/corpus`` (a re-run) keeps the number it was written with;
    at least 64 vehicles are kept.
    """
    options = work / "corpus" / "corpus.json"
    if options.is_file():
        return int(json.loads(options.read_text())["num_vehicles"])
    pilot = work / "corpus_pilot"
    timings = []
    for per_worker in (1, 5):
        shutil.rmtree(pilot, ignore_errors=True)
        count = max(per_worker * workers, 2)
        start = time.monotonic()
        write_prior_corpus(pilot, num_vehicles=count, views_per_vehicle=views_per_vehicle,
                           num_validation_vehicles=1, seed=seed, num_workers=workers,
                           progress=False)  # fmt: skip
        timings.append((count, time.monotonic() - start))
    shutil.rmtree(pilot, ignore_errors=True)
    (few, few_seconds), (many, many_seconds) = timings
    extra = many_seconds - few_seconds
    rate = (many - few) / extra if extra > 0 else many / many_seconds  # vehicles per second, rendering
    start_up = max(few_seconds - few / rate, 0.0)
    affordable = int(0.9 * rate * max(60.0 * minutes - start_up, 0.0))
    logger.info("corpus pilots: %.1f vehicles/s after %.1f s start-up; %d fit %.1f min", rate, start_up,
                affordable, minutes)  # fmt: skip
    return max(min(num_vehicles, affordable), 64)


def pack_pipeline(pipeline: Path, out: Path, name: str) -> list[str]:
    """The pipeline folder with its UNet in float16, as ``out/<name>.tar.part00, 01, ...`` (each at most
    :data:`PART_BYTES`); returns the parts' names.

    The archive leaves out ``vae/`` (a bundled prior's, restored from the package) and the manifest, which
    sealed the folder with the float32 UNet: the restored folder loads as an unsealed one, into float32.
    """
    from diffusers import UNet2DConditionModel

    unet = UNet2DConditionModel.from_pretrained(pipeline / "unet")
    unet.to(torch.float16).save_pretrained(pipeline / "unet")
    archive = out / f"{name}.tar"
    with tarfile.open(archive, "w") as tar:
        tar.add(pipeline, arcname=f"{name}_pipeline", filter=_without_vae)
    payload = archive.read_bytes()
    archive.unlink()
    parts = []
    for index, start in enumerate(range(0, len(payload), PART_BYTES)):
        part = out / f"{name}.tar.part{index:02d}"
        part.write_bytes(payload[start : start + PART_BYTES])
        parts.append(part.name)
    return parts


def _without_vae(member: tarfile.TarInfo) -> tarfile.TarInfo | None:
    return None if "/vae" in member.name or member.name.endswith("/manifest.json") else member


def budgeted_plans(config: QuickstartConfig) -> list[StagePlan]:
    """The quickstart's stages for ``config`` (:func:`~sar_zero123.stages.quickstart.plan_stages`) in the
    order a budgeted call runs them: SimCLR, (VAE,) evaluators, (base model,) fine-tunes, evaluation.

    Raises:
        ValueError: Naming the stages, for a recipe that simulates data or renders a corpus.
    """
    plans = {plan.name: plan for plan in plan_stages(config)}
    finetunes = [name for name in plans if name.startswith("finetune ")]
    order = [n for n in ("simclr", "vae", "evaluators", "base model", *finetunes, "evaluate") if n in plans]
    unknown = sorted(set(plans) - set(order))
    if unknown:
        raise ValueError(f"recipe {config.recipe!r} plans stages this call does not run: {unknown}")
    return [plans[name] for name in order]


def with_budget(
    plan: StagePlan, minutes: float | None, simclr_minutes: float, eval_batch_size: int
) -> StagePlan:
    """``plan`` fitted into the call: SimCLR stops at ``simclr_minutes``; a fine-tune trains for ``minutes``
    (its steps unbounded, its cached latents on the device); the evaluation runs without the speed sweep,
    ``eval_batch_size`` pairs per call; the VAE and the evaluators as planned.

    Raises:
        ValueError: Naming the stage, for a fine-tune whose learning rate would decay over the unbounded
            steps.
        TypeError: For a stage this call has no rule for.
    """
    config = plan.config
    if isinstance(config, PretrainSimCLRConfig):
        config = dataclasses.replace(config, max_train_minutes=simclr_minutes)
    elif isinstance(config, FinetuneConfig):
        if config.lr_scheduler not in ("constant", "constant_with_warmup"):
            raise ValueError(f"stage {plan.name}: lr_scheduler {config.lr_scheduler!r} would decay over "
                             f"{UNBOUNDED_STEPS:,} steps; a fine-tune bounded by minutes takes 'constant'")
        config = dataclasses.replace(config, max_train_minutes=minutes, max_train_steps=UNBOUNDED_STEPS,
                                     checkpointing_steps=UNBOUNDED_STEPS, cache_on_device=True)  # fmt: skip
    elif isinstance(config, EvaluateConfig):
        config = dataclasses.replace(config, steps=[], schedulers=[], speed_n=None,
                                     eval_batch_size=eval_batch_size)  # fmt: skip
    elif not isinstance(config, TrainEvaluatorsConfig | TrainVAEConfig):
        raise TypeError(f"stage {plan.name}: no budget rule for {type(config).__name__}")
    return dataclasses.replace(plan, config=config)
