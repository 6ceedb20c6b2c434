"""The Table III protocol: evaluation pairs, generated targets, their scores, the floor and the ceilings.

Pairs are two views of one object with their relative pose. An ``ood-<CLASS>`` protocol draws half from
the seen classes (the extended test split, 15 deg, without the held-out class) and half from every chip of
the unseen class; ``extended`` only seen pairs. Every pipeline answers the same pairs with the same
per-pair seeds. Reference rows bound the scores: :data:`INPUT_COPY` (ignores the pose: the floor),
:data:`REAL_TARGET` and :data:`VAE_ROUND_TRIP` (the ceiling of a latent model); :func:`gap_closed` is the
fraction of the floor-to-ceiling gap a model closes.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

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
from sar_zero123.evaluation.evaluators import (
    Evaluators,
    check_class_names,
)
from sar_zero123.evaluation.scoring import closer_to_target_depression, score_views, standard_error
from sar_zero123.evaluation.template import read_chip_templates, turned_and_kept
from sar_zero123.model.build import same_weights
from sar_zero123.model.conditioning import encode_condition_latents
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import SCHEDULERS, SamplerSettings, set_scheduler
from sar_zero123.model.spatial_pose import takes_proxy

logger = logging.getLogger(__name__)

__all__ = [
    "BLUR_SIGMA_PX",
    "GAP_METRICS",
    "INPUT_COPY",
    "PAPER_TABLE3",
    "REAL_TARGET",
    "REFERENCE_ROWS",
    "SCHEDULERS",
    "VAE_ROUND_TRIP",
    "PairSet",
    "add_gap_closed",
    "build_pair_sets",
    "check_pipeline_scaling",
    "d_el_counts",
    "evaluation_groups",
    "gap_closed",
    "generate_pair_targets",
    "input_depression_views",
    "same_weights",
    "score",
    "set_scheduler",
    "vae_round_trip",
]

# the errors whose floor-to-ceiling gap Table III reports, keyed `<first word>_gap_closed`
GAP_METRICS = ("azimuth_error_deg", "accuracy", "depression_error_deg", "template_azimuth_error_deg")
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
# the input view returned as the generated one: it ignores the pose (every class kept, nothing turned)
INPUT_COPY = "input copy (unturned, keeps identity)"
REAL_TARGET = "real target (ceiling)"  # the true target view: the best any generator can score
VAE_ROUND_TRIP = "VAE round trip (ceiling)"  # the target encoded and decoded: the best for this VAE
REFERENCE_ROWS = (INPUT_COPY, REAL_TARGET, VAE_ROUND_TRIP)
_PAIR_COLUMNS = (
    "input",
    "target",
    "d_az_deg",
    "d_el_deg",
    "label",
    "input_azimuth_deg",
    "target_azimuth_deg",
    "input_depression_deg",
    "target_depression_deg",
)
_LOAD_BATCH = 64  # pairs loaded per DataLoader batch
_LOAD_LOG_EVERY = 16  # loader batches between two progress lines


# --------------------------------------------------------------------------------------------- pairs
@dataclass
class PairSet:
    """The evaluation pairs of one group (seen or unseen), stacked."""

    inputs: torch.Tensor  # (N, 1, S, S)
    targets: torch.Tensor  # (N, 1, S, S)
    d_az_deg: torch.Tensor  # (N,)
    d_el_deg: torch.Tensor  # (N,)
    labels: torch.Tensor  # (N,)
    input_azimuth_deg: torch.Tensor  # (N,) the input chip's absolute azimuth (its header or index.csv)
    target_azimuth_deg: torch.Tensor  # (N,)
    seeds: torch.Tensor  # (N,) generator seed of each sample
    input_depression_deg: torch.Tensor  # (N,)
    target_depression_deg: torch.Tensor  # (N,)
    # (N,) whether the pair has d_el != 0 and a true view at the target azimuth and the input's depression
    has_reference: torch.Tensor
    # (N, 1, S, S) those views (zeros where has_reference is False); None where no pair has one
    references: torch.Tensor | None = None
    # the template reading's turntable (`chip_templates`): chips (M, 1, S, S) and their azimuths (M,), shared
    # by every pair, and (N, M) which of them each pair's view is read against; None: no template reading
    templates: torch.Tensor | None = None
    template_azimuth_deg: torch.Tensor | None = None
    template_candidates: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.inputs.shape[0]

    def subset(self, count: int) -> PairSet:
        """The first `count` pairs (the templates, shared by every pair, whole)."""
        shared = ("templates", "template_azimuth_deg")
        columns = {f: getattr(self, f) for f in self.__dataclass_fields__}
        return PairSet(**{
            f: column if column is None or f in shared else column[:count] for f, column in columns.items()
        })  # fmt: skip


def evaluation_groups(
    data: str | os.PathLike | None, protocol: str, work_dir: str | os.PathLike, *, seed: int,
    by_depression: bool = False,
) -> tuple[list[ChipRecord], dict[str, list[ChipRecord]]]:  # fmt: skip
    """Every chip of the data, and the chips each group ("seen", and "unseen" for ood) draws pairs from.

    The paper's groups: seen = the extended test split (15 deg) without the held-out class, unseen = every
    chip of the held-out class. With ``by_depression`` seen is every seen-class chip at every depression.

    Args:
        data: Data folder with ``index.csv``; ``None`` simulates the built-in dataset into ``work_dir``.
        protocol: ``"extended"`` or ``"ood-<CLASS>"``.
        seed: Seed of the splits (and of the simulator).
    """
    if by_depression and data is not None:
        records = load_index(data)
        seen = records
    else:
        extended = prepare_splits(data, "extended", work_dir, seed=seed)
        records = extended["train"] + extended["test"]
        seen = records if by_depression else extended["test"]
    if protocol == "extended":
        return records, {"seen": seen}
    ood = split_records(records, protocol, seed=seed)
    held_out = ood["test"][0].target_class
    return records, {"seen": [r for r in seen if r.target_class != held_out], "unseen": ood["test"]}


def build_pair_sets(
    evaluators: Evaluators,
    *,
    data: str | os.PathLike | None,
    protocol: str,
    n: int,
    image_size: int,
    work_dir: str | os.PathLike,
    seed: int = 0,
    same_depression: bool = True,
    input_depression_deg: float | None = None,
    target_depressions_deg: Sequence[float] | None = None,
    max_d_az_deg: float | None = None,
    chip_crop_size: int | None = None,
    evaluators_name: str = "evaluators",
) -> dict[str, PairSet]:
    """Samples the seen (and unseen) pairs of the protocol with the evaluators' scaling and classes.

    An ``ood`` protocol splits ``n`` into ``n - n // 2`` seen and ``n // 2`` unseen pairs. Each pair has its
    own generator seed, so its noise does not depend on its batch.

    Args:
        data: Data folder with ``index.csv``; ``None`` simulates the built-in dataset into ``work_dir``.
        protocol: ``"extended"`` or ``"ood-<CLASS>"``.
        image_size: Chip side fed to the pipelines.
        same_depression: Pair views at one depression only.
        input_depression_deg: Only inputs at this depression (``None``: any).
        target_depressions_deg: Only targets at one of these depressions (``None``: any).
        max_d_az_deg: Largest |d_az| of a pair (``None``: any).
        chip_crop_size: Centre crop of the chip files before resizing.
        evaluators_name: The evaluators' folder, named in messages.

    Returns:
        ``{"seen": PairSet, "unseen": PairSet}`` (``"seen"`` only for ``extended``).

    Raises:
        ValueError: If the evaluators know other classes than the data, or a group's chips admit fewer
            distinct pairs than it needs.
    """
    by_depression = input_depression_deg is not None or target_depressions_deg is not None
    records, groups = evaluation_groups(data, protocol, work_dir, seed=seed, by_depression=by_depression)
    check_class_names(evaluators.class_names, sorted({r.target_class for r in records}), evaluators_name)
    counts = {"seen": n} if protocol == "extended" else {"seen": n - n // 2, "unseen": n // 2}
    datasets = {}
    for offset, (group, group_records) in enumerate(groups.items()):
        datasets[group] = ViewPairDataset(
            group_records,
            size=image_size,
            scaling=evaluators.classifier.scaling,
            max_d_az_deg=max_d_az_deg,
            same_depression=same_depression,
            seed=seed + offset,
            num_pairs=counts[group],
            class_names=evaluators.class_names,
            crop_size=chip_crop_size,
            input_depressions_deg=None if input_depression_deg is None else [input_depression_deg],
            target_depressions_deg=target_depressions_deg,
        )
        available = datasets[group].num_admissible_pairs
        if available < counts[group]:
            raise ValueError(
                f"n: the {group} group needs {counts[group]} distinct pairs (n = {n}, protocol {protocol}) "
                f"but its {len(group_records)} chips admit only {available}; lower n or widen the pairs "
                "(max_d_az_deg, same_depression, the depression requests)"
            )
    # seeds: distinct per group and sample (offset by group), so groups never share noise
    return {
        group: _stack_pairs(group, dataset, first_seed=seed * 1_000_003 + offset * 100_003)
        for offset, (group, dataset) in enumerate(datasets.items())
    }


def _stack_pairs(group: str, dataset: ViewPairDataset, first_seed: int) -> PairSet:
    """Loads every pair of `dataset` (logging progress) and stacks it into a :class:`PairSet`."""
    columns: dict[str, list[torch.Tensor]] = {}
    loaded = 0
    for index, batch in enumerate(DataLoader(dataset, batch_size=_LOAD_BATCH, shuffle=False)):
        for key in _PAIR_COLUMNS:
            columns.setdefault(key, []).append(torch.as_tensor(batch[key]))
        loaded += len(batch["input"])
        if (index + 1) % _LOAD_LOG_EVERY == 0:
            logger.info("%s: loaded %d/%d pairs", group, loaded, len(dataset))
    references, has_reference = input_depression_views(dataset)
    templates, template_azimuth_deg, template_candidates = chip_templates(dataset)
    logger.info("%s: %d pairs from %d chips", group, len(dataset), len(dataset.records))
    return PairSet(
        inputs=torch.cat(columns["input"]),
        targets=torch.cat(columns["target"]),
        d_az_deg=torch.cat(columns["d_az_deg"]).float(),
        d_el_deg=torch.cat(columns["d_el_deg"]).float(),
        labels=torch.cat(columns["label"]).long(),
        input_azimuth_deg=torch.cat(columns["input_azimuth_deg"]).double(),
        target_azimuth_deg=torch.cat(columns["target_azimuth_deg"]).double(),
        seeds=torch.arange(len(dataset)) + first_seed,
        input_depression_deg=torch.cat(columns["input_depression_deg"]).float(),
        target_depression_deg=torch.cat(columns["target_depression_deg"]).float(),
        has_reference=has_reference,
        references=references,
        templates=templates,
        template_azimuth_deg=template_azimuth_deg,
        template_candidates=template_candidates,
    )


def chip_templates(
    dataset: ViewPairDataset, depression_tol_deg: float = 0.01
) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """The turntable each pair's view is read against (:func:`~.template.read_chip_templates`): the other
    chips of the target's vehicle (class and serial) at the target's depression.

    Returns:
        ``(chips (M, 1, S, S) normalised dB, their azimuths (M,) float64, candidates (N, M) bool)``;
        ``(None, None, None)`` where a pair has no other chip.
    """
    records = dataset.records
    per_pair = []
    for _, target in dataset.pairs:
        chosen = records[int(target)]
        depression = chosen.depression_deg
        per_pair.append([
            index for index in dataset.object_members[chosen.object_id]
            if index != target and abs(records[index].depression_deg - depression) <= depression_tol_deg
        ])  # fmt: skip
    if not per_pair or not all(per_pair):
        return None, None, None
    used = sorted({index for indices in per_pair for index in indices})
    column = {index: k for k, index in enumerate(used)}
    candidates = torch.zeros(len(per_pair), len(used), dtype=torch.bool)
    for row, indices in enumerate(per_pair):
        candidates[row, [column[index] for index in indices]] = True
    chips = torch.stack([_normalised_chip(dataset, i) for i in used]).float()
    azimuths = torch.tensor([records[i].azimuth_deg for i in used], dtype=torch.float64)
    return chips, azimuths, candidates


def input_depression_views(dataset: ViewPairDataset) -> tuple[torch.Tensor | None, torch.Tensor]:
    """For each pair with d_el != 0: the true view at its target azimuth and its input's depression.

    Returns:
        ``(views (N, 1, S, S) normalised dB, zeros where missing, or None where every view is missing;
        found (N,) bool)``.
    """
    indices = [dataset.target_at_input_depression(i) for i in range(len(dataset))]
    found = torch.tensor([index is not None for index in indices], dtype=torch.bool)
    if not found.any():
        return None, found
    views = torch.zeros(len(dataset), 1, dataset.size, dataset.size)
    for i, index in enumerate(indices):
        if index is not None:
            views[i] = _normalised_chip(dataset, index)
    return views, found


def _normalised_chip(dataset: ViewPairDataset, index: int) -> torch.Tensor:
    """Record ``index`` of ``dataset`` read as its pairs' chips are: ``(1, S, S)`` normalised dB."""
    magnitude = load_chip(dataset.records[index].path, dataset.size, dataset.crop_size)
    return dataset.scaling.normalize(torch.from_numpy(magnitude)[None])


