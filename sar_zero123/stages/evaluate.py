"""The evaluate stage: novel-view pipelines scored with the paper's protocol
(:mod:`sar_zero123.evaluation.protocol`), in a run folder.

Outputs: ``table3.{json,md}`` (the paper's rows beside ours, with the floor and the ceilings),
``table4.{json,md}`` (azimuth error under every evaluator backbone), ``views.png`` (Fig. 7/8),
``lambda_sweep.png`` (with ``lambdas``, Fig. 12), and with ``steps``/``schedulers``
``speed_error.{json,md,png}``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.domain import MAX_IMAGE_SIZE
from sar_zero123.evaluation.evaluators import Evaluators, load_evaluators
from sar_zero123.evaluation.protocol import (
    INPUT_COPY,
    PAPER_TABLE3,
    REAL_TARGET,
    SCHEDULERS,
    VAE_ROUND_TRIP,
    PairSet,
    add_gap_closed,
    build_pair_sets,
    check_pipeline_scaling,
    d_el_counts,
    generate_pair_targets,
    same_weights,
    score,
    vae_round_trip,
)
from sar_zero123.evaluation.scoring import PAPER_SCORING_SIZE
from sar_zero123.evaluation.speed import speed_error_rows, write_speed_error
from sar_zero123.evaluation.tables import (
    plot_lambda_sweep,
    plot_views,
    table3_markdown,
    table4_markdown,
)
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import MAX_INFERENCE_STEPS, SamplerSettings, check_sampler_start
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.runs.folder import (
    StageTimer,
    data_identity,
    finish_run,
    read_run_record,
)
from sar_zero123.runs.launch import check_device
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.stages.evaluators import model_identity

logger = logging.getLogger(__name__)

__all__ = [
    "EVALUATE_MAY_DIFFER",
    "MAX_EVALUATION_PAIRS",
    "MAX_EVAL_BATCH_SIZE",
    "MAX_FIGURE_PAIRS",
    "MAX_INFERENCE_STEPS",
    "MAX_SWEEP_STEP_COUNTS",
    "EvaluateConfig",
    "evaluation_pairs",
    "load_evaluation",
    "run_evaluate",
]

MAX_EVALUATION_PAIRS = 100_000
MAX_SWEEP_STEP_COUNTS = 16  # each a full generation per pipeline and scheduler
MAX_FIGURE_PAIRS = 32  # per group in views.png
MAX_EVAL_BATCH_SIZE = 1_024
#: Settings that never change what the folder holds.
EVALUATE_MAY_DIFFER = ("resume", "restart", "device", "output_dir")


@dataclass
class EvaluateConfig(SamplerSettings):
    """Score novel-view pipelines with the paper's protocol and write Tables III/IV and figures.

    The sampler's fields are inherited (:class:`~sar_zero123.model.sampler.SamplerSettings`); each left unset
    takes the value each pipeline records, else the library's.
    """

    ADVANCED_FIELDS = (
        "same_depression", "input_depression_deg", "outside_trained_range",
        "speed_n", "image_size",
        "crop_size", "eval_batch_size", "num_figure_pairs", "device",
    )  # fmt: skip
    REMOVED_FIELDS = {
        "work_dir": RemovedField(None, "the simulated dataset is cached in output_dir"),
        "chip_crop_size": RemovedField(None, "chips larger than image_size are centre-cropped to it (their "
                                       "pixel spacing kept)"),
        "max_d_az_deg": RemovedField(None, "every pair of views of one object is scored, any |d_az|"),
        "paper_scoring_size": RemovedField(256, f"the paper-comparable metrics resize to the authors' "
                                           f"{PAPER_SCORING_SIZE} px before their crop"),
        "vae": RemovedField(None, "a VAE replacing the pipelines' served the decoder fine-tune, which "
                            "measured no gain; each pipeline decodes with its own VAE"),
        "speckle_looks": RemovedField(None, "rows of views with speckle re-added were a diagnostic that "
                                      "moved accuracy little"),
        "blurred_target_sigmas_px": RemovedField([], "rows of blurred real targets were a diagnostic"),
    }  # fmt: skip

    pipeline: list[str] = field(default_factory=list)  # SARZero123Pipeline folders (repeat the flag)
    pipeline_names: list[str] = field(default_factory=list)  # row labels (default: folder names)
    lambdas: list[float] = field(default_factory=list)  # PFM weight of each pipeline, for the Fig. 12 sweep
    evaluators: str = "runs/evaluators"  # output folder of train/train_evaluators.py
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
    protocol: str = "extended"  # "extended" (seen only) or "ood-<CLASS>" (half seen, half unseen)
    same_depression: bool = True  # pair views at one depression; False also pairs across (d_el != 0)
    input_depression_deg: float | None = None  # only pairs whose input is at this depression (None: any)
    target_depressions_deg: list[float] | None = None  # only pairs with targets at one of these (None: any)
    # evaluate requests outside a pipeline's trained d_el / depression range (listed in table3.json)
    outside_trained_range: bool = False
    n: int = 1000  # generated samples in total (split evenly between seen and unseen; at most 100,000)
    steps: list[int] = field(default_factory=list)  # speed/error sweep: step counts (e.g. 10 20 50)
    schedulers: list[str] = field(default_factory=list)  # speed/error sweep: ddim, dpmsolver++, euler, unipc
    speed_n: int | None = None  # samples per speed/error point, from the seen pairs (None: all of them)
    image_size: int | None = None  # chip size fed to the pipelines (None: the pipeline's own)
    crop_size: int = 64  # centre crop for MS-SSIM and Kuan+SSIM (paper: 64)
    eval_batch_size: int = 16  # pairs per pipeline call (and per VAE / evaluator call)
    num_figure_pairs: int = 4  # pairs per group shown in views.png
    output_dir: str = "runs/eval"  # where tables and figures go
    device: str | None = None  # torch device (None: cuda when available)
    seed: int = 0  # pair sampling and generator seeds
    resume: bool = False  # an unfinished run with the same settings is redone; a finished one is returned
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.device is not None:
            check_device(self.device)
        self._check_pipelines()
        self._check_sizes()
        self._check_sweep()
        self._check_start()
        self._check_depressions()
        if self.resume and self.restart:
            raise ValueError("resume and restart: choose one (continue this run, or move it aside)")

    def _check_pipelines(self) -> None:
        if not self.pipeline:
            raise ValueError("pipeline: give at least one pipeline folder")
        if self.pipeline_names and len(self.pipeline_names) != len(self.pipeline):
            raise ValueError(
                f"pipeline_names has {len(self.pipeline_names)} names for {len(self.pipeline)} pipelines"
            )
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"pipeline_names: each row needs its own name, got {self.names}")
        if self.lambdas and len(self.lambdas) != len(self.pipeline):
            raise ValueError(f"lambdas has {len(self.lambdas)} values for {len(self.pipeline)} pipelines")
        if self.protocol != "extended" and not self.protocol.startswith("ood-"):
            raise ValueError(f"protocol must be 'extended' or 'ood-<CLASS>', got {self.protocol!r}")

    def _check_start(self) -> None:
        """A given ``strength`` leaves a denoising step at the sweep's step counts too."""
        if self.strength is not None and self.steps:
            check_sampler_start(self.strength, None, {"steps": min(self.steps)})

    def _check_sizes(self) -> None:
        check_minimum(self, "n", "eval_batch_size", "crop_size", minimum=1)
        check_minimum(self, "image_size", "speed_n", minimum=1, optional=True)
        check_minimum(self, "num_figure_pairs", minimum=0)
        for name, bound in (
            ("n", MAX_EVALUATION_PAIRS),
            ("eval_batch_size", MAX_EVAL_BATCH_SIZE),
            ("num_figure_pairs", MAX_FIGURE_PAIRS),
            ("image_size", MAX_IMAGE_SIZE),
            ("crop_size", MAX_IMAGE_SIZE),
        ):
            value = getattr(self, name)
            if value is not None and value > bound:
                raise ValueError(f"{name} must be <= {bound:,}, got {value:,}")
        if self.crop_size > PAPER_SCORING_SIZE:
            raise ValueError(f"crop_size must be <= {PAPER_SCORING_SIZE}, got {self.crop_size}")
        if self.protocol.startswith("ood-") and self.n < 4:
            raise ValueError(
                f"n must be >= 4 for an ood protocol (at least 2 seen and 2 unseen pairs), got {self.n}"
            )
        if self.n < 2:
            raise ValueError(f"n must be >= 2 (the Frechet distance needs two views), got {self.n}")

    def _check_sweep(self) -> None:
        unknown = sorted(set(self.schedulers) - set(SCHEDULERS))
        if unknown:
            raise ValueError(f"schedulers: unknown {unknown}; choose from {sorted(SCHEDULERS)}")
        if bool(self.steps) != bool(self.schedulers):
            raise ValueError("steps and schedulers must be given together for the speed/error sweep")
        for name in ("steps", "schedulers"):
            if len(set(getattr(self, name))) != len(getattr(self, name)):
                raise ValueError(f"{name}: each value once, got {getattr(self, name)}")
        if len(self.steps) > MAX_SWEEP_STEP_COUNTS:
            raise ValueError(f"steps: at most {MAX_SWEEP_STEP_COUNTS} step counts, got {len(self.steps)}")
        if any(not 1 <= step <= MAX_INFERENCE_STEPS for step in self.steps):
            raise ValueError(f"steps must lie in [1, {MAX_INFERENCE_STEPS}], got {self.steps}")
        seen = self.n if self.protocol == "extended" else self.n - self.n // 2
        if self.speed_n is not None and self.speed_n > seen:
            raise ValueError(
                f"speed_n must be <= the {seen} seen pairs its points are drawn from (n = {self.n}, protocol "
                f"{self.protocol}), got {self.speed_n}"
            )

    def _check_depressions(self) -> None:
        if self.target_depressions_deg is not None and not self.target_depressions_deg:
            raise ValueError("target_depressions_deg: give at least one depression, or none for any")
        for name, values in (
            ("input_depression_deg", [self.input_depression_deg]),
            ("target_depressions_deg", self.target_depressions_deg or []),
        ):
            if any(value is not None and not 0.0 < value < 90.0 for value in values):
                raise ValueError(f"{name} must lie in (0, 90) degrees, got {getattr(self, name)}")
        if (
            self.same_depression
            and self.input_depression_deg is not None
            and any(t != self.input_depression_deg for t in self.target_depressions_deg or [])
        ):
            raise ValueError(
                f"same_depression pairs views at one depression, so no {self.input_depression_deg} deg input "
                f"has a target at {self.target_depressions_deg} deg; pass --no-same_depression"
            )

    @property
    def names(self) -> list[str]:
        """Row label of each pipeline."""
        if self.pipeline_names:
            return list(self.pipeline_names)
        names = [Path(p).name for p in self.pipeline]
        if len(set(names)) != len(names):
            names = [f"{Path(p).parent.name}/{Path(p).name}" for p in self.pipeline]
        return names


