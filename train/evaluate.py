"""Evaluate novel-view pipelines with the paper's protocol (Table III, Table IV, Fig. 7/8, Fig. 12, speed).

    python train/evaluate.py --pipeline runs/pfm0/pipeline --pipeline runs/pfm4/pipeline \\
        --evaluators runs/evaluators --data /path/to/mstar --protocol ood-T72 --n 1000 \\
        --num-inference-steps 50 --guidance-scale 3.0 --seed 0 --output_dir runs/eval

Protocol: pairs of two test views of one object (input, target), conditioned on their relative pose
(d_az, d_el). With `--protocol ood-<CLASS>` half the pairs come from the seen classes (extended test split,
15 deg, without the held-out class) and half from the unseen class (every chip of it); with `extended` all
pairs are seen. Each pipeline generates the target view from the input view; the five metrics of
`sar_zero123.evaluators.score_views` score it. Pairs and generator seeds are the same for every pipeline.

Depression requests: `--input_depression_deg 17 --target_depressions_deg 10 30 45 --no-same_depression`
pairs 17 deg inputs with targets at 10, 30 and 45 deg (d_el = -7, +13, +28), drawn from every chip of the
seen (and unseen) classes at every depression. With a depression regressor among the evaluators
(`train_evaluators.py --depression_data`) Table III gains `Dep. err.` and `Dep. gap closed`; for pairs with
d_el != 0 it gains `Closer to target dep.` (`sar_zero123.evaluators.closer_to_target_depression`).

Outputs in `--output_dir`: `table3.{json,md}` (the paper's rows beside ours, plus an "input copy" baseline
that returns the input view unchanged), `table4.{json,md}` (azimuth error under every evaluator backbone),
`views.png` (input | each pipeline | target, Fig. 7/8), `lambda_sweep.png` (with `--lambdas`, Fig. 12),
and with `--steps`/`--schedulers`: `speed_error.{json,md,png}` (azimuth error and accuracy against images/s).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from diffusers import DDIMScheduler, DPMSolverMultistepScheduler, EulerDiscreteScheduler
from torch.utils.data import DataLoader
from tqdm.auto import tqdm

from sar_zero123.conditioning import encode_condition_latents
from sar_zero123.config import check_minimum, parse_config, save_config, write_json_atomic
from sar_zero123.data import (
    SCALING_FILE,
    ChipRecord,
    DecibelScaling,
    ViewPairDataset,
    load_chip,
    load_index,
    prepare_splits,
    split_records,
)
from sar_zero123.evaluators import (
    Evaluators,
    check_class_names,
    closer_to_target_depression,
    load_evaluators,
    score_views,
    standard_error,
)
from sar_zero123.pipeline import SARZero123Pipeline

logger = logging.getLogger(__name__)

# ms_ssim / kuan_ssim are paper-comparable (the authors' calls); the *_corrected columns sit beside them.
METRICS = (
    "accuracy",
    "azimuth_error_deg",
    "sfd",
    "ms_ssim",
    "kuan_ssim",
    "ms_ssim_corrected",
    "kuan_ssim_corrected",
)
METRIC_LABELS = {
    "accuracy": "Acc. (%) ↑",
    "azimuth_error_deg": "Az. err. (deg) ↓",
    "sfd": "SFD ↓",
    "ms_ssim": "MS-SSIM ↑",
    "kuan_ssim": "Kuan+SSIM ↑",
    "ms_ssim_corrected": "MS-SSIM corr. ↑",
    "kuan_ssim_corrected": "Kuan+SSIM corr. ↑",
    "depression_error_deg": "Dep. err. (deg) ↓",
    "closer_to_target_depression": "Closer to target dep. ↑",
}
# columns only pairs with a depression change (and a depression regressor, for the error) give
DEPRESSION_METRICS = ("depression_error_deg", "closer_to_target_depression")
# the errors whose floor-to-ceiling gap Table III reports, keyed `<first word>_gap_closed`
GAP_METRICS = ("azimuth_error_deg", "accuracy", "depression_error_deg")
GAP_LABELS = {
    "azimuth_gap_closed": "Az. gap closed ↑",
    "accuracy_gap_closed": "Acc. gap closed ↑",
    "depression_gap_closed": "Dep. gap closed ↑",
}
BLUR_SIGMA_PX = 1.5  # Gaussian blur before the "closer to target depression" correlations
# Table III of the paper (zero123 fine-tuned on MSTAR, 1,000 samples: 500 seen, 500 unseen T72).
PAPER_TABLE3 = {
    "paper: w/o PFM": {
        "seen": {
            "accuracy": 86.6,
            "azimuth_error_deg": 28.5,
            "sfd": 3.89,
            "ms_ssim": 0.6680,
            "kuan_ssim": 0.7330,
        },
        "unseen": {
            "accuracy": 25.8,
            "azimuth_error_deg": 53.4,
            "sfd": 8.43,
            "ms_ssim": 0.6165,
            "kuan_ssim": 0.6731,
        },
    },
    "paper: PFM (lambda=4)": {
        "seen": {
            "accuracy": 89.0,
            "azimuth_error_deg": 23.5,
            "sfd": 1.84,
            "ms_ssim": 0.6720,
            "kuan_ssim": 0.7374,
        },
        "unseen": {
            "accuracy": 46.6,
            "azimuth_error_deg": 44.0,
            "sfd": 6.28,
            "ms_ssim": 0.6195,
            "kuan_ssim": 0.6786,
        },
    },
}
INPUT_COPY = "input copy (floor)"  # the input view returned as the generated one: ignores the pose
REAL_TARGET = "real target (ceiling)"  # the true target view: the best any generator can score
VAE_ROUND_TRIP = "VAE round trip (ceiling)"  # the target encoded and decoded: the best for this VAE
REFERENCE_ROWS = (INPUT_COPY, REAL_TARGET, VAE_ROUND_TRIP)
SCHEDULERS = {
    "ddim": (DDIMScheduler, {}),
    "dpmsolver++": (DPMSolverMultistepScheduler, {"algorithm_type": "dpmsolver++"}),
    "euler": (EulerDiscreteScheduler, {}),
}


@dataclass
class EvaluateConfig:
    """Score novel-view pipelines with the paper's protocol and write Tables III/IV and figures."""

    pipeline: list[str] = field(default_factory=list)  # SARZero123Pipeline folders (repeat the flag)
    pipeline_names: list[str] = field(default_factory=list)  # row labels (default: folder names)
    lambdas: list[float] = field(default_factory=list)  # PFM weight of each pipeline, for the Fig. 12 sweep
    evaluators: str = "runs/evaluators"  # output folder of train/train_evaluators.py
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
    work_dir: str | None = None  # cache of the simulated dataset (default: output_dir)
    protocol: str = "extended"  # "extended" (seen only) or "ood-<CLASS>" (half seen, half unseen)
    same_depression: bool = True  # pair views at one depression; False also pairs across (d_el != 0)
    input_depression_deg: float | None = None  # only pairs whose input is at this depression (None: any)
    target_depressions_deg: list[float] | None = None  # only pairs with targets at one of these (None: any)
    # evaluate requests outside a pipeline's trained d_el / depression range (its refusal lifted, listed in
    # table3.json): to measure how a model that never saw such requests answers them
    outside_trained_range: bool = False
    max_d_az_deg: float | None = None  # largest |d_az| of a pair (None: any)
    n: int = 1000  # generated samples in total (split evenly between seen and unseen)
    num_inference_steps: int = 50  # denoising steps for Tables III/IV
    guidance_scale: float = 3.0  # classifier-free guidance weight
    steps: list[int] = field(default_factory=list)  # speed/error sweep: step counts (e.g. 10 20 50)
    schedulers: list[str] = field(default_factory=list)  # speed/error sweep: ddim, dpmsolver++, euler
    speed_n: int | None = None  # samples per speed/error point (None: n)
    image_size: int | None = None  # chip size fed to the pipelines (None: the pipeline's own)
    chip_crop_size: int | None = None  # centre crop of the chip files before resizing
    crop_size: int = 64  # centre crop for MS-SSIM and Kuan+SSIM (paper: 64)
    paper_scoring_size: int | None = 256  # side before the paper-comparable 64 crop (authors: 256)
    eval_batch_size: int = 16  # pairs per pipeline call (and per VAE / evaluator call)
    num_figure_pairs: int = 4  # pairs per group shown in views.png
    output_dir: str = "runs/eval"  # where tables and figures go
    device: str | None = None  # torch device (None: cuda when available)
    seed: int = 0  # pair sampling and generator seeds

    def __post_init__(self) -> None:
        if not self.pipeline:
            raise ValueError("pipeline: give at least one pipeline folder")
        if self.pipeline_names and len(self.pipeline_names) != len(self.pipeline):
            raise ValueError(
                f"pipeline_names has {len(self.pipeline_names)} names for {len(self.pipeline)} pipelines"
            )
        if self.lambdas and len(self.lambdas) != len(self.pipeline):
            raise ValueError(f"lambdas has {len(self.lambdas)} values for {len(self.pipeline)} pipelines")
        if self.protocol != "extended" and not self.protocol.startswith("ood-"):
            raise ValueError(f"protocol must be 'extended' or 'ood-<CLASS>', got {self.protocol!r}")
        check_minimum(self, "n", "num_inference_steps", "eval_batch_size", "crop_size", minimum=1)
        if self.paper_scoring_size is not None and self.paper_scoring_size < self.crop_size:
            raise ValueError(
                f"paper_scoring_size must be >= crop_size or None, got {self.paper_scoring_size}"
            )
        # the Frechet distance (SFD) needs two views per group: checked here, before any model runs
        if self.protocol.startswith("ood-") and self.n < 4:
            raise ValueError(
                f"n must be >= 4 for an ood protocol (at least 2 seen and 2 unseen pairs), got {self.n}"
            )
        if self.n < 2:
            raise ValueError(f"n must be >= 2 (the Frechet distance needs two views), got {self.n}")
        unknown = sorted(set(self.schedulers) - set(SCHEDULERS))
        if unknown:
            raise ValueError(f"schedulers: unknown {unknown}; choose from {sorted(SCHEDULERS)}")
        if bool(self.steps) != bool(self.schedulers):
            raise ValueError("steps and schedulers must be given together for the speed/error sweep")
        if any(step < 1 for step in self.steps):
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        check_minimum(self, "speed_n", minimum=1, optional=True)
        check_minimum(self, "num_figure_pairs", minimum=0)
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

    @property
    def depression_requests(self) -> bool:
        """Whether pairs are chosen by depression (`input_depression_deg` or `target_depressions_deg`)."""
        return self.input_depression_deg is not None or self.target_depressions_deg is not None