def check_pipeline_scaling(pipeline_dir: str | os.PathLike, evaluators: Evaluators) -> None:
    """Rejects a pipeline trained on other decibel bounds than the evaluators (inputs would not match).

    Raises:
        ValueError: If the pipeline folder's `decibel_scaling.json` differs from the evaluators' scaling.
    """
    path = Path(pipeline_dir) / SCALING_FILE
    if not path.is_file():
        return
    pipeline_scaling = DecibelScaling.from_dict(json.loads(path.read_text()))
    evaluator_scaling = evaluators.classifier.scaling
    if not pipeline_scaling.isclose(evaluator_scaling):
        raise ValueError(
            f"pipeline {pipeline_dir} expects decibel scaling {pipeline_scaling.to_dict()} but the "
            f"evaluators were trained with {evaluator_scaling.to_dict()}; train both with the same --scaling"
        )


# ---------------------------------------------------------------------------------------- generation
@torch.no_grad()
def generate_pair_targets(
    pipe: SARZero123Pipeline,
    pairs: PairSet,
    *,
    sampler: SamplerSettings,
    batch_size: int,
    device: torch.device,
    desc: str = "generating",
) -> tuple[torch.Tensor, float]:
    """Generates the target view of every pair (seeded per pair), in batches, timing the pipeline calls.

    A pipeline whose pose carries the input's depression gets each pair's; a call that uses a proxy gets
    each input's depression and azimuth, so the pipeline fits the proxy itself. ``sampler`` fields left
    ``None`` are the pipeline's recorded values. Each batch logs a line (``desc``) outside the timing.

    Returns:
        ``(images (N, 1, S, S) on CPU, seconds spent in the pipeline)``.
    """
    device = torch.device(device)
    outputs, seconds = [], 0.0
    recorded = getattr(pipe.config, "sampler", None)
    start = sampler.resolved(recorded)["start_from"]
    uses_proxy = start == "proxy" or takes_proxy(pipe.pose_projection)
    takes_depression = uses_proxy or getattr(pipe.pose_projection.config, "input_depression", False)
    for start in range(0, len(pairs), batch_size):
        stop = min(start + batch_size, len(pairs))
        generators = [torch.Generator(device).manual_seed(int(s)) for s in pairs.seeds[start:stop]]
        depression = pairs.input_depression_deg[start:stop].to(device) if takes_depression else None
        azimuth = pairs.input_azimuth_deg[start:stop] if uses_proxy else None
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        begin = time.perf_counter()
        images = pipe(
            image=pairs.inputs[start:stop].to(device),
            d_az=pairs.d_az_deg[start:stop].to(device),
            d_el=pairs.d_el_deg[start:stop].to(device),
            input_depression_deg=depression,
            input_azimuth_deg=azimuth,
            generator=generators,
            output_type="pt",
            **sampler.sampler_arguments(),
        ).images
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds += time.perf_counter() - begin
        outputs.append(images.float().cpu())
        logger.info("%s: %d/%d views generated (%.1f s)", desc, stop, len(pairs), seconds)
    return torch.cat(outputs), seconds


