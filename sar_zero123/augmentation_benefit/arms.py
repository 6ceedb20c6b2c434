"""The sparse-azimuth protocol's arms: classifiers trained on few real chips, with and without the views
a generator made of them (:class:`AugmentationBenefit`), and MSTAR EOC-1's depression transfer as arms of
the same kind (:class:`DepressionTransfer`)."""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import re
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, load_index, signed_to_unit
from sar_zero123.data.selection import at_depression, cv_folds, keep_evenly_spaced, keep_sector
from sar_zero123.evaluation.evaluators import SARClassifier, load_evaluator
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.training.few_view_classifier import train_classifier

from .config import (
    RESULT_FILE,
    TEST_DEPRESSION_DEG,
    TRAIN_DEPRESSION_DEG,
    VIEW_FILTERS,
    AugmentationBenefitConfig,
    check_settings,
)
from .gains import add_paired_gains, real_baseline, seed_summary
from .generators import build_generator, fill_offsets_deg, timed, variant_suffix

__all__ = [
    "AugmentationBenefit",
    "DepressionTransfer",
    "accuracy",
    "load_images",
    "predict",
    "vae_round_trip",
]

logger = logging.getLogger("augmentation_benefit")


def load_images(
    records: Sequence[ChipRecord], class_names: list[str], scaling: DecibelScaling, size: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The chips as normalised dB centre crops and their labels. Shape: (N, 1, size, size), (N,)."""
    dataset = ChipDataset(list(records), size=size, scaling=scaling, class_names=class_names)
    items = [dataset[i] for i in range(len(dataset))]
    images = torch.stack([item["image"] for item in items]).float()
    labels = torch.tensor([item["label"] for item in items], dtype=torch.long)
    return images, labels


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


class AugmentationBenefit:
    """The chips in memory once, and the arms that train classifiers on subsets of them."""

    def __init__(self, config: AugmentationBenefitConfig) -> None:
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
        generator_records: Sequence[ChipRecord] | None = None, strength: float = 1.0, d_el: float = 0.0,
        heading_guidance: float = 0.0, view_filter: str | None = None, filter_classifier: Path | None = None,
        views_tag: str = "", depression_guidance: float = 0.0,
    ) -> Any:  # fmt: skip
        def build(arm_dir: Path) -> dict[str, Any]:
            trained_on = kept if generator_records is None else generator_records
            views_dir, times = build_generator(
                self.config,
                trained_on,
                kept,
                generator_dir,
                d_az,
                strength,
                d_el,
                heading_guidance,
                views_tag,
                depression_guidance,
            )
            generated = load_index(views_dir)
            views = self.filter_views(generated, view_filter, filter_classifier)
            result = self.classifiers(list(kept) + views, arm_dir)
            if view_filter is not None:
                result.update(view_filter=view_filter, n_generated_before_filter=len(generated))
            result.update(
                description=description,
                n_real=len(kept),
                n_generated=len(views),
                d_az_deg=d_az,
                d_el_deg=d_el,
                generator=str(generator_dir),
                generator_times=times,
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

        ``strength`` starts each view from its kept chip's noised latent,
        ``same_azimuth_control`` makes the plain views and the strength views again at ``d_az = 0`` (what the
        requested pose adds), ``heading_guidance`` samples the plain views with that heading guidance.
        """
        config = self.config
        variants: list[tuple[dict[str, Any], bool, str]] = []
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
            self.run_arm(
                f"{name}{variant_suffix(**options, same_azimuth=same)}",
                self.generated_arm(
                    kept,
                    [0.0] * len(d_az) if same else d_az,
                    generator_dir,
                    f"{description}, {words}",
                    generator_records=generator_records,
                    **options,
                ),
            )  # fmt: skip
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
            "benchmark": "augmentation_benefit",
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


class DepressionTransfer(AugmentationBenefit):
    """MSTAR EOC-1's arms: train at 17 deg on the objects of the test chips, test at their depression.

    The training chips are the parent benchmark's 17 deg chips of the (class, serial) pairs the test chips
    show; the classes are those of the test chips. Generated views change the depression by
    ``d_el = test depression - 17 deg`` (the control: ``d_el = 0``), one per chip at ``d_az = 0``.
    """

    CEILING = "eoc1_ceiling_cv"

    def __init__(self, parent: AugmentationBenefit, test_records: Sequence[ChipRecord]) -> None:
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
                    (self.d_el, "", 0.0),
                    (0.0, "_d_el0", 0.0),
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
