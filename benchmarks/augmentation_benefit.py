"""Do generated views help a classifier that has few real views? (issue 26, section 2)

Sparse-azimuth benchmark on a dataset with 17 and 15 deg chips (real MSTAR): keep K chips per class, evenly
spaced in azimuth, at 17 deg, and train the same small classifier (``SARClassifier``, a four-stage ResNet on
64 px centre crops, random +-4 px shifts) in three arms, each tested on every 15 deg chip:

- ``real_k{K}``: the K kept chips per class only (the floor);
- ``generated_k{K}``: the kept chips plus ``views_per_chip`` generated views of each, at the azimuths
  between the kept ones, from a generator that saw only the kept chips (the pipeline ``pipeline`` fine-tuned
  on them with :func:`sar_zero123.stages.run_finetune`, the views written by
  :func:`sar_zero123.augment_dataset.augment_dataset`);
- ``all_chips``: every 17 deg chip (the ceiling).

Optional arms: ``--sectors`` keeps only the chips in a ``sector_deg`` azimuth sector per class (views at
the other sectors); ``--unseen_class T72`` adds, per K, a generator fine-tuned without that class, whose views
of it are what a user gets for a new vehicle. For each generated arm, ``view_quality`` says what limits the
views: the ceiling classifier's accuracy on the generated views against their source's class, on the VAE
round trip of real 15 deg chips (the generator's decoder bound) and on the same real chips.

Variant arms, from the same fine-tuned generator per K: ``--speckle_looks L`` adds
``generated_k{K}_speckle{L}`` (the views with L-look speckle re-added, ``augment_dataset --speckle_looks``),
``--heading_guidance H`` adds ``generated_k{K}_heading{H}`` (the plain views sampled with heading guidance
``H``, ``SARZero123Pipeline``'s pull away from the request turned by 180 deg); ``--strength S`` adds
``generated_k{K}_strength{S}`` (the views started from the kept chip's own latent,
SDEdit); ``--same_azimuth_control`` adds the controls ``generated_k{K}_d_az0`` (and
``..._strength{S}_d_az0``): the same views made at the chip's own azimuth, what the requested pose
adds. Every plain generated arm (per K, the sector's, the unseen class's) gets the selected variants.

``--eoc1_data`` adds the depression transfer of MSTAR's EOC-1 (issue 37): train on the 17 deg chips of the
objects whose chips that folder holds (2S1 b01, BRDM2 E-71, T72 A64, ZSU234 d08 in
``../shared/data/mstar_eoc1``), test on that folder's chips (30 deg). Arms, each with every 17 deg chip of
those serials and with ``eoc1_ks`` chips per class: ``eoc1_real_*`` (real 17 deg chips only),
``eoc1_generated_*`` (+ one view per chip at ``d_el`` = test depression - 17 deg, from a generator fine-tuned
on those 17 deg chips only, never on a test chip) and ``eoc1_generated_*_d_el0`` (+ the same number of views
at ``d_el = 0``: the control), and ``eoc1_ceiling_cv`` (a classifier trained on the test chips themselves,
cross-validated: seed i holds out fold i). ``--depression_guidance G`` adds
``eoc1_generated_*_depression{G}`` (the d_el views sampled with depression guidance G; their control is
the plain ``_d_el0``). ``--strength S`` adds ``eoc1_generated_*_strength{S}`` (the views
started from the chip's noised latent) and ``--eoc1_views_per_chip N`` (N > 1) ``eoc1_generated_*_views{N}``
(N views per chip at ``d_az = 0`` and offsets spread evenly in the gap to its neighbours), each with its
``_d_el0`` control; ``--no-eoc1_all`` drops the arms with every chip. A generator fine-tuned on one
depression has never paired two, so these arms need ``--rehearsal_data`` (a prior corpus mixed into every
generator's fine-tune, ``FinetuneConfig.rehearsal_data``). Their ``view_quality`` scores the views with
the ceiling's seed-0 classifier (trained on test-depression chips), beside the views' 17 deg sources (the
floor) and its held-out fold (the ceiling): views that moved towards the test depression score above their
sources.

Every arm trains its classifiers with the same seeds, so arms are compared seed by seed: each generated arm
carries ``gain_over_real`` (against the real-only arm with the same kept chips) and each arm whose control
ran ``gain_over_same_azimuth`` (:func:`add_paired_gains`).

Every arm writes into its own folder under ``--out`` and ends with ``result.json``; an arm whose
``result.json`` exists is skipped, a generator or an augmentation cut short resumes (run-folder rule), so
a killed run is continued by the same command. ``--out``/``results.json`` gathers every finished arm
of the folder, this invocation's first, then those of earlier invocations.

    python benchmarks/augmentation_benefit.py --data ../shared/data/mstar --out runs/aug26 [--quick]
    python benchmarks/augmentation_benefit.py --data ../shared/data/mstar --out runs/eoc1 --ks --no-sectors \
        --unseen_class none --eoc1_data ../shared/data/mstar_eoc1 --rehearsal_data runs/prior/corpus
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import re
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline
from sar_zero123.augment_dataset import AugmentConfig, augment_dataset
from sar_zero123.config import field_comments, write_json_atomic
from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, load_index, signed_to_unit
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluation.evaluators import SARClassifier, load_evaluator
from sar_zero123.runs.folder import field_defaults
from sar_zero123.stages import FinetuneConfig, run_finetune

logger = logging.getLogger("augmentation_benefit")

TRAIN_DEPRESSION_DEG = 17.0
TEST_DEPRESSION_DEG = 15.0
RESULT_FILE = "result.json"
#: Fields that only add or drop arms: a resumed benchmark may change them; any other change is refused.
ARM_SELECTION_FIELDS = (
    "data", "out", "ks", "sectors", "unseen_class", "unseen_k", "speckle_looks", "strength",
    "same_azimuth_control", "eoc1_data", "eoc1_ks", "eoc1_all", "eoc1_views_per_chip", "heading_guidance",
    "view_filters", "validation_chips_per_class", "depression_guidance",
)  # fmt: skip
#: Ways of keeping fewer generated views (BenchmarkConfig.view_filters).
VIEW_FILTERS = ("confident", "ratio1")
#: The reduced configuration: two K, no sector or unseen-class arms (about 30 min on 2 CPU cores, estimated).
QUICK = {"ks": [12, 48], "sectors": False, "unseen_class": None}


@dataclass
class BenchmarkConfig:
    """The whole benchmark; the defaults are the full configuration of issue 26."""

    data: str = ""  # dataset folder with index.csv holding 17 and 15 deg chips
    out: str = ""  # benchmark folder: one sub-folder per arm and generator, results.json
    ks: list[int] = field(default_factory=lambda: [12, 24, 48])  # kept 17 deg chips per class
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])  # classifier seeds per arm
    sectors: bool = True  # also the missing-sector arms
    sector_deg: float = 90.0  # width of the kept azimuth sector (from 0 deg)
    unseen_class: str | None = "T72"  # class the unseen-class generator never sees (None: no variant)
    unseen_k: int = 12  # K of the unseen-class variant
    views_per_chip: int = 3  # generated views per kept chip, evenly between it and its neighbours
    # pretrained pipeline each generator is fine-tuned from: the prior that also sees the input turned by
    # d_az; its K = 12 views help by their pose (+4.2 points over the same-azimuth control, against -1.2 from
    # sim-prior; docs/results/history/augmentation_benefit.md, "The rotated prior as the generator")
    pipeline: str = SIM_PRIOR_ROTATED
    finetune_steps: int = 3000  # fine-tune steps per generator (400 and 1,000 keep too little identity)
    finetune_batch_size: int = 16  # pairs per fine-tune step
    finetune_learning_rate: float = 1e-3  # AdamW learning rate of the fine-tune
    num_inference_steps: int = 10  # DDIM steps per generated view
    guidance_scale: float = 3.0  # classifier-free guidance of the generated views
    image_size: int = 64  # classifier input: centre crop in pixels at the native spacing
    classifier_steps: int = 1000  # optimisation steps per classifier (the same in every arm)
    classifier_batch_size: int = 32  # chips per classifier step
    classifier_learning_rate: float = 2e-3  # AdamW peak learning rate (cosine decay to 0)
    classifier_weight_decay: float = 5e-4  # AdamW weight decay
    max_shift_px: int = 4  # training augmentation: random shifts up to this many pixels
    quality_chips_per_class: int = 50  # 15 deg chips per class for the VAE round-trip bound
    speckle_looks: int | None = None  # also arms whose views get L-look speckle re-added (None: no such arms)
    strength: float | None = None  # also arms whose views start from the kept chip's noised latent (SDEdit)
    same_azimuth_control: bool = False  # also the plain (and strength) views at d_az = 0: what the pose adds
    heading_guidance: float | None = None  # also arms of the plain views at this heading guidance; None: no
    # also arms of the plain views filtered (VIEW_FILTERS): "confident" keeps the views the real-only
    # classifier of the same chips reads as their class, "ratio1" one view per kept chip (of views_per_chip)
    view_filters: list[str] = field(default_factory=list)
    validation_chips_per_class: int = 50  # 17 deg chips left out of an arm's K, for its validation accuracy
    # a prior corpus (write_prior_corpus, e.g. train/pretrain_prior.py's corpus/) mixed into every generator's
    # fine-tune (FinetuneConfig.rehearsal_data); None: the kept chips only. The EOC-1 arms need it
    rehearsal_data: str | None = None
    rehearsal_fraction: float = 0.25  # share of each generator's training pairs drawn from rehearsal_data
    eoc1_data: str | None = None  # folder of EOC-1's test chips (one depression): adds the EOC-1 arms
    eoc1_ks: list[int] = field(default_factory=lambda: [24])  # EOC-1 arms with K chips/class, beside all
    eoc1_all: bool = True  # also the EOC-1 arms with every 17 deg chip of the four serials
    # views per kept chip in the EOC-1 arms: 1 (at d_az = 0) or N > 1, which adds the arms ..._views{N} (at
    # d_az = 0 and N - 1 offsets spread evenly in the azimuth gap to the chip's neighbours)
    eoc1_views_per_chip: int = 1
    # also EOC-1 arms whose depression views are sampled with this depression guidance (SARZero123Pipeline's
    # pull away from the same request at the chip's own depression), ..._depression{G}; their d_el = 0
    # control is the plain one (the guidance leaves d_el = 0 requests unchanged). None: no such arms
    depression_guidance: float | None = None

    def __post_init__(self) -> None:
        for name in ("ks", "eoc1_ks"):
            if any(k < 2 for k in getattr(self, name)):
                raise ValueError(f"{name} must hold values >= 2, got {getattr(self, name)}")
        if not self.seeds:
            raise ValueError("seeds must not be empty")
        for name in ("views_per_chip", "eoc1_views_per_chip"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.sector_deg < 360.0:
            raise ValueError(f"sector_deg must lie in (0, 360), got {self.sector_deg}")
        for name in ("finetune_steps", "classifier_steps", "classifier_batch_size", "num_inference_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.speckle_looks is not None and self.speckle_looks < 1:
            raise ValueError(f"speckle_looks must be None or >= 1, got {self.speckle_looks}")
        if self.strength is not None and not 0.0 < self.strength < 1.0:
            raise ValueError(f"strength must be None or in (0, 1), got {self.strength}")
        for name in ("heading_guidance", "depression_guidance"):
            value = getattr(self, name)
            if value is not None and not 0.0 < value <= 100.0:
                raise ValueError(f"{name} must be None or in (0, 100], got {value}")
        unknown = sorted(set(self.view_filters) - set(VIEW_FILTERS))
        if unknown:
            raise ValueError(f"view_filters must be among {VIEW_FILTERS}, got {unknown}")
        if not 0.0 <= self.rehearsal_fraction < 1.0:
            raise ValueError(f"rehearsal_fraction must lie in [0, 1), got {self.rehearsal_fraction}")
        if self.eoc1_data is not None and (self.rehearsal_data is None or self.rehearsal_fraction == 0.0):
            raise ValueError(
                "rehearsal_data: the EOC-1 arms ask for views at another depression, which a generator "
                "fine-tuned on 17 deg chips alone never paired; give a prior corpus "
                "(train/pretrain_prior.py's corpus/) and a rehearsal_fraction above 0"
            )


# ------------------------------------------------------------------------------------------ selection
def at_depression(records: Sequence[ChipRecord], depression_deg: float) -> list[ChipRecord]:
    """The records within 0.01 deg of a depression."""
    return [r for r in records if abs(r.depression_deg - depression_deg) < 0.01]


def circular_distance_deg(a: float, b: float) -> float:
    """Smallest angle between two azimuths in degrees, in [0, 180]."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def keep_evenly_spaced(records: Sequence[ChipRecord], k: int) -> list[ChipRecord]:
    """Per class, the `k` chips nearest to the azimuths ``i * 360 / k`` (each chip once), in record order.

    Raises:
        ValueError: If a class has fewer than `k` chips.
    """
    kept: set[int] = set()
    for name in sorted({r.target_class for r in records}):
        members = [i for i, r in enumerate(records) if r.target_class == name]
        if len(members) < k:
            raise ValueError(f"class {name} has {len(members)} chips, fewer than k={k}")
        for i in range(k):
            grid_deg = i * 360.0 / k
            free = [j for j in members if j not in kept]
            kept.add(min(free, key=lambda j: circular_distance_deg(records[j].azimuth_deg, grid_deg)))
    return [records[i] for i in sorted(kept)]