@torch.no_grad()
def vae_round_trip(pipe: SARZero123Pipeline, images: torch.Tensor, batch_size: int, device) -> torch.Tensor:
    """Each view encoded (posterior mode) and decoded by the pipeline's VAE, the best a latent model with
    this VAE can return. ``(N, 1, S, S)`` in [0, 1] -> same, on the CPU.
    """
    outputs = []
    for start in range(0, images.shape[0], batch_size):
        chunk = images[start : start + batch_size].to(device)
        latents = encode_condition_latents(pipe.vae, chunk) * pipe.vae.config.scaling_factor
        outputs.append(pipe.decode_latents(latents).cpu())
    return torch.cat(outputs)


# ------------------------------------------------------------------------------------------- scores
def score(
    generated: torch.Tensor,
    pairs: PairSet,
    evaluators: Evaluators,
    *,
    crop_size: int,
    paper_scoring_size: int | None,
    batch_size: int,
    device,
) -> dict[str, float]:
    """Table III/IV metrics of a generated set ``(N, 1, S, S)`` (:func:`~.scoring.score_views`), and for pairs
    with a depression change and a true view at the input's depression, the fraction of views closer to the
    requested depression's truth (``closer_to_target_depression``, its standard error and ``_n``).

    Args:
        crop_size: Centre crop for MS-SSIM and Kuan+SSIM.
        paper_scoring_size: Side before the paper-comparable crop (``None``: the generated side).
        batch_size: Views per evaluator call.
    """
    scores, per_sample = score_views(
        generated,
        pairs.targets,
        pairs.labels,
        pairs.target_azimuth_deg,
        evaluators,
        target_depression_deg=pairs.target_depression_deg,
        input_depression_deg=pairs.input_depression_deg,
        crop_size=crop_size,
        paper_scoring_size=paper_scoring_size,
        batch_size=batch_size,
        device=device,
        return_per_sample=True,
    )
    if pairs.templates is not None:  # the azimuth a footprint turned in place cannot fool
        views = generated[:, 0].detach().cpu().numpy()
        readings = read_chip_templates(
            views, pairs.templates[:, 0].numpy(), pairs.template_azimuth_deg.numpy(),
            pairs.template_candidates.numpy(), pairs.target_azimuth_deg.numpy(), blur_sigma_px=BLUR_SIGMA_PX,
        )  # fmt: skip
        kept = per_sample["accuracy"].numpy() > 0  # the classifier keeps the view's class
        joint = turned_and_kept(readings.azimuth_error_deg, kept)
        for name, values, scale in (("template_azimuth_error_deg", readings.azimuth_error_deg, 1.0),
                                    ("front_back_right", readings.front_back_right, 100.0),
                                    ("turned_and_kept", joint, 100.0)):  # fmt: skip
            values = torch.from_numpy(values.astype(np.float64)) * scale
            scores[name] = values.mean().item()
            scores[f"{name}_se"] = standard_error(values)
    if pairs.references is not None:
        mask = pairs.has_reference
        closer = closer_to_target_depression(
            generated[mask], pairs.targets[mask], pairs.references[mask], sigma_px=BLUR_SIGMA_PX
        ).double()
        scores["closer_to_target_depression"] = closer.mean().item()
        scores["closer_to_target_depression_se"] = standard_error(closer)
        scores["closer_to_target_depression_n"] = float(closer.numel())
    return scores


def gap_closed(
    model: float, floor: float, ceiling: float, higher_is_better: bool = False, gap_se: float = 0.0
) -> float:
    """Fraction of the floor-to-ceiling gap a model closes, ``(floor - model) / (floor - ceiling)``.

    1: like the ceiling, 0: like the floor, below 0: worse. NaN where the floor is not worse than the
    ceiling by more than ``gap_se`` (their difference's standard error): no gap the pairs resolve.
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


def d_el_counts(d_el_deg: torch.Tensor) -> dict[str, int]:
    """How many pairs ask for each depression change, keyed by the change in degrees (``"+13"``)."""
    values, counts = torch.unique(d_el_deg.double().round(decimals=3), return_counts=True)
    return {f"{value:+g}": int(count) for value, count in zip(values.tolist(), counts.tolist())}