# --------------------------------------------------------------------------------------------- data
@dataclass
class PairSet:
    """The evaluation pairs of one group (seen or unseen), stacked."""

    inputs: torch.Tensor  # (N, 1, S, S)
    targets: torch.Tensor  # (N, 1, S, S)
    d_az_deg: torch.Tensor  # (N,)
    d_el_deg: torch.Tensor  # (N,)
    labels: torch.Tensor  # (N,)
    target_azimuth_deg: torch.Tensor  # (N,)
    seeds: torch.Tensor  # (N,) generator seed of each sample
    input_depression_deg: torch.Tensor  # (N,)
    target_depression_deg: torch.Tensor  # (N,)
    # (N,) whether the pair has d_el != 0 and a true view at the target azimuth and the input's depression
    has_reference: torch.Tensor
    # (N, 1, S, S) those views (zeros where has_reference is False); None where no pair has one
    references: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.inputs.shape[0]

    def subset(self, count: int) -> PairSet:
        """The first `count` pairs."""
        columns = (getattr(self, f) for f in self.__dataclass_fields__)
        return PairSet(*(None if column is None else column[:count] for column in columns))


def evaluation_groups(config: EvaluateConfig, work_dir: Path) -> tuple[list[ChipRecord], dict[str, list]]:
    """Every chip of the data, and the chips each group ("seen", and "unseen" for ood) draws pairs from.

    The paper's groups: seen = the extended test split (15 deg) without the held-out class, unseen = every
    chip of the held-out class. Pairs chosen by depression need chips at other depressions than the
    extended split's 17 and 15 deg: there, seen = every chip of the seen classes, at every depression.
    """
    if config.depression_requests and config.data is not None:
        records = load_index(config.data)
        seen = records
    else:
        extended = prepare_splits(config.data, "extended", work_dir, seed=config.seed)
        records = extended["train"] + extended["test"]
        seen = records if config.depression_requests else extended["test"]
    if config.protocol == "extended":
        return records, {"seen": seen}
    ood = split_records(records, config.protocol, seed=config.seed)
    held_out = ood["test"][0].target_class
    return records, {"seen": [r for r in seen if r.target_class != held_out], "unseen": ood["test"]}