def evaluation_pairs(config: EvaluateConfig, evaluators: Evaluators, image_size: int) -> dict[str, PairSet]:
    """The pairs of ``config``'s protocol: the same pairs and seeds for every pipeline and every run."""
    return build_pair_sets(
        evaluators,
        data=config.data,
        protocol=config.protocol,
        n=config.n,
        image_size=image_size,
        work_dir=config.output_dir,
        seed=config.seed,
        same_depression=config.same_depression,
        input_depression_deg=config.input_depression_deg,
        target_depressions_deg=config.target_depressions_deg,
        chip_crop_size=None,
        evaluators_name=config.evaluators,
    )


def load_evaluation(folder: str | Path) -> dict[str, Any]:
    """What a finished evaluation wrote: ``{"table3": {row: {group: scores}}, "speed_error": [rows]}``.

    Raises:
        ValueError: If ``folder`` holds no finished evaluate run (its tables would be partial or stale).
    """
    folder = Path(folder)
    record = read_run_record(folder)
    if record is None or record.get("stage") != "evaluate" or not record.get("finished"):
        raise ValueError(f"{str(folder)!r} holds no finished evaluate run")
    speed = folder / "speed_error.json"
    return {
        "table3": json.loads((folder / "table3.json").read_text())["results"],
        "speed_error": json.loads(speed.read_text())["rows"] if speed.is_file() else [],
    }