def keep_sector(records: Sequence[ChipRecord], sector_deg: float) -> list[ChipRecord]:
    """The chips with azimuth in ``[0, sector_deg)``."""
    return [r for r in records if r.azimuth_deg < sector_deg]


def fill_offsets_deg(gap_deg: float, views_per_chip: int) -> list[float]:
    """Azimuth changes that place `views_per_chip` views evenly in the gaps around a kept chip.

    The views sit at ``j * gap / (views_per_chip + 1)`` for ``j = 1..views_per_chip`` after the chip, each
    generated from the nearer of the two kept chips around it: offsets past half the gap are taken
    backwards from the next chip, so ``|d_az| <= gap / 2``.
    """
    step = gap_deg / (views_per_chip + 1)
    offsets = [j * step for j in range(1, views_per_chip + 1)]
    return [o if o <= gap_deg / 2 else o - gap_deg for o in offsets]


# ---------------------------------------------------------------------------------------------- chips
def load_images(
    records: Sequence[ChipRecord], class_names: list[str], scaling: DecibelScaling, size: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The chips as normalised dB centre crops and their labels. Shape: (N, 1, size, size), (N,)."""
    dataset = ChipDataset(list(records), size=size, scaling=scaling, class_names=class_names)
    items = [dataset[i] for i in range(len(dataset))]
    images = torch.stack([item["image"] for item in items]).float()
    labels = torch.tensor([item["label"] for item in items], dtype=torch.long)
    return images, labels


def random_shift(images: torch.Tensor, max_shift_px: int, generator: torch.Generator) -> torch.Tensor:
    """Each image shifted by its own random offset in ``[-max_shift_px, max_shift_px]`` (reflected border)."""
    if max_shift_px == 0:
        return images
    size = images.shape[-1]
    padded = F.pad(images, (max_shift_px,) * 4, mode="reflect")
    offsets = torch.randint(0, 2 * max_shift_px + 1, (len(images), 2), generator=generator)
    return torch.stack([p[:, y : y + size, x : x + size] for p, (y, x) in zip(padded, offsets.tolist())])


def train_classifier(
    images: torch.Tensor,
    labels: torch.Tensor,
    *,
    class_names: list[str],
    scaling: DecibelScaling,
    steps: int,
    batch_size: int,
    learning_rate: float,
    weight_decay: float,
    max_shift_px: int,
    seed: int,
) -> SARClassifier:
    """The benchmark's classifier trained `steps` AdamW steps (cosine to 0) on random shifts of the chips.

    Every arm trains for the same number of steps, so that an arm with more chips does not also get more
    compute. The ResNet is the quickstart's evaluator (stages of one block, widths 16-128, no CIFAR stem).
    """
    torch.manual_seed(seed)
    encoder_config = SAREncoderConfig(
        image_size=images.shape[-1], in_channels=1, cifar_stem=False, depths=(1, 1, 1, 1),
        hidden_sizes=(16, 32, 64, 128),
    )  # fmt: skip
    model = SARClassifier(encoder_config, class_names, scaling)
    optimizer = torch.optim.AdamW(model.parameters(), lr=learning_rate, weight_decay=weight_decay)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=steps)
    generator = torch.Generator().manual_seed(seed)
    model.train()
    order = torch.randperm(len(images), generator=generator)
    position = 0
    for _ in range(steps):
        if position + batch_size > len(order):
            order, position = torch.randperm(len(images), generator=generator), 0
        batch = order[position : position + batch_size]
        position += batch_size
        loss = F.cross_entropy(model(random_shift(images[batch], max_shift_px, generator)), labels[batch])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
    return model.eval()


@torch.no_grad()
def predict(model: SARClassifier, images: torch.Tensor, batch_size: int = 256) -> torch.Tensor:
    """Predicted class indices. Shape: (N,)."""
    model.eval()
    starts = range(0, len(images), batch_size)
    return torch.cat([model(images[i : i + batch_size]).argmax(dim=1) for i in starts])


def accuracy(model: SARClassifier, images: torch.Tensor, labels: torch.Tensor) -> float:
    """Share of correctly classified chips, in [0, 1]."""
    return float((predict(model, images) == labels).float().mean())


@torch.no_grad()
def vae_round_trip(pipe: SARZero123Pipeline, images: torch.Tensor, batch_size: int = 64) -> torch.Tensor:
    """Normalised dB images through the pipeline's VAE (latent mode, decoded), the views' best case."""
    out = []
    for i in range(0, len(images), batch_size):
        signed = images[i : i + batch_size] * 2.0 - 1.0
        latents = pipe.vae.encode(signed).latent_dist.mode()
        out.append(signed_to_unit(pipe.vae.decode(latents).sample).clamp(0.0, 1.0))
    return torch.cat(out)


# ---------------------------------------------------------------------------------------- generation
def write_generator_data(kept: Sequence[ChipRecord], folder: Path) -> Path:
    """A dataset folder the generator trains on: the kept chips (17 deg, absolute paths) only.

    The ``extended`` protocol also needs a 15 deg split; it gets a symbolic link to each kept chip listed at
    15 deg, which fine-tuning never trains on (no validation): the generator sees the kept chips only.
    """
    folder.mkdir(parents=True, exist_ok=True)
    links = folder / "links"
    links.mkdir(exist_ok=True)
    rows = list(kept)
    for i, record in enumerate(kept):
        link = links / f"{i:05d}{Path(record.path).suffix}"
        if not link.is_symlink():
            link.symlink_to(Path(record.path).resolve())
        rows.append(
            ChipRecord(**{**asdict(record), "path": link, "depression_deg": TEST_DEPRESSION_DEG})
        )
    index = folder / "index.csv"
    header = "path,target_class,target_type,serial,depression_deg,azimuth_deg,height,width\n"
    lines = [
        f"{Path(r.path).absolute()},{r.target_class},{r.target_type},{r.serial},{r.depression_deg:g},"
        f"{r.azimuth_deg:.4f},{r.height},{r.width}\n"
        for r in rows
    ]
    tmp = index.with_suffix(".tmp")
    tmp.write_text(header + "".join(lines))
    os.replace(tmp, index)
    return folder


def seed_summary(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """An arm's classifiers: accuracy mean and sample std over seeds, the per-seed records, CPU and wall s."""
    accuracies = np.array([s["test_accuracy"] for s in per_seed])
    return {
        "test_accuracy_mean": float(accuracies.mean()),
        "test_accuracy_std": float(accuracies.std(ddof=1)) if len(accuracies) > 1 else 0.0,
        "seeds": per_seed,
        "classifier_cpu_s": sum(s["cpu_s"] for s in per_seed),
        "classifier_wall_s": sum(s["wall_s"] for s in per_seed),
    }


def timed(function: Any, *args: Any, **kwargs: Any) -> tuple[Any, dict[str, float]]:
    """Calls `function` and returns its result with its wall and process CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = function(*args, **kwargs)
    return result, {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}


def build_generator(
    config: BenchmarkConfig,
    trained_on: Sequence[ChipRecord],
    sources: Sequence[ChipRecord],
    folder: Path,
    d_az: list[float],
    speckle_looks: int | None = None,
    strength: float = 1.0,
    d_el: float = 0.0,
    heading_guidance: float = 0.0,
    views_tag: str = "",
    depression_guidance: float = 0.0,
) -> tuple[Path, dict[str, Any]]:
    """Fine-tunes the pipeline on `trained_on`, then generates `d_az` views (at depression change `d_el`)
    of each of `sources`; both resumable. With `speckle_looks` or `strength` < 1, the views (in their own
    folder, from the same fine-tune) get L-look speckle re-added or start from the source's noised latent
    (``AugmentConfig``). `views_tag` (e.g. ``"_views3"``) names views whose `d_az` list differs from the
    folder's usual one, so that two lists never share a views folder.

    Returns the augmented dataset folder (views only) and the times of the fine-tune and this generation.
    """
    timing_file = folder / "timing.json"
    times = json.loads(timing_file.read_text()) if timing_file.is_file() else {}
    data = write_generator_data(trained_on, folder / "data")
    source_data = write_generator_data(sources, folder / "sources")
    if "finetune" not in times:
        _, times["finetune"] = timed(run_finetune, FinetuneConfig(
            output_dir=str(folder / "finetune"), pretrained=config.pipeline, data=str(data),
            protocol="extended", scaling="unit", pfm_weight=0.0, learning_rate=config.finetune_learning_rate,
            train_batch_size=config.finetune_batch_size, max_train_steps=config.finetune_steps,
            use_ema=False, snr_gamma=5.0, validation_steps=0, report_to=None,
            checkpointing_steps=max(config.finetune_steps // 3, 1), checkpoints_total_limit=1,
            resume_from_checkpoint="latest", seed=0, rehearsal_data=config.rehearsal_data,
            rehearsal_fraction=config.rehearsal_fraction,
        ))  # fmt: skip
        write_json_atomic(times, timing_file)
    suffix = variant_suffix(speckle_looks, strength, same_azimuth=all(d == 0.0 for d in d_az), d_el=d_el,
                            heading_guidance=heading_guidance,
                            depression_guidance=depression_guidance) + views_tag  # fmt: skip
    views, key = folder / f"views{suffix}", f"generate{suffix}"
    if key not in times:
        _, times[key] = timed(augment_dataset, AugmentConfig(
            data=str(source_data), pipeline=str(folder / "finetune" / "pipeline"), out=str(views), d_az=d_az,
            d_el=[d_el], depressions_deg=[TRAIN_DEPRESSION_DEG],
            num_inference_steps=config.num_inference_steps, guidance_scale=config.guidance_scale,
            scheduler="ddim", batch_size=16, seed=0,
            speckle_looks=speckle_looks, strength=strength, heading_guidance_scale=heading_guidance,
            depression_guidance_scale=depression_guidance,
        ))  # fmt: skip
        times[key]["views"] = len(load_index(views))
        write_json_atomic(times, timing_file)
    return views, {"finetune": times["finetune"], key: times[key]}


def variant_suffix(
    speckle_looks: int | None = None, strength: float = 1.0, same_azimuth: bool = False, d_el: float = 0.0,
    heading_guidance: float = 0.0, view_filter: str | None = None, filter_classifier: Path | None = None,
    depression_guidance: float = 0.0,
) -> str:
    """``_speckle<L>``, ``_strength<S>``, ``_heading<H>``, ``_depression<G>``, ``_d_az0``, ``_d_el<D>`` and
    ``_<filter>`` for views generated or kept other than plainly (``""``)."""
    return (
        ("" if view_filter is None else f"_{view_filter}")
        + ("" if speckle_looks is None else f"_speckle{speckle_looks}")
        + ("" if strength == 1.0 else f"_strength{strength:g}")
        + ("" if heading_guidance == 0.0 else f"_heading{heading_guidance:g}")
        + ("" if depression_guidance == 0.0 else f"_depression{depression_guidance:g}")
        + ("_d_az0" if same_azimuth else "")
        + ("" if d_el == 0.0 else f"_d_el{d_el:g}")
    )


def check_settings(config: BenchmarkConfig, out: Path) -> None:
    """Records the settings in ``out/settings.json``, or refuses a resume whose settings differ there.

    Raises:
        ValueError: Naming each field (outside :data:`ARM_SELECTION_FIELDS`) that differs from the record.
    """
    settings = {k: v for k, v in asdict(config).items() if k not in ARM_SELECTION_FIELDS}
    record = out / "settings.json"
    if record.is_file():
        # a setting the record lacks was made with its default (a folder written before the setting existed)
        defaults = {k: v for k, v in field_defaults(BenchmarkConfig).items() if k in settings}
        recorded = {**defaults, **json.loads(record.read_text())}
        changed = sorted(k for k in settings.keys() | recorded.keys() if settings.get(k) != recorded.get(k))
        if changed:
            details = ", ".join(f"{k}: {recorded.get(k)!r} -> {settings.get(k)!r}" for k in changed)
            raise ValueError(f"out: {out} holds a benchmark with other settings ({details}); use another out")
        return
    write_json_atomic(settings, record)


# ---------------------------------------------------------------------------------------------- arms
class Benchmark:
    """The chips in memory once, and the arms that train classifiers on subsets of them."""

    def __init__(self, config: BenchmarkConfig) -> None:
        self.config = config
        self.out = Path(config.out)
        check_settings(config, self.out)
        records = load_index(config.data)
        self.train_records = at_depression(records, TRAIN_DEPRESSION_DEG)
        self.test_records = at_depression(records, TEST_DEPRESSION_DEG)
        if not self.train_records or not self.test_records:
            raise ValueError(f"data: needs chips at {TRAIN_DEPRESSION_DEG} and {TEST_DEPRESSION_DEG} deg")
        self.class_names = sorted({r.target_class for r in records})
        self.scaling = DecibelScaling.for_unit_magnitude()
        self._cache: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        self.test_images, self.test_labels = self.images(self.test_records)

    def images(self, records: Sequence[ChipRecord]) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised crops and labels of records, each chip read from disk once."""
        missing = [r for r in records if str(r.path) not in self._cache]
        if missing:
            images, labels = load_images(missing, self.class_names, self.scaling, self.config.image_size)
            for record, image, label in zip(missing, images, labels):
                self._cache[str(record.path)] = (image, label)
        pairs = [self._cache[str(r.path)] for r in records]
        return torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])

    def classifiers(self, records: Sequence[ChipRecord], arm_dir: Path) -> dict[str, Any]:
        """Trains one classifier per seed on the records and scores each on every 15 deg chip."""
        config = self.config
        images, labels = self.images(records)
        per_seed = []
        for seed in config.seeds:
            model, times = timed(
                train_classifier, images, labels, class_names=self.class_names, scaling=self.scaling,
                steps=config.classifier_steps, batch_size=config.classifier_batch_size,
                learning_rate=config.classifier_learning_rate, weight_decay=config.classifier_weight_decay,
                max_shift_px=config.max_shift_px, seed=seed,
            )  # fmt: skip
            test_accuracy = accuracy(model, self.test_images, self.test_labels)
            per_seed.append({"seed": seed, "test_accuracy": test_accuracy, **times})
            if seed == config.seeds[0]:
                model.save_pretrained(arm_dir / "classifier_seed0")
            logger.info("%s seed %d: %.4f", arm_dir.name, seed, per_seed[-1]["test_accuracy"])
        return {"n_train": len(records), "n_test": len(self.test_records), **seed_summary(per_seed)}

    def run_arm(self, name: str, build: Any) -> dict[str, Any]:
        """Runs one arm into ``out/<name>`` unless its ``result.json`` exists; returns its result."""
        arm_dir = self.out / name
        result_file = arm_dir / RESULT_FILE
        if result_file.is_file():
            logger.info("%s finished; skipping", name)
            return json.loads(result_file.read_text())
        arm_dir.mkdir(parents=True, exist_ok=True)
        logger.info("arm %s", name)
        result = {"arm": name, **build(arm_dir)}
        result["total_cpu_s"] = result["classifier_cpu_s"] + result.get("generator_cpu_s", 0.0)
        result["total_wall_s"] = result["classifier_wall_s"] + result.get("generator_wall_s", 0.0)
        write_json_atomic(result, result_file)
        return result

    def real_arm(self, kept: Sequence[ChipRecord], description: str) -> Any:
        return lambda arm_dir: {"description": description, **self.classifiers(kept, arm_dir)}

    def generated_arm(
        self, kept: Sequence[ChipRecord], d_az: list[float], generator_dir: Path, description: str,
        generator_records: Sequence[ChipRecord] | None = None, speckle_looks: int | None = None,
        strength: float = 1.0, d_el: float = 0.0, heading_guidance: float = 0.0,
        view_filter: str | None = None, filter_classifier: Path | None = None, views_tag: str = "",
        depression_guidance: float = 0.0,
    ) -> Any:  # fmt: skip
        def build(arm_dir: Path) -> dict[str, Any]:
            trained_on = kept if generator_records is None else generator_records
            views_dir, times = build_generator(
                self.config, trained_on, kept, generator_dir, d_az, speckle_looks, strength, d_el,
                heading_guidance, views_tag, depression_guidance,
            )
            generated = load_index(views_dir)
            views = self.filter_views(generated, view_filter, filter_classifier)
            result = self.classifiers(list(kept) + views, arm_dir)
            if view_filter is not None:
                result.update(view_filter=view_filter, n_generated_before_filter=len(generated))
            result.update(
                description=description, n_real=len(kept), n_generated=len(views), d_az_deg=d_az,
                d_el_deg=d_el,
                generator=str(generator_dir), generator_times=times,
                generator_cpu_s=sum(t["cpu_s"] for t in times.values()),
                generator_wall_s=sum(t["wall_s"] for t in times.values()),
                view_quality=self.view_quality(views, generator_dir),
            )
            return result

        return build

    def filter_views(
        self, views: list[ChipRecord], view_filter: str | None, classifier_dir: Path | None
    ) -> list[ChipRecord]:
        """The generated views an arm keeps: all (None); those a classifier trained on the real chips of
        the same arm reads as their class ("confident"); or one per kept chip ("ratio1": the view whose
        ``(row + request) % views_per_chip == 0``, so the kept offsets rotate across chips)."""
        if view_filter is None:
            return views
        if view_filter == "ratio1":
            def index(view: ChipRecord) -> tuple[int, int]:  # ..._r<row>_q<request>.npy
                row, request = Path(view.path).stem.split("_")[-2:]
                return int(row[1:]), int(request[1:])

            return [v for v in views if sum(index(v)) % self.config.views_per_chip == 0]
        if view_filter == "confident":
            if classifier_dir is None:
                raise ValueError("view_filter 'confident' needs the real-only arm's classifier")
            images, labels = self.images(views)
            keep = (predict(load_evaluator(classifier_dir), images) == labels).tolist()
            return [v for v, k in zip(views, keep) if k]
        raise ValueError(f"view_filter must be None or one of {VIEW_FILTERS}, got {view_filter!r}")

    def validation_accuracy(self, arm: dict[str, Any]) -> float | None:
        """Seed 0's classifier of a K arm on 17 deg chips left out of that arm's K
        (``validation_chips_per_class`` per class, evenly spaced): a validation split of the training
        depression, never a test chip; None for other arms or an arm without a saved classifier."""
        match = re.match(r"(real|generated)_k(\d+)", arm["arm"])
        classifier = self.out / arm["arm"] / "classifier_seed0"
        if match is None or not (classifier / "evaluator.json").is_file():
            return None
        kept = {str(r.path) for r in keep_evenly_spaced(self.train_records, int(match.group(2)))}
        pool = []
        for name in self.class_names:
            members = [r for r in self.train_records if r.target_class == name and str(r.path) not in kept]
            step = max(len(members) // self.config.validation_chips_per_class, 1)
            pool += members[::step][: self.config.validation_chips_per_class]
        images, labels = self.images(pool)
        return accuracy(load_evaluator(classifier), images, labels)

    def view_quality(self, views: Sequence[ChipRecord], generator_dir: Path) -> dict[str, Any]:
        """The ceiling classifier on the generated views, on VAE round trips of 15 deg chips and on those
        chips."""
        ceiling = load_evaluator(self.out / "all_chips" / "classifier_seed0")
        view_images, view_labels = self.images(views)
        sample = []
        for name in self.class_names:
            members = [r for r in self.test_records if r.target_class == name]
            step = max(len(members) // self.config.quality_chips_per_class, 1)
            sample += members[::step][: self.config.quality_chips_per_class]
        real_images, real_labels = self.images(sample)
        pipe = SARZero123Pipeline.from_pretrained(generator_dir / "finetune" / "pipeline")
        round_trip = vae_round_trip(pipe, real_images)
        per_class = {
            name: float((predict(ceiling, view_images[view_labels == i]) == i).float().mean())
            for i, name in enumerate(self.class_names)
            if (view_labels == i).any()
        }
        return {
            "classifier": "all_chips seed 0",
            "generated_views_accuracy": accuracy(ceiling, view_images, view_labels),
            "generated_views_accuracy_per_class": per_class,
            "n_views": len(views),
            "vae_round_trip_accuracy": accuracy(ceiling, round_trip, real_labels),
            "real_accuracy_same_chips": accuracy(ceiling, real_images, real_labels),
            "n_round_trip": len(sample),
            "vae_round_trip_mae": float((round_trip - real_images).abs().mean()),
            "normalised_db_mean_std": {
                "generated": [float(view_images.mean()), float(view_images.std())],
                "real_15deg": [float(real_images.mean()), float(real_images.std())],
                "vae_round_trip": [float(round_trip.mean()), float(round_trip.std())],
            },
        }

    def variant_arms(
        self, name: str, kept: Sequence[ChipRecord], d_az: list[float], generator_dir: Path,
        description: str, generator_records: Sequence[ChipRecord] | None = None,
    ) -> list[dict[str, Any]]:  # fmt: skip
        """The selected variants of the plain arm `name`: the same generator's views made otherwise.

        ``speckle_looks`` re-adds speckle, ``strength`` starts each view from its kept chip's noised latent,
        ``same_azimuth_control`` makes the plain views and the strength views again at ``d_az = 0`` (what the
        requested pose adds), ``heading_guidance`` samples the plain views with that heading guidance.
        """
        config = self.config
        variants: list[tuple[dict[str, Any], bool, str]] = []
        if config.speckle_looks is not None:
            variants.append(({"speckle_looks": config.speckle_looks}, False,
                             f"{config.speckle_looks}-look speckle re-added"))  # fmt: skip
        if config.same_azimuth_control:
            variants.append(({}, True, "at the chip's own azimuth"))
        if config.strength is not None:
            words = f"started from the chip, strength {config.strength:g}"
            variants.append(({"strength": config.strength}, False, words))
            if config.same_azimuth_control:
                variants.append(({"strength": config.strength}, True, f"{words}, at the chip's own azimuth"))
        if config.heading_guidance is not None:
            words = f"heading guidance {config.heading_guidance:g}"
            variants.append(({"heading_guidance": config.heading_guidance}, False, words))
        baseline = real_baseline(name)
        for view_filter in config.view_filters:
            words = {"confident": "only the views the real-only classifier reads as their class",
                     "ratio1": "one view per kept chip"}[view_filter]  # fmt: skip
            classifier = None if baseline is None else self.out / baseline / "classifier_seed0"
            variants.append(({"view_filter": view_filter, "filter_classifier": classifier}, False, words))
        return [
            self.run_arm(f"{name}{variant_suffix(**options, same_azimuth=same)}", self.generated_arm(
                kept, [0.0] * len(d_az) if same else d_az, generator_dir, f"{description}, {words}",
                generator_records=generator_records, **options,
            ))  # fmt: skip
            for options, same, words in variants
        ]

    def run(self) -> dict[str, Any]:
        """Every arm of the configuration, ceiling first (the view-quality classifier)."""
        config = self.config
        results = [self.run_arm("all_chips", self.real_arm(self.train_records, "every 17 deg chip"))]
        for k in config.ks:
            kept = keep_evenly_spaced(self.train_records, k)
            d_az = fill_offsets_deg(360.0 / k, config.views_per_chip)
            results.append(self.run_arm(f"real_k{k}", self.real_arm(kept, f"{k} evenly spaced chips/class")))
            results.append(self.run_arm(f"generated_k{k}", self.generated_arm(
                kept, d_az, self.out / f"generator_k{k}",
                f"{k} chips/class + {config.views_per_chip} views each",
            )))  # fmt: skip
            results += self.variant_arms(
                f"generated_k{k}", kept, d_az, self.out / f"generator_k{k}",
                f"{k} chips/class + {config.views_per_chip} views each",
            )  # fmt: skip
        if config.sectors:
            kept = keep_sector(self.train_records, config.sector_deg)
            sectors = math.floor(360.0 / config.sector_deg)
            d_az = [config.sector_deg * j for j in range(1, sectors)]
            d_az = [d if d <= 180.0 else d - 360.0 for d in d_az]
            sector = f"[0, {config.sector_deg:g}) deg"
            results.append(self.run_arm("real_sector", self.real_arm(kept, sector)))
            results.append(self.run_arm("generated_sector", self.generated_arm(
                kept, d_az, self.out / "generator_sector", f"{sector} + rotated views",
            )))  # fmt: skip
            results += self.variant_arms(
                "generated_sector", kept, d_az, self.out / "generator_sector", f"{sector} + rotated views"
            )
        if config.unseen_class is not None:
            k = config.unseen_k
            kept = keep_evenly_spaced(self.train_records, k)
            seen = [r for r in kept if r.target_class != config.unseen_class]
            d_az = fill_offsets_deg(360.0 / k, config.views_per_chip)
            # views of every class, from a generator that never saw the unseen one
            results.append(self.run_arm(f"generated_k{k}_unseen_{config.unseen_class}", self.generated_arm(
                kept, d_az, self.out / f"generator_k{k}_without_{config.unseen_class}",
                f"{k} chips/class + views; generator trained without {config.unseen_class}",
                generator_records=seen,
            )))  # fmt: skip
            results += self.variant_arms(
                f"generated_k{k}_unseen_{config.unseen_class}", kept, d_az,
                self.out / f"generator_k{k}_without_{config.unseen_class}",
                f"{k} chips/class + views; generator trained without {config.unseen_class}",
                generator_records=seen,
            )  # fmt: skip
        if config.eoc1_data is not None:
            results += DepressionTransfer(self, load_index(config.eoc1_data)).run_arms()
        results += self.earlier_arms({arm["arm"] for arm in results})
        for arm in results:
            value = self.validation_accuracy(arm)
            if value is not None:
                arm["validation_accuracy_seed0"] = value
        summary = {
            "benchmark": "augmentation_benefit (issue 26, EOC-1: issue 37)",
            "config": asdict(config),
            "device": f"CPU, {os.cpu_count()} cores, torch {torch.__version__}",
            "platform": platform.platform(),
            "arms": add_paired_gains(results),
        }
        write_json_atomic(summary, self.out / "results.json")
        return summary

    def earlier_arms(self, names: set[str]) -> list[dict[str, Any]]:
        """The finished arms of this folder that this invocation did not select (earlier invocations'),
        in name order, so that ``results.json`` holds every arm of the folder."""
        found = sorted(path for path in self.out.glob(f"*/{RESULT_FILE}") if path.parent.name not in names)
        return [json.loads(path.read_text()) for path in found]


def cv_folds(records: Sequence[ChipRecord], folds: int, seed: int = 0) -> list[int]:
    """A fold index in ``[0, folds)`` per record: each class's records in a seeded random order, dealt
    round-robin, so every fold holds each class in proportion.

    Raises:
        ValueError: If `folds` is below 2 or a class has fewer records than folds.
    """
    if folds < 2:
        raise ValueError(f"folds must be >= 2, got {folds}")
    assignment = [0] * len(records)
    rng = np.random.default_rng(seed)
    for name in sorted({r.target_class for r in records}):
        members = [i for i, r in enumerate(records) if r.target_class == name]
        if len(members) < folds:
            raise ValueError(f"class {name} has {len(members)} chips, fewer than {folds} folds")
        for position, j in enumerate(rng.permutation(len(members))):
            assignment[members[j]] = position % folds
    return assignment


class DepressionTransfer(Benchmark):
    """MSTAR EOC-1's arms: train at 17 deg on the objects of the test chips, test at their depression.

    The training chips are the parent benchmark's 17 deg chips of the (class, serial) pairs the test chips
    show; the classes are those of the test chips. Generated views change the depression by
    ``d_el = test depression - 17 deg`` (the control: ``d_el = 0``), one per chip at ``d_az = 0``.
    """

    CEILING = "eoc1_ceiling_cv"

    def __init__(self, parent: Benchmark, test_records: Sequence[ChipRecord]) -> None:
        depressions = sorted({round(r.depression_deg, 2) for r in test_records})
        if len(depressions) != 1:
            raise ValueError(f"eoc1_data: expected chips at one depression, got {depressions}")
        objects = {r.object_id for r in test_records}
        self.config, self.out, self.scaling = parent.config, parent.out, parent.scaling
        self.train_records = [r for r in parent.train_records if r.object_id in objects]
        missing = objects - {r.object_id for r in self.train_records}
        if missing:
            raise ValueError(f"eoc1_data: data has no {TRAIN_DEPRESSION_DEG:g} deg chip of {sorted(missing)}")
        self.test_records = list(test_records)
        self.class_names = sorted({r.target_class for r in test_records})
        self.d_el = depressions[0] - TRAIN_DEPRESSION_DEG
        self.folds = cv_folds(self.test_records, max(len(self.config.seeds), 2))
        self._cache = {}
        self.test_images, self.test_labels = self.images(self.test_records)

    def ceiling_arm(self) -> Any:
        """Classifiers trained on the test chips themselves: seed i trains on every fold but i % folds and
        is scored on that fold (cross-validation, the chips never scored by a classifier that saw them)."""

        def build(arm_dir: Path) -> dict[str, Any]:
            config, folds = self.config, max(self.folds) + 1
            per_seed = []
            for i, seed in enumerate(config.seeds):
                train = [r for r, f in zip(self.test_records, self.folds) if f != i % folds]
                held = [r for r, f in zip(self.test_records, self.folds) if f == i % folds]
                images, labels = self.images(train)
                model, times = timed(
                    train_classifier, images, labels, class_names=self.class_names, scaling=self.scaling,
                    steps=config.classifier_steps, batch_size=config.classifier_batch_size,
                    learning_rate=config.classifier_learning_rate,
                    weight_decay=config.classifier_weight_decay, max_shift_px=config.max_shift_px, seed=seed,
                )  # fmt: skip
                per_seed.append({"seed": seed, "fold": i % folds, "n_held_out": len(held),
                                 "test_accuracy": accuracy(model, *self.images(held)), **times})  # fmt: skip
                if i == 0:
                    model.save_pretrained(arm_dir / "classifier_seed0")
                logger.info("%s seed %d: %.4f", arm_dir.name, seed, per_seed[-1]["test_accuracy"])
            return {
                "description": f"{folds}-fold cross-validation on the test chips themselves (the ceiling)",
                "n_train": len(self.test_records) - per_seed[0]["n_held_out"],
                "n_test": len(self.test_records),
                **seed_summary(per_seed),
            }

        return build

    def view_quality(self, views: Sequence[ChipRecord], generator_dir: Path) -> dict[str, Any]:
        """The ceiling's seed-0 classifier (trained on test-depression chips) on the views, on their
        17 deg sources (the floor: the depression unchanged) and on its held-out fold (the ceiling)."""
        ceiling = load_evaluator(self.out / self.CEILING / "classifier_seed0")
        sources = at_depression(load_index(generator_dir / "sources"), TRAIN_DEPRESSION_DEG)
        held = [r for r, f in zip(self.test_records, self.folds) if f == 0]
        measured = {"generated": self.images(views), "source_17deg": self.images(sources),
                    "held_out_test": self.images(held)}  # fmt: skip
        return {
            "classifier": f"{self.CEILING} seed 0 (on {TRAIN_DEPRESSION_DEG + self.d_el:g} deg chips)",
            "n_views": len(views),
            **{f"{name}_accuracy": accuracy(ceiling, *pair) for name, pair in measured.items()},
            **{f"n_{name}": len(pair[1]) for name, pair in measured.items()},
            "normalised_db_mean_std": {
                name: [float(pair[0].mean()), float(pair[0].std())] for name, pair in measured.items()
            },
        }

    def run_arms(self) -> list[dict[str, Any]]:
        """The ceiling first (the views' judge), then per selection the real, generated and control arms."""
        config = self.config
        results = [self.run_arm(self.CEILING, self.ceiling_arm())]
        selections = [("all", list(self.train_records), f"every {TRAIN_DEPRESSION_DEG:g} deg chip")]
        selections += [(f"k{k}", keep_evenly_spaced(self.train_records, k), f"{k} evenly spaced chips/class")
                       for k in config.eoc1_ks]  # fmt: skip
        if not config.eoc1_all:
            selections = selections[1:]
        for name, kept, words in selections:
            generator = self.out / f"eoc1_generator_{name}"
            results.append(self.run_arm(f"eoc1_real_{name}", self.real_arm(kept, f"EOC-1: {words}")))
            for views_tag, d_az, strength in self.view_variants(kept):
                arm = f"eoc1_generated_{name}{views_tag}{variant_suffix(strength=strength)}"
                views = "one view" if len(d_az) == 1 else f"{len(d_az)} views (d_az {d_az})"
                started = "" if strength == 1.0 else f", started from the chip (strength {strength:g})"
                # a guided arm's control is the plain _d_el0 arm: the guidance leaves d_el = 0 views unchanged
                guidances = [] if config.depression_guidance is None else [config.depression_guidance]
                for d_el, suffix, guidance in (
                    (self.d_el, "", 0.0), (0.0, "_d_el0", 0.0),
                    *((self.d_el, variant_suffix(depression_guidance=g), g) for g in guidances),
                ):
                    guided = "" if guidance == 0.0 else f", depression guidance {guidance:g}"
                    words_all = f"EOC-1: {words} + {views} each at d_el = {d_el:+g} deg{started}{guided}"
                    results.append(self.run_arm(arm + suffix, self.generated_arm(
                        kept, d_az, generator, words_all, d_el=d_el, strength=strength, views_tag=views_tag,
                        depression_guidance=guidance,
                    )))  # fmt: skip
        return results

    def view_variants(self, kept: Sequence[ChipRecord]) -> list[tuple[str, list[float], float]]:
        """The EOC-1 views an arm adds, as (views tag, d_az list, strength): one view per chip at
        ``d_az = 0``, plainly and (``strength``) started from the chip; with ``eoc1_views_per_chip`` N > 1
        the same with N views per chip, at ``d_az = 0`` and ``fill_offsets_deg`` of the kept chips' mean
        azimuth gap per class."""
        config = self.config
        strengths = [1.0] + ([] if config.strength is None else [config.strength])
        counts = [1] + ([] if config.eoc1_views_per_chip == 1 else [config.eoc1_views_per_chip])
        per_class = len(kept) / len({r.target_class for r in kept})
        variants = []
        for count in counts:
            d_az = [0.0] + fill_offsets_deg(360.0 / per_class, count - 1) if count > 1 else [0.0]
            variants += [("" if count == 1 else f"_views{count}", d_az, strength) for strength in strengths]
        return variants


def real_baseline(arm: str) -> str | None:
    """The real-only arm a generated arm adds views to: ``generated_k{K}...`` (the unseen-class variant too)
    -> ``real_k{K}``, ``generated_sector...`` -> ``real_sector``, ``eoc1_generated_{all,k{K}}...`` ->
    ``eoc1_real_{all,k{K}}``; None for a real arm."""
    match = re.match(r"(eoc1_)?generated_(k\d+|sector|all)", arm)
    return None if match is None else f"{match.group(1) or ''}real_{match.group(2)}"


def paired_gain(arm: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """Accuracy of `arm` minus `baseline`, seed by seed: both arms train their classifiers with the same
    seeds, so the difference removes the spread the seeds share. Per seed, mean and sample std (accuracy).

    Raises:
        ValueError: If the two arms share no seed.
    """
    base = {s["seed"]: s["test_accuracy"] for s in baseline["seeds"]}
    diffs = [s["test_accuracy"] - base[s["seed"]] for s in arm["seeds"] if s["seed"] in base]
    if not diffs:
        raise ValueError(f"arms {arm['arm']} and {baseline['arm']} share no classifier seed")
    values = np.asarray(diffs, dtype=np.float64)
    return {
        "against": baseline["arm"],
        "per_seed": diffs,
        "mean": float(values.mean()),
        "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
    }


def add_paired_gains(arms: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Adds ``gain_over_real`` to each generated arm (against its :func:`real_baseline`) and, to each arm
    whose same-azimuth control ran, ``gain_over_same_azimuth`` (what the requested pose adds), whose
    same-depression control (``..._d_el0``; for a ``..._depression{G}`` arm the unguided arm's) ran,
    ``gain_over_same_depression``; returns `arms`."""
    by_name = {arm["arm"]: arm for arm in arms}
    for arm in arms:
        baseline = real_baseline(arm["arm"])
        if baseline in by_name:
            arm["gain_over_real"] = paired_gain(arm, by_name[baseline])
        control = by_name.get(arm["arm"] + "_d_az0")
        if control is not None:
            arm["gain_over_same_azimuth"] = paired_gain(arm, control)
        # a depression-guided arm's control is the unguided one's (the guidance leaves d_el = 0 views as
        # they are)
        control = by_name.get(re.sub(r"_depression[0-9.e+-]+$", "", arm["arm"]) + "_d_el0")
        if control is not None:
            arm["gain_over_same_depression"] = paired_gain(arm, control)
    return arms


def format_table(summary: dict[str, Any]) -> str:
    """The arms as a Markdown table: accuracy (mean +- std over seeds, %), the paired gain over real-only
    (points), chips, times."""
    lines = [
        "| arm | real chips | generated views | test accuracy (%) | gain over real-only (points, paired) | "
        "seeds | generator CPU (min) | arm CPU (min) | arm wall (min) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for arm in summary["arms"]:
        generated = arm.get("n_generated", 0)
        gain = arm.get("gain_over_real")
        gain_text = "" if gain is None else f"{100 * gain['mean']:+.1f} +- {100 * gain['std']:.1f}"
        lines.append(
            f"| {arm['arm']} | {arm['n_train'] - generated} | {generated} | "
            f"{100 * arm['test_accuracy_mean']:.1f} +- {100 * arm['test_accuracy_std']:.1f} | {gain_text} | "
            f"{len(arm['seeds'])} | {arm.get('generator_cpu_s', 0.0) / 60:.1f} | "
            f"{arm['total_cpu_s'] / 60:.1f} | {arm['total_wall_s'] / 60:.1f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    defaults = BenchmarkConfig()
    comments = field_comments(BenchmarkConfig)  # each field's comment in the source, as its help
    for name, value in asdict(defaults).items():
        flag, words = f"--{name}", {"default": value, "help": comments.get(name)}
        if isinstance(value, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, **words)
        elif name == "seeds":
            parser.add_argument(flag, nargs="+", type=int, **words)
        elif name == "view_filters":
            parser.add_argument(flag, nargs="*", choices=VIEW_FILTERS, **words)
        elif isinstance(value, list):  # no value: no such arms
            parser.add_argument(flag, nargs="*", type=int, **words)
        elif name in ("rehearsal_data", "eoc1_data", "unseen_class"):
            parser.add_argument(flag, type=lambda s: None if s.lower() == "none" else s, **words)
        elif name == "speckle_looks":
            parser.add_argument(flag, type=lambda s: None if s.lower() == "none" else int(s), **words)
        elif name in ("strength", "heading_guidance", "depression_guidance"):
            parser.add_argument(flag, type=lambda s: None if s.lower() == "none" else float(s), **words)
        else:
            parser.add_argument(flag, type=type(value), **words)
    parser.add_argument("--quick", action="store_true", help=f"the reduced run: {QUICK}")
    args = vars(parser.parse_args(argv))
    if args.pop("quick"):
        args.update(QUICK)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(max(torch.get_num_threads(), 1))
    summary = Benchmark(BenchmarkConfig(**args)).run()
    print(format_table(summary))
    return summary


if __name__ == "__main__":
    main()