def build_pair_sets(config: EvaluateConfig, evaluators: Evaluators, image_size: int) -> dict[str, PairSet]:
    """Samples the seen (and unseen) pairs of the protocol with the evaluators' scaling and classes."""
    work_dir = Path(config.work_dir) if config.work_dir is not None else Path(config.output_dir)
    records, groups = evaluation_groups(config, work_dir)
    data_classes = sorted({r.target_class for r in records})
    check_class_names(evaluators.class_names, data_classes, config.evaluators)
    if config.protocol == "extended":
        counts = {"seen": config.n}
    else:
        counts = {"seen": config.n - config.n // 2, "unseen": config.n // 2}
    scaling = evaluators.classifier.scaling
    input_depressions = None if config.input_depression_deg is None else [config.input_depression_deg]
    pair_sets = {}
    for offset, (group, group_records) in enumerate(groups.items()):
        dataset = ViewPairDataset(
            group_records,
            size=image_size,
            scaling=scaling,
            max_d_az_deg=config.max_d_az_deg,
            same_depression=config.same_depression,
            seed=config.seed + offset,
            num_pairs=counts[group],
            class_names=evaluators.class_names,
            crop_size=config.chip_crop_size,
            input_depressions_deg=input_depressions,
            target_depressions_deg=config.target_depressions_deg,
        )
        columns: dict[str, list[torch.Tensor]] = {}
        keys = (
            "input",
            "target",
            "d_az_deg",
            "d_el_deg",
            "label",
            "target_azimuth_deg",
            "input_depression_deg",
            "target_depression_deg",
        )
        for batch in DataLoader(dataset, batch_size=64, shuffle=False):
            for key in keys:
                columns.setdefault(key, []).append(torch.as_tensor(batch[key]))
        count = len(dataset)
        references, has_reference = input_depression_views(dataset)
        pair_sets[group] = PairSet(
            inputs=torch.cat(columns["input"]),
            targets=torch.cat(columns["target"]),
            d_az_deg=torch.cat(columns["d_az_deg"]).float(),
            d_el_deg=torch.cat(columns["d_el_deg"]).float(),
            labels=torch.cat(columns["label"]).long(),
            target_azimuth_deg=torch.cat(columns["target_azimuth_deg"]).double(),
            # Distinct seeds per group and sample: a sample's noise does not depend on the batch size.
            seeds=torch.arange(count) + config.seed * 1_000_003 + offset * 100_003,
            input_depression_deg=torch.cat(columns["input_depression_deg"]).float(),
            target_depression_deg=torch.cat(columns["target_depression_deg"]).float(),
            has_reference=has_reference,
            references=references,
        )
        logger.info("%s: %d pairs from %d chips", group, count, len(group_records))
    return pair_sets


def input_depression_views(dataset: ViewPairDataset) -> tuple[torch.Tensor | None, torch.Tensor]:
    """For each pair with d_el != 0: the true view at its target azimuth but its input's depression
    (`ViewPairDataset.target_at_input_depression`: same object, azimuth within 0.01 deg).

    Returns:
        ``(views (N, 1, S, S) normalised dB, zeros where missing, or None where every view is missing;
        found (N,) bool, False for pairs with d_el = 0 or without such a view)``.
    """
    indices = [dataset.target_at_input_depression(i) for i in range(len(dataset))]
    found = torch.tensor([index is not None for index in indices], dtype=torch.bool)
    if not found.any():
        return None, found
    views = torch.zeros(len(dataset), 1, dataset.size, dataset.size)
    for i, index in enumerate(indices):
        if index is not None:
            magnitude = load_chip(dataset.records[index].path, dataset.size, dataset.crop_size)
            views[i] = dataset.scaling.normalize(torch.from_numpy(magnitude)[None])
    return views, found


def check_pipeline_scaling(pipeline_dir: str | Path, evaluators: Evaluators) -> None:
    """Rejects a pipeline trained on other decibel bounds than the evaluators (inputs would not match).

    Raises:
        ValueError: If the pipeline folder's `decibel_scaling.json` differs from the evaluators' scaling.
    """
    path = Path(pipeline_dir) / SCALING_FILE
    if not path.is_file():
        return
    pipeline_scaling = DecibelScaling.from_dict(json.loads(path.read_text()))
    evaluator_scaling = evaluators.classifier.scaling
    if not all(
        math.isclose(getattr(pipeline_scaling, key), getattr(evaluator_scaling, key), abs_tol=1e-6)
        for key in ("min_db", "max_db")
    ):
        raise ValueError(
            f"pipeline {pipeline_dir} expects decibel scaling {pipeline_scaling.to_dict()} but the "
            f"evaluators were trained with {evaluator_scaling.to_dict()}; train both with the same --scaling"
        )


# --------------------------------------------------------------------------------------- generation
def set_scheduler(pipe: SARZero123Pipeline, name: str) -> None:
    """Swaps the pipeline's sampler for `ddim`, `dpmsolver++` or `euler`, keeping the noise schedule."""
    scheduler_class, overrides = SCHEDULERS[name]
    pipe.scheduler = scheduler_class.from_config(pipe.scheduler.config, **overrides)


@torch.no_grad()
def generate_pair_targets(
    pipe: SARZero123Pipeline,
    pairs: PairSet,
    *,
    num_inference_steps: int,
    guidance_scale: float,
    batch_size: int,
    device: torch.device,
    desc: str = "generating",
) -> tuple[torch.Tensor, float]:
    """Generates the target view of every pair (seeded per pair), in batches, timing the pipeline calls.

    Not :func:`sar_zero123.generate.generate_views`, which generates several views of one chip. A pipeline
    whose pose carries the input's absolute depression (``pose_projection.config.input_depression``) gets
    each pair's input depression.

    Returns:
        ``(images (N, 1, S, S) on CPU, seconds spent in the pipeline)``.
    """
    outputs, seconds = [], 0.0
    takes_depression = getattr(pipe.pose_projection.config, "input_depression", False)
    for start in tqdm(range(0, len(pairs), batch_size), desc=desc, leave=False):
        stop = min(start + batch_size, len(pairs))
        generators = [torch.Generator(device).manual_seed(int(s)) for s in pairs.seeds[start:stop]]
        depression = pairs.input_depression_deg[start:stop].to(device) if takes_depression else None
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        begin = time.perf_counter()
        images = pipe(
            image=pairs.inputs[start:stop].to(device),
            d_az=pairs.d_az_deg[start:stop].to(device),
            d_el=pairs.d_el_deg[start:stop].to(device),
            input_depression_deg=depression,
            num_inference_steps=num_inference_steps,
            guidance_scale=guidance_scale,
            generator=generators,
            output_type="pt",
        ).images
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds += time.perf_counter() - begin
        outputs.append(images.float().cpu())
    return torch.cat(outputs), seconds


@torch.no_grad()
def vae_round_trip(pipe: SARZero123Pipeline, images: torch.Tensor, batch_size: int, device) -> torch.Tensor:
    """Each view encoded (posterior mode) and decoded by the pipeline's VAE: the best a latent model with this
    VAE can return. Shape: ``(N, 1, S, S)`` in [0, 1] -> same, on the CPU."""
    outputs = []
    for start in range(0, images.shape[0], batch_size):
        chunk = images[start : start + batch_size].to(device)
        latents = encode_condition_latents(pipe.vae, chunk) * pipe.vae.config.scaling_factor
        outputs.append(pipe.decode_latents(latents).cpu())
    return torch.cat(outputs)


def gap_closed(
    model: float, floor: float, ceiling: float, higher_is_better: bool = False, gap_se: float = 0.0
) -> float:
    """Fraction of the floor-to-ceiling gap a model closes, ``(floor - model) / (floor - ceiling)``.

    1 means the model scores like the ceiling (VAE round trip of the real target), 0 like the floor (the
    input copied as the output), below 0 worse than the floor. NaN where the floor is not worse than the
    ceiling by more than ``gap_se`` (the standard error of their difference): no gap to close, or one the
    pairs do not resolve, whose fraction would be noise divided by noise (accuracy, for instance, when the
    input copy keeps the class and the VAE round trip keeps it about as often).
    """
    gap = ceiling - floor if higher_is_better else floor - ceiling
    if not gap > max(gap_se, 1e-9):
        return float("nan")
    return (floor - model) / (floor - ceiling)


def add_gap_closed(results: dict[str, dict[str, dict[str, float]]], floor: str, ceiling: str) -> None:
    """Adds ``azimuth_gap_closed``, ``accuracy_gap_closed`` and, where the rows have a depression error,
    ``depression_gap_closed`` to every row except the reference rows."""
    for method, groups in results.items():
        if method.startswith(REFERENCE_ROWS):  # the rows themselves and per-pipeline VAE round trips
            continue
        for group, values in groups.items():
            low, high = results[floor][group], results[ceiling][group]
            for metric in (m for m in GAP_METRICS if m in values and m in low and m in high):
                key = f"{metric.split('_')[0]}_gap_closed"
                gap_se = math.hypot(low.get(f"{metric}_se", 0.0), high.get(f"{metric}_se", 0.0))
                higher_is_better = metric == "accuracy"
                values[key] = gap_closed(values[metric], low[metric], high[metric], higher_is_better, gap_se)


def score(
    generated: torch.Tensor, pairs: PairSet, evaluators: Evaluators, config: EvaluateConfig, device
) -> dict:
    """Table III/IV metrics of a generated set (see `score_views`), and for the pairs with a depression
    change and a true view at the target azimuth and the input's depression, the fraction of generated
    views closer to the requested depression's truth (`closer_to_target_depression`, with its standard
    error and `closer_to_target_depression_n`, the pairs it counts)."""
    scores = score_views(
        generated,
        pairs.targets,
        pairs.labels,
        pairs.target_azimuth_deg,
        evaluators,
        target_depression_deg=pairs.target_depression_deg,
        crop_size=config.crop_size,
        paper_scoring_size=config.paper_scoring_size,
        batch_size=max(config.eval_batch_size, 32),
        device=device,
    )
    if pairs.references is not None:
        mask = pairs.has_reference
        closer = closer_to_target_depression(
            generated[mask], pairs.targets[mask], pairs.references[mask], sigma_px=BLUR_SIGMA_PX
        ).double()
        scores["closer_to_target_depression"] = closer.mean().item()
        scores["closer_to_target_depression_se"] = standard_error(closer)
        scores["closer_to_target_depression_n"] = float(closer.numel())
    return scores


# ------------------------------------------------------------------------------------------ reports
def _format(metric: str, value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if metric == "accuracy":
        return f"{value:.1f}"
    if metric in ("azimuth_error_deg", "depression_error_deg"):
        return f"{value:.1f}"
    if metric in ("sfd", "closer_to_target_depression"):
        return f"{value:.2f}"
    return f"{value:.4f}"


def _cell(metric: str, values: dict[str, float]) -> str:
    """A metric with its standard error when known (``43.8 ± 8.8``)."""
    text = _format(metric, values.get(metric))
    se = values.get(f"{metric}_se")
    if text == "-" or se is None or math.isnan(se):
        return text
    return f"{text} ± {_format(metric, se)}"


def _fraction(value: float | None) -> str:
    if value is None:
        return ""
    return "no gap" if math.isnan(value) else f"{100 * value:.0f} %"


def table3_markdown(results: dict[str, dict[str, dict[str, float]]], include_paper: bool) -> str:
    """Markdown Table III: one row per (method, group), the paper's rows first when `include_paper`.

    Metrics carry ± their standard error; the gap columns give the fraction of the gap between the
    input copy (floor) and the VAE round trip (ceiling) that each model closes. The depression columns
    appear when some row has them (a depression regressor, pairs with d_el != 0).
    """
    present = {key for groups in results.values() for values in groups.values() for key in values}
    metrics = [*METRICS, *(m for m in DEPRESSION_METRICS if m in present)]
    gaps = [key for key in GAP_LABELS if key != "depression_gap_closed" or "depression_error_deg" in present]
    labels = [METRIC_LABELS[m] for m in metrics] + [GAP_LABELS[key] for key in gaps]
    header = "| Method | Views | " + " | ".join(labels) + " | n |"
    lines = [header, "|" + " --- |" * (len(labels) + 3)]
    rows = dict(PAPER_TABLE3) if include_paper else {}
    rows.update(results)
    for method, groups in rows.items():
        for group, values in groups.items():
            n = values.get("n")
            cells = " | ".join(_cell(m, values) for m in metrics)
            fractions = " | ".join(_fraction(values.get(key)) for key in gaps)
            lines.append(f"| {method} | {group} | {cells} | {fractions} | {'' if n is None else int(n)} |")
    lines.append("")
    lines.append(
        f"Floor: `{INPUT_COPY}` returns the input view (a generator that ignores the pose). Ceilings: "
        f"`{REAL_TARGET}` scores the true target view, `{VAE_ROUND_TRIP}` the target encoded and decoded by "
        'the pipeline\'s VAE. Gap closed = (floor - model) / (floor - VAE round trip); "no gap" where '
        "the floor scores at least as well as the ceiling, or within one standard error of their difference "
        "(accuracy: the input copy keeps the class). ± is one standard error of the mean over the n pairs."
    )
    lines.append(
        "MS-SSIM and Kuan+SSIM are paper-comparable (`sar_zero123.paper_metrics`, the authors' calls: 8-bit "
        "views resized to 256 px, centre 64 crop; torchmetrics MS-SSIM with its 9x9 window, findpeaks Kuan "
        "filter then scikit-image SSIM); the `corr.` columns are the corrected variants "
        "(`sar_zero123.metrics`: true 7x7 Gaussian windows, centred 7x7 Kuan filter, generated resolution); "
        "SFD: Frechet distance of the azimuth regressor's pooled features at the n shown."
    )
    if "depression_error_deg" in present:
        lines.append(
            "Dep. err.: |depression regressor's prediction on the view - the target's true depression|."
        )
    if "closer_to_target_depression" in present:
        lines.append(
            "Closer to target dep.: fraction of the pairs with d_el != 0 whose view, blurred (Gaussian, "
            f"sigma {BLUR_SIGMA_PX:g} px) like both truths, correlates more with the true target view than "
            "with the true view at the target azimuth but the input's depression (a model that ignores "
            "d_el returns the latter); counted over the pairs where that view exists "
            "(`closer_to_target_depression_n` in table3.json)."
        )
    return "\n".join(lines) + "\n"


def table4_markdown(results: dict[str, dict[str, dict[str, float]]]) -> str:
    """Markdown Table IV: azimuth error of generated views under every evaluator backbone."""
    backbones = sorted(
        {
            key.split("/", 1)[1]
            for groups in results.values()
            for v in groups.values()
            for key in v
            if "/" in key
        },
        key=lambda name: (name != "scratch", name),
    )
    lines = ["| Method | Views | " + " | ".join(f"Az. err. (deg), {b}" for b in backbones) + " |"]
    lines.append("|" + " --- |" * (len(backbones) + 2))
    for method, groups in results.items():
        for group, values in groups.items():
            cells = " | ".join(
                _format("azimuth_error_deg", values.get(f"azimuth_error_deg/{b}")) for b in backbones
            )
            lines.append(f"| {method} | {group} | {cells} |")
    return "\n".join(lines) + "\n"


def plot_views(
    pair_sets: dict[str, PairSet], generated: dict[str, dict[str, torch.Tensor]], count: int, path: Path
) -> Path:
    """Fig. 7/8-like grid: rows are pairs, columns input | each pipeline | target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(generated)
    rows = [(group, i) for group, pairs in pair_sets.items() for i in range(min(count, len(pairs)))]
    columns = ["input", *names, "target"]
    figure, axes = plt.subplots(
        len(rows), len(columns), figsize=(1.6 * len(columns), 1.6 * len(rows)), squeeze=False
    )
    for row, (group, i) in enumerate(rows):
        pairs = pair_sets[group]
        images = [pairs.inputs[i], *(generated[name][group][i] for name in names), pairs.targets[i]]
        for column, image in enumerate(images):
            axis = axes[row, column]
            axis.imshow(image[0].numpy(), cmap="gray", vmin=0.0, vmax=1.0)
            axis.set_xticks([])
            axis.set_yticks([])
            if row == 0:
                axis.set_title(columns[column], fontsize=8)
        label = f"{group}\nΔaz {pairs.d_az_deg[i]:.0f}°, Δel {pairs.d_el_deg[i]:.0f}°"
        axes[row, 0].set_ylabel(label, fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_lambda_sweep(
    results: dict[str, dict[str, dict[str, float]]], lambdas: dict[str, float], path: Path
) -> Path:
    """Fig. 12-like plot: each metric against the PFM weight lambda, one line per view group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(METRICS), figsize=(3.2 * len(METRICS), 3.0))
    order = sorted(lambdas, key=lambdas.get)
    groups = list(next(iter(results.values())))
    for axis, metric in zip(axes, METRICS):
        for group in groups:
            axis.plot(
                [lambdas[m] for m in order], [results[m][group][metric] for m in order], "o-", label=group
            )
        axis.set_xlabel("λ (PFM weight)")
        axis.set_title(METRIC_LABELS[metric], fontsize=9)
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_speed_error(rows: list[dict[str, Any]], path: Path) -> Path:
    """Azimuth error and accuracy against images/s, one line per (pipeline, scheduler), points = steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(9.0, 3.6))
    lines: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        lines.setdefault((row["pipeline"], row["scheduler"]), []).append(row)
    for (pipeline, scheduler), points in lines.items():
        points = sorted(points, key=lambda r: r["images_per_s"])
        speed = [p["images_per_s"] for p in points]
        for axis, metric in zip(axes, ("azimuth_error_deg", "accuracy")):
            axis.plot(speed, [p[metric] for p in points], "o-", label=f"{pipeline} / {scheduler}")
            for p in points:
                axis.annotate(
                    str(p["steps"]),
                    (p["images_per_s"], p[metric]),
                    fontsize=7,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
    axes[0].set_ylabel("azimuth error (deg) ↓")
    axes[1].set_ylabel("accuracy (%) ↑")
    for axis in axes:
        axis.set_xlabel("images / s")
        axis.set_xscale("log")
        axis.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def speed_markdown(rows: list[dict[str, Any]], device: str) -> str:
    """Markdown speed/error table."""
    lines = [
        f"Device: {device}. Points use the seen pairs; images/s counts pipeline calls only.\n",
        "| Pipeline | Scheduler | Steps | images/s | Az. err. (deg) ↓ | Acc. (%) ↑ | n |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        lines.append(
            f"| {row['pipeline']} | {row['scheduler']} | {row['steps']} | {row['images_per_s']:.2f} | "
            f"{row['azimuth_error_deg']:.1f} | {row['accuracy']:.1f} | {row['n']} |"
        )
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- main
def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Runs the evaluation; returns `{"table3": ..., "speed_error": [...]}` (also written to disk)."""

    config = parse_config(EvaluateConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    output_dir = Path(config.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, output_dir)
    device = torch.device(config.device or ("cuda" if torch.cuda.is_available() else "cpu"))

    # 1. models
    evaluators = load_evaluators(config.evaluators, device=device)
    pipes = {}
    lifted: dict[str, dict] = {}  # pipelines whose trained-range refusal was lifted, with their ranges
    for name, path in zip(config.names, config.pipeline):
        check_pipeline_scaling(path, evaluators)
        pipe = SARZero123Pipeline.from_pretrained(path).to(device)
        pipe.set_progress_bar_config(disable=True)
        pipes[name] = pipe
        projection = pipe.pose_projection.config
        if config.outside_trained_range and projection.get("trained_d_el_deg") is not None:
            logger.warning(
                "%s: trained d_el range %s lifted (--outside_trained_range)",
                name,
                projection["trained_d_el_deg"],
            )
            lifted[name] = {
                "trained_d_el_deg": projection["trained_d_el_deg"],
                "trained_depression_deg": projection.get("trained_depression_deg"),
            }
            pipe.pose_projection.register_to_config(trained_d_el_deg=None, trained_depression_deg=None)
    sizes = {pipe.default_image_size for pipe in pipes.values()}
    if config.image_size is None and len(sizes) != 1:
        raise ValueError(f"pipelines were built for different image sizes {sorted(sizes)}; pass --image_size")
    image_size = config.image_size or sizes.pop()

    # 2. pairs (same pairs and seeds for every pipeline)
    pair_sets = build_pair_sets(config, evaluators, image_size)

    # 3. Table III / IV, with the floor (input copy) and the ceilings (real target, VAE round trip)
    results: dict[str, dict[str, dict[str, float]]] = {}
    results[INPUT_COPY] = {
        group: score(pairs.inputs, pairs, evaluators, config, device) for group, pairs in pair_sets.items()
    }
    results[REAL_TARGET] = {
        group: score(pairs.targets, pairs, evaluators, config, device) for group, pairs in pair_sets.items()
    }
    round_trip_rows = []
    for name, pipe in pipes.items():
        row = VAE_ROUND_TRIP if not round_trip_rows else f"{VAE_ROUND_TRIP} ({name})"
        if round_trip_rows and same_weights(pipe.vae, pipes[config.names[0]].vae):
            continue  # one row per distinct VAE
        results[row] = {
            group: score(
                vae_round_trip(pipe, pairs.targets, config.eval_batch_size, device),
                pairs,
                evaluators,
                config,
                device,
            )
            for group, pairs in pair_sets.items()
        }
        round_trip_rows.append(row)
    generated: dict[str, dict[str, torch.Tensor]] = {}
    for name, pipe in pipes.items():
        results[name], generated[name] = {}, {}
        for group, pairs in pair_sets.items():
            images, seconds = generate_pair_targets(
                pipe,
                pairs,
                num_inference_steps=config.num_inference_steps,
                guidance_scale=config.guidance_scale,
                batch_size=config.eval_batch_size,
                device=device,
                desc=f"{name} {group}",
            )
            generated[name][group] = images
            results[name][group] = {**score(images, pairs, evaluators, config, device), "seconds": seconds}
            logger.info("%s %s: %s", name, group, json.dumps(results[name][group]))
    add_gap_closed(results, floor=INPUT_COPY, ceiling=VAE_ROUND_TRIP)
    include_paper = config.protocol.startswith("ood-")
    evaluator_metrics = {
        name: model.metrics
        for name, model in (
            ("classifier", evaluators.classifier),
            ("regressor", evaluators.regressor),
            ("depression_regressor", evaluators.depression_regressor),
        )
        if model is not None
    }
    write_json_atomic(
        {
            "protocol": config.protocol,
            "device": str(device),
            "num_inference_steps": config.num_inference_steps,
            "guidance_scale": config.guidance_scale,
            "results": results,
            "paper": PAPER_TABLE3,
            "evaluator_test_metrics": evaluator_metrics,
            "same_depression": config.same_depression,
            "outside_trained_range": lifted,
            "input_depression_deg": config.input_depression_deg,
            "target_depressions_deg": config.target_depressions_deg,
            "pairs_per_d_el_deg": {group: d_el_counts(pairs.d_el_deg) for group, pairs in pair_sets.items()},
        },
        output_dir / "table3.json",
    )
    (output_dir / "table3.md").write_text(table3_markdown(results, include_paper))
    table4 = {name: results[name] for name in results}
    write_json_atomic(table4, output_dir / "table4.json")
    (output_dir / "table4.md").write_text(table4_markdown(table4))
    if config.num_figure_pairs > 0:
        plot_views(pair_sets, generated, config.num_figure_pairs, output_dir / "views.png")
    if config.lambdas:
        plot_lambda_sweep(
            {n: results[n] for n in pipes}, dict(zip(pipes, config.lambdas)), output_dir / "lambda_sweep.png"
        )

    # 4. speed against error (seen pairs)
    speed_rows: list[dict[str, Any]] = []
    if config.steps:
        pairs = pair_sets["seen"].subset(config.speed_n or config.n)
        for name, pipe in pipes.items():
            original = pipe.scheduler
            for scheduler in config.schedulers:
                set_scheduler(pipe, scheduler)
                # Warm-up call so one-time costs (allocation, kernel selection) do not count.
                generate_pair_targets(
                    pipe,
                    pairs.subset(1),
                    num_inference_steps=1,
                    guidance_scale=config.guidance_scale,
                    batch_size=1,
                    device=device,
                )
                for steps in config.steps:
                    images, seconds = generate_pair_targets(
                        pipe,
                        pairs,
                        num_inference_steps=steps,
                        guidance_scale=config.guidance_scale,
                        batch_size=config.eval_batch_size,
                        device=device,
                        desc=f"{name} {scheduler} {steps}",
                    )
                    scores = score(images, pairs, evaluators, config, device)
                    speed_rows.append(
                        {
                            "pipeline": name,
                            "scheduler": scheduler,
                            "steps": steps,
                            "n": len(pairs),
                            "images_per_s": len(pairs) / seconds,
                            "azimuth_error_deg": scores["azimuth_error_deg"],
                            "accuracy": scores["accuracy"],
                            "ms_ssim": scores["ms_ssim"],
                        }
                    )
                    logger.info("speed %s", json.dumps(speed_rows[-1]))
            pipe.scheduler = original
        write_json_atomic({"device": str(device), "rows": speed_rows}, output_dir / "speed_error.json")
        (output_dir / "speed_error.md").write_text(speed_markdown(speed_rows, _device_name(device)))
        plot_speed_error(speed_rows, output_dir / "speed_error.png")

    print(table3_markdown(results, include_paper))
    return {"table3": results, "speed_error": speed_rows}


def d_el_counts(d_el_deg: torch.Tensor) -> dict[str, int]:
    """How many pairs ask for each depression change, keyed by the change in degrees (``"+13"``)."""
    values, counts = torch.unique(d_el_deg.double().round(decimals=3), return_counts=True)
    return {f"{value:+g}": int(count) for value, count in zip(values.tolist(), counts.tolist())}


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether two modules hold identical parameters (same names, shapes and values)."""
    first, second = a.state_dict(), b.state_dict()
    return first.keys() == second.keys() and all(
        first[k].shape == second[k].shape and torch.equal(first[k].cpu(), second[k].cpu()) for k in first
    )


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU ({torch.get_num_threads()} threads)"


if __name__ == "__main__":
    main()