def run_evaluate(config: EvaluateConfig) -> Path:
    """Score every pipeline on the protocol's pairs and write the tables and figures; returns the folder.

    Raises:
        ValueError: For a folder holding other work; if the data cannot supply ``n`` distinct pairs.
        FileNotFoundError: If the data, the evaluators or a pipeline folder does not exist.
    """
    timer = StageTimer()
    # 1. the run-folder rule, before any work
    inputs = {
        "data": data_identity(config.data),
        "evaluators": model_identity(config.evaluators, "evaluators"),
        "pipelines": [
            model_identity(resolve_pretrained(path), f"pipeline[{i}]")
            for i, path in enumerate(config.pipeline)
        ],
    }
    folder = open_stage_folder(
        config.output_dir, "evaluate", config, data=inputs, resume=config.resume, restart=config.restart,
        may_differ=EVALUATE_MAY_DIFFER, resume_hint="--resume",
    )  # fmt: skip
    if folder.finished:
        logger.info("%s already holds this evaluation", folder.path)
        return folder.path
    device = torch.device(config.device or ("cuda" if torch.cuda.is_available() else "cpu"))

    # 2. models and pairs
    with withdrawn_if_setup_fails(folder):
        evaluators = load_evaluators(config.evaluators, device=device)
        pipes, lifted = _load_pipelines(config, evaluators, device)
        sizes = {pipe.default_image_size for pipe in pipes.values()}
        if config.image_size is None and len(sizes) != 1:
            raise ValueError(
                f"pipelines were built for different image sizes {sorted(sizes)}; pass --image_size"
            )
        pair_sets = evaluation_pairs(config, evaluators, config.image_size or sizes.pop())
    save_config(config, folder.path)

    # 3. Table III / IV, with the floor (input copy) and the ceilings (real target, VAE round trip)
    results = _score_references(config, pipes, pair_sets, evaluators, device)
    generated = _score_pipelines(config, pipes, pair_sets, evaluators, device, results)
    add_gap_closed(results, floor=INPUT_COPY, ceiling=VAE_ROUND_TRIP)
    outputs = _write_tables(config, folder.path, results, pair_sets, evaluators, lifted, device, pipes)
    if config.num_figure_pairs > 0:
        plot_views(pair_sets, generated, config.num_figure_pairs, folder.path / "views.png")
        outputs.append("views.png")
    if config.lambdas:
        sweep = {name: results[name] for name in pipes}
        plot_lambda_sweep(sweep, dict(zip(pipes, config.lambdas)), folder.path / "lambda_sweep.png")
        outputs.append("lambda_sweep.png")

    # 4. speed against error (the first speed_n seen pairs)
    if config.steps:
        seen = pair_sets["seen"].subset(config.speed_n or len(pair_sets["seen"]))
        rows = speed_error_rows(
            pipes, seen, evaluators, schedulers=config.schedulers, steps=config.steps,
            guidance_scale=config.guidance_scale, sampler=config.sampler_settings(),
            batch_size=config.eval_batch_size, scoring=_scoring(config, device), device=device,
        )  # fmt: skip
        outputs += write_speed_error(rows, folder.path, device, num_pairs=len(seen))
    finish_run(
        folder, outputs, seconds=timer.seconds,
        results={"rows": list(results), "pairs": {group: len(p) for group, p in pair_sets.items()},
                 "device": str(device)},
    )  # fmt: skip
    return folder.path


