"""The protocol's generators: a pipeline fine-tuned on an arm's kept chips, then its views of them
(:func:`build_generator`); where the views sit (:func:`fill_offsets_deg`) and how a variant's folder is
named (:func:`variant_suffix`)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from sar_zero123.augment_dataset import AugmentConfig, augment_dataset
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import ChipRecord, load_index
from sar_zero123.model.sampler import SamplerSettings
from sar_zero123.stages import FinetuneConfig, run_finetune

from .config import TEST_DEPRESSION_DEG, TRAIN_DEPRESSION_DEG, AugmentationBenefitConfig

__all__ = [
    "build_generator", "fill_offsets_deg", "generator_sampler", "timed", "variant_suffix",
    "write_generator_data",
]  # fmt: skip


def fill_offsets_deg(gap_deg: float, views_per_chip: int) -> list[float]:
    """Azimuth changes that place `views_per_chip` views evenly in the gaps around a kept chip.

    The views sit at ``j * gap / (views_per_chip + 1)`` for ``j = 1..views_per_chip`` after the chip, each
    generated from the nearer of the two kept chips around it: offsets past half the gap are taken
    backwards from the next chip, so ``|d_az| <= gap / 2``.
    """
    step = gap_deg / (views_per_chip + 1)
    offsets = [j * step for j in range(1, views_per_chip + 1)]
    return [o if o <= gap_deg / 2 else o - gap_deg for o in offsets]


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
        rows.append(ChipRecord(**{**asdict(record), "path": link, "depression_deg": TEST_DEPRESSION_DEG}))
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


def timed(function: Any, *args: Any, **kwargs: Any) -> tuple[Any, dict[str, float]]:
    """Calls `function` and returns its result with its wall and process CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = function(*args, **kwargs)
    return result, {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}


def generator_sampler(
    config: AugmentationBenefitConfig, strength: float = 1.0, heading_guidance: float = 0.0,
    depression_guidance: float = 0.0,
) -> SamplerSettings:
    """How a generator samples its views: the protocol's DDIM steps and guidance, then a variant's start
    (`strength`) and contrast guidance weights."""
    plain = SamplerSettings(num_inference_steps=config.num_inference_steps, scheduler="ddim",
                            guidance_scale=config.guidance_scale, strength=strength)  # fmt: skip
    return plain.with_contrasts(heading=heading_guidance, depression=depression_guidance)


def build_generator(
    config: AugmentationBenefitConfig,
    trained_on: Sequence[ChipRecord],
    sources: Sequence[ChipRecord],
    folder: Path,
    d_az: list[float],
    strength: float = 1.0,
    d_el: float = 0.0,
    heading_guidance: float = 0.0,
    views_tag: str = "",
    depression_guidance: float = 0.0,
) -> tuple[Path, dict[str, Any]]:
    """Fine-tunes the pipeline on `trained_on`, then generates `d_az` views (at depression change `d_el`)
    of each of `sources`; both resumable. With `strength` < 1, the views (in their own folder, from the
    same fine-tune) start from the source's noised latent
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
    suffix = variant_suffix(strength, same_azimuth=all(d == 0.0 for d in d_az), d_el=d_el,
                            heading_guidance=heading_guidance,
                            depression_guidance=depression_guidance) + views_tag  # fmt: skip
    views, key = folder / f"views{suffix}", f"generate{suffix}"
    if key not in times:
        _, times[key] = timed(augment_dataset, AugmentConfig(
            data=str(source_data), pipeline=str(folder / "finetune" / "pipeline"), out=str(views), d_az=d_az,
            d_el=[d_el], depressions_deg=[TRAIN_DEPRESSION_DEG], batch_size=16, seed=0,
            **asdict(generator_sampler(config, strength, heading_guidance, depression_guidance)),
        ))  # fmt: skip
        times[key]["views"] = len(load_index(views))
        write_json_atomic(times, timing_file)
    return views, {"finetune": times["finetune"], key: times[key]}


def variant_suffix(
    strength: float = 1.0,
    same_azimuth: bool = False,
    d_el: float = 0.0,
    heading_guidance: float = 0.0,
    view_filter: str | None = None,
    filter_classifier: Path | None = None,
    depression_guidance: float = 0.0,
) -> str:
    """``_strength<S>``, ``_heading<H>``, ``_depression<G>``, ``_d_az0``, ``_d_el<D>`` and
    ``_<filter>`` for views generated or kept other than plainly (``""``)."""
    return (
        ("" if view_filter is None else f"_{view_filter}")
        + ("" if strength == 1.0 else f"_strength{strength:g}")
        + ("" if heading_guidance == 0.0 else f"_heading{heading_guidance:g}")
        + ("" if depression_guidance == 0.0 else f"_depression{depression_guidance:g}")
        + ("_d_az0" if same_azimuth else "")
        + ("" if d_el == 0.0 else f"_d_el{d_el:g}")
    )