def _load_pipelines(
    config: EvaluateConfig, evaluators: Evaluators, device: torch.device
) -> tuple[dict[str, SARZero123Pipeline], dict[str, dict]]:
    """Each pipeline by its row name, and those whose trained-range refusal was lifted, with their ranges."""
    pipes, lifted = {}, {}
    for name, path in zip(config.names, config.pipeline):
        check_pipeline_scaling(resolve_pretrained(path), evaluators)
        pipe = SARZero123Pipeline.from_pretrained(path)
        pipe = pipe.to(device)
        pipe.set_progress_bar_config(disable=True)
        config.apply_scheduler(pipe)
        pipes[name] = pipe
        projection = pipe.pose_projection.config
        if config.outside_trained_range and projection.get("trained_d_el_deg") is not None:
            trained = projection["trained_d_el_deg"]
            logger.warning("%s: trained d_el range %s lifted (--outside_trained_range)", name, trained)
            lifted[name] = {
                "trained_d_el_deg": trained,
                "trained_depression_deg": projection.get("trained_depression_deg"),
            }
            pipe.pose_projection.register_to_config(trained_d_el_deg=None, trained_depression_deg=None)
    return pipes, lifted


def _scoring(config: EvaluateConfig, device: torch.device) -> dict[str, Any]:
    """The keyword arguments of :func:`~sar_zero123.evaluation.protocol.score` for this evaluation."""
    return {
        "crop_size": config.crop_size,
        "paper_scoring_size": PAPER_SCORING_SIZE,
        "batch_size": max(config.eval_batch_size, 32),
        "device": device,
    }


def _score_references(
    config: EvaluateConfig,
    pipes: dict[str, SARZero123Pipeline],
    pair_sets: dict[str, PairSet],
    evaluators: Evaluators,
    device: torch.device,
) -> dict[str, dict[str, dict[str, float]]]:
    """The floor (input copy) and the ceilings (real target; VAE round trip, one row per distinct VAE)."""
    scoring = _scoring(config, device)
    results = {
        INPUT_COPY: {group: score(p.inputs, p, evaluators, **scoring) for group, p in pair_sets.items()},
        REAL_TARGET: {group: score(p.targets, p, evaluators, **scoring) for group, p in pair_sets.items()},
    }
    first_vae = next(iter(pipes.values())).vae
    for index, (name, pipe) in enumerate(pipes.items()):
        if index > 0 and same_weights(pipe.vae, first_vae):
            continue
        row = VAE_ROUND_TRIP if index == 0 else f"{VAE_ROUND_TRIP} ({name})"
        results[row] = {}
        for group, pairs in pair_sets.items():
            views = vae_round_trip(pipe, pairs.targets, config.eval_batch_size, device)
            results[row][group] = score(views, pairs, evaluators, **scoring)
        logger.info("%s: %s", row, json.dumps(results[row]))
    return results


def _score_pipelines(
    config: EvaluateConfig,
    pipes: dict[str, SARZero123Pipeline],
    pair_sets: dict[str, PairSet],
    evaluators: Evaluators,
    device: torch.device,
    results: dict[str, dict[str, dict[str, float]]],
) -> dict[str, dict[str, torch.Tensor]]:
    """Adds each pipeline's row to ``results``; returns its generated views, ``{name: {group: views}}``."""
    generated: dict[str, dict[str, torch.Tensor]] = {}
    for name, pipe in pipes.items():
        results[name], generated[name] = {}, {}
        for group, pairs in pair_sets.items():
            images, seconds = generate_pair_targets(
                pipe, pairs, sampler=config.sampler_settings(), batch_size=config.eval_batch_size,
                device=device, desc=f"{name} {group}",
            )  # fmt: skip
            generated[name][group] = images
            scores = score(images, pairs, evaluators, **_scoring(config, device))
            results[name][group] = {**scores, "seconds": seconds}
            logger.info("%s %s: %s", name, group, json.dumps(results[name][group]))
    return generated


def _write_tables(
    config: EvaluateConfig,
    output_dir: Path,
    results: dict[str, dict[str, dict[str, float]]],
    pair_sets: dict[str, PairSet],
    evaluators: Evaluators,
    lifted: dict[str, dict],
    device: torch.device,
    pipes: dict[str, SARZero123Pipeline],
) -> list[str]:
    """``table3.{json,md}`` and ``table4.{json,md}``; returns their names."""
    evaluator_metrics = {
        name: model.metrics
        for name, model in (
            ("classifier", evaluators.classifier),
            ("regressor", evaluators.regressor),
            ("depression_regressor", evaluators.depression_regressor),
        )
        if model is not None
    }
    table3 = {
        "protocol": config.protocol,
        "device": str(device),
        **config.sampler_arguments(),
        "samplers": {name: config.resolved(getattr(p.config, "sampler", None)) for name, p in pipes.items()},
        "results": results,
        "paper": PAPER_TABLE3,
        "evaluator_test_metrics": evaluator_metrics,
        "same_depression": config.same_depression,
        "outside_trained_range": lifted,
        "input_depression_deg": config.input_depression_deg,
        "target_depressions_deg": config.target_depressions_deg,
        "pairs_per_d_el_deg": {group: d_el_counts(pairs.d_el_deg) for group, pairs in pair_sets.items()},
    }
    write_json_atomic(table3, output_dir / "table3.json")
    (output_dir / "table3.md").write_text(table3_markdown(results, config.protocol.startswith("ood-")))
    write_json_atomic(results, output_dir / "table4.json")
    (output_dir / "table4.md").write_text(table4_markdown(results))
    return ["table3.json", "table3.md", "table4.json", "table4.md"]
