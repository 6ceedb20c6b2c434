"""The evaluators stage: the models that score generated views (Table III, Table IV), in a run folder.

Writes ``classifier/`` (ResNet-18 from scratch), ``regressor/`` (ResNet-18 + MLP 256-256, azimuth / 2pi),
optionally ``probes/<name>/`` (frozen SimCLR encoder + MLP, Table IV) and ``depression_regressor/``
(depression / 90 deg), and ``metrics.json``. They train on the ``extended`` train split, every class: for
MSTAR-OOD the classifier must still know the held-out class, as in the paper. The depression regressor
trains on ``depression_data`` (the protocols' splits hold two depressions) but a held-out share.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from accelerate.utils import set_seed

from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, load_index, prepare_splits
from sar_zero123.data.selection import hold_out, subsample
from sar_zero123.domain import MAX_IMAGE_SIZE
from sar_zero123.encoder import SAREncoder, SAREncoderConfig, resolve_encoder_dir
from sar_zero123.evaluation.evaluators import (
    CLASSIFIER_DIR,
    DEPRESSION_REGRESSOR_DIR,
    PROBES_DIR,
    REGRESSOR_DIR,
    AzimuthRegressor,
    DepressionRegressor,
    SARClassifier,
)
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.training.evaluators import EvaluatorTraining, train_model

logger = logging.getLogger(__name__)

__all__ = [
    "EVALUATORS_MAY_DIFFER",
    "MAX_EPOCHS",
    "TrainEvaluatorsConfig",
    "model_identity",
    "run_evaluators",
]

Evaluator = SARClassifier | AzimuthRegressor | DepressionRegressor

MAX_EPOCHS = 10_000
MAX_BATCH_SIZE = 4096
#: The share of ``depression_data``'s chips held out (seeded) for the depression regressor's test error.
DEPRESSION_TEST_FRACTION = 0.2
ADAMW_WEIGHT_DECAY = 5e-4
CHECKPOINTING_EPOCHS = 5  # each model's resumable checkpoint interval
#: Settings that never change what the folder holds.
EVALUATORS_MAY_DIFFER = (
    "resume", "restart", "resume_from_checkpoint", "num_workers", "output_dir",
)  # fmt: skip


@dataclass
class TrainEvaluatorsConfig:
    """Train the scratch ResNet-18 classifier, azimuth regressor (SimCLR probes, depression regressor)."""

    ADVANCED_FIELDS = (
        "cifar_stem", "depths", "hidden_sizes", "mlp_hidden_sizes", "probe_epochs", "max_train_chips",
        "resume_from_checkpoint", "num_workers", "mixed_precision",
    )  # fmt: skip
    REMOVED_FIELDS = {
        "depression_test_fraction": RemovedField(
            0.2, f"{DEPRESSION_TEST_FRACTION} of depression_data's chips are held out for its test error"
        ),
        "work_dir": RemovedField(None, "the simulated dataset is cached in output_dir"),
        "chip_crop_size": RemovedField(None, "chips larger than image_size are centre-cropped to it (their "
                                       "pixel spacing kept)"),
        "weight_decay": RemovedField(5e-4, f"AdamW's weight decay is {ADAMW_WEIGHT_DECAY:g}"),
        "checkpointing_epochs": RemovedField(
            5, f"a resumable checkpoint is saved every {CHECKPOINTING_EPOCHS} epochs"
        ),
    }  # fmt: skip

    output_dir: str = "runs/evaluators"  # folder for classifier/, regressor/, probes/, metrics.json
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
    depression_data: str | None = None  # chip folder (index.csv) at many depressions: depression_regressor/
    scaling: str = "unit"  # decibel bounds: "unit" (8-bit images, simulator), "mstar_raw" or "fit"
    image_size: int = 128  # chip side in pixels fed to the evaluators
    cifar_stem: bool = True  # 3x3 stride-1 stem without max-pool (reference setting for SAR chips)
    depths: tuple[int, ...] = (2, 2, 2, 2)  # ResNet-18 blocks per stage
    hidden_sizes: tuple[int, ...] = (64, 128, 256, 512)  # ResNet-18 stage widths
    mlp_hidden_sizes: tuple[int, ...] = (256, 256)  # azimuth MLP widths (paper: 256-256)
    epochs: int = 30  # passes over the train split per scratch model
    probe_epochs: int = 30  # passes for the MLP heads of the SimCLR probes
    train_batch_size: int = 64  # chips per process per step (also the scoring batch)
    learning_rate: float = 1e-3  # AdamW peak learning rate (cosine decay to 0)
    simclr_encoders: list[str] = field(default_factory=list)  # SimCLR encoder folders to probe (Table IV)
    max_train_chips: int | None = None  # subsample the train split (quick runs); None uses all
    resume_from_checkpoint: str | None = "latest"  # with resume: "latest", a checkpoint folder, or None
    num_workers: int = 0  # DataLoader worker processes
    mixed_precision: str = "no"  # accelerate mixed precision: "no", "fp16" or "bf16"
    seed: int = 0  # seeds the split, the initialisation and the shuffling
    resume: bool = False  # an unfinished run with the same settings is continued; a finished one is returned
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over

    def __post_init__(self) -> None:
        if self.scaling not in ("unit", "mstar_raw", "fit"):
            raise ValueError(f"scaling must be 'unit', 'mstar_raw' or 'fit', got {self.scaling!r}")
        counts = ("image_size", "epochs", "train_batch_size", "probe_epochs")
        check_minimum(self, *counts, minimum=1)
        for name, bound in (("image_size", MAX_IMAGE_SIZE), ("epochs", MAX_EPOCHS),
                            ("probe_epochs", MAX_EPOCHS), ("train_batch_size", MAX_BATCH_SIZE)):  # fmt: skip
            if getattr(self, name) > bound:
                raise ValueError(f"{name} must be <= {bound}, got {getattr(self, name)}")
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        check_minimum(self, "num_workers", minimum=0)
        check_minimum(self, "max_train_chips", minimum=1, optional=True)
        if len(self.mlp_hidden_sizes) == 0 or min(self.mlp_hidden_sizes) < 1:
            raise ValueError(f"mlp_hidden_sizes must be positive widths, got {self.mlp_hidden_sizes}")
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")
        names = [Path(p).name for p in self.simclr_encoders]
        if len(set(names)) != len(names):
            raise ValueError(f"simclr_encoders must have distinct folder names (probe names), got {names}")
        if self.resume and self.restart:
            raise ValueError("resume and restart: choose one (continue this run, or move it aside)")

    @property
    def training(self) -> EvaluatorTraining:
        """The optimisation settings every model of the stage shares."""
        return EvaluatorTraining(
            batch_size=self.train_batch_size,
            learning_rate=self.learning_rate,
            weight_decay=ADAMW_WEIGHT_DECAY,
            checkpointing_epochs=CHECKPOINTING_EPOCHS,
            resume_from_checkpoint=self.resume_from_checkpoint,
            num_workers=self.num_workers,
            mixed_precision=self.mixed_precision,
        )


def model_identity(path: str | os.PathLike, name: str) -> dict[str, Any]:
    """What a model folder held when a stage read it (files' names, sizes and modification times), so that a
    model retrained in place is not taken for the one a finished run scored.

    Raises:
        FileNotFoundError: If ``path`` does not exist (naming the setting ``name``).
    """
    root = Path(path)
    if not root.exists():
        raise FileNotFoundError(f"{name}: {str(root)!r} does not exist")
    files = sorted(p for p in root.rglob("*") if p.is_file()) if root.is_dir() else [root]
    digest = hashlib.sha256()
    for file in files:
        stat = file.stat()
        relative = file.relative_to(root).as_posix() if root.is_dir() else file.name
        digest.update(f"{relative}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return {"path": str(root.resolve()), "files": len(files), "files_sha256": digest.hexdigest()}


def run_evaluators(config: TrainEvaluatorsConfig) -> Path:
    """Train the classifier, the azimuth regressor, the SimCLR probes and the depression regressor into
    ``config.output_dir``; returns the folder.

    Raises:
        ValueError: For a folder holding other work; if ``depression_data`` holds fewer than two depressions.
        FileNotFoundError: If ``data``, ``depression_data`` or a SimCLR encoder folder does not exist.
    """
    timer = StageTimer()
    # 1. inputs checked, then the run-folder rule, before any work
    depression_records = _depression_records(config.depression_data)
    inputs: dict[str, Any] = {"data": data_identity(config.data)}
    if config.depression_data is not None:
        inputs["depression_data"] = data_identity(config.depression_data)
    if config.simclr_encoders:
        inputs["simclr_encoders"] = [
            model_identity(path, f"simclr_encoders[{i}]") for i, path in enumerate(config.simclr_encoders)
        ]
    folder = open_stage_folder(
        config.output_dir, "evaluators", config, data=inputs, resume=config.resume, restart=config.restart,
        may_differ=EVALUATORS_MAY_DIFFER, resume_hint="--resume",
    )  # fmt: skip
    if folder.finished:
        logger.info("%s already holds these evaluators", folder.path)
        return folder.path
    output_dir = folder.path

    # 2. data (the extended train split: every class, the OOD class included) and the SimCLR encoders
    with withdrawn_if_setup_fails(folder):
        splits = prepare_splits(config.data, "extended", output_dir, seed=config.seed)
        train_records = subsample(splits["train"], config.max_train_chips, config.seed)
        scaling = DecibelScaling.from_choice(config.scaling, train_records)
        class_names = sorted({r.target_class for r in splits["train"] + splits["test"]})
        train_set, test_set = (
            _chips(records, config, scaling, class_names) for records in (train_records, splits["test"])
        )
        encoders = _probe_encoders(config)
    save_config(config, output_dir)
    logger.info(
        "evaluators: %d train / %d test chips, classes %s", len(train_set), len(test_set), class_names
    )
    encoder_config = SAREncoderConfig(
        image_size=config.image_size,
        in_channels=1,
        cifar_stem=config.cifar_stem,
        depths=config.depths,
        hidden_sizes=config.hidden_sizes,
    )

    # 3. scratch classifier and regressor, Table IV probes, depression regressor
    results = _train_scratch_models(
        config, encoder_config, scaling, class_names, train_set, test_set, output_dir
    )
    results.update(_train_probes(config, encoders, scaling, class_names, train_set, test_set, output_dir))
    summary: dict[str, Any] = {"trained_on": "extended/train (all classes)"}
    if depression_records is not None:
        seed = config.seed + 2 + len(config.simclr_encoders)
        results["depression_regressor"] = _train_depression_regressor(
            config, depression_records, encoder_config, scaling, output_dir / DEPRESSION_REGRESSOR_DIR, seed
        )
        summary["depression_regressor_trained_on"] = (
            f"{config.depression_data} except a held-out {DEPRESSION_TEST_FRACTION:g} of its chips"
        )

    # 4. metrics.json, the last output
    write_json_atomic(
        {"class_names": class_names, "scaling": scaling.to_dict(), **summary, "models": results},
        output_dir / "metrics.json",
    )
    finish_run(folder, ["metrics.json"], seconds=timer.seconds, results={"models": sorted(results)})
    return output_dir


def _depression_records(depression_data: str | None) -> list[ChipRecord] | None:
    """The chips of ``depression_data`` (``None`` without one), checked to span several depressions.

    Raises:
        ValueError: If the folder's chips sit at fewer than two depressions.
    """
    if depression_data is None:
        return None
    records = load_index(depression_data)
    depressions = sorted({round(r.depression_deg, 3) for r in records})
    if len(depressions) < 2:
        raise ValueError(
            f"depression_data {depression_data} holds chips at depressions {depressions} deg; "
            "a depression regressor needs at least two"
        )
    return records


def _chips(
    records: list[ChipRecord], config: TrainEvaluatorsConfig, scaling: DecibelScaling, class_names: list[str]
) -> ChipDataset:
    """The evaluators' view of some chips: ``image_size`` px, ``scaling``."""
    return ChipDataset(records, size=config.image_size, scaling=scaling, class_names=class_names)


def _train_scratch_models(
    config: TrainEvaluatorsConfig,
    encoder_config: SAREncoderConfig,
    scaling: DecibelScaling,
    class_names: list[str],
    train_set: ChipDataset,
    test_set: ChipDataset,
    output_dir: Path,
) -> dict[str, dict[str, float]]:
    """The classifier (seed) and the azimuth regressor (seed + 1), from scratch."""
    set_seed(config.seed)
    classifier = SARClassifier(encoder_config, class_names, scaling)
    results = {
        "classifier": train_model(classifier, train_set, test_set, output_dir / CLASSIFIER_DIR,
                                  training=config.training, epochs=config.epochs, seed=config.seed)
    }  # fmt: skip
    set_seed(config.seed + 1)
    regressor = AzimuthRegressor(encoder_config, class_names, scaling, config.mlp_hidden_sizes)
    results["regressor"] = train_model(
        regressor, train_set, test_set, output_dir / REGRESSOR_DIR,
        training=config.training, epochs=config.epochs, seed=config.seed + 1,
    )  # fmt: skip
    return results


def _probe_encoders(config: TrainEvaluatorsConfig) -> dict[str, SAREncoder]:
    """The SimCLR encoders to probe, by probe name (their folder names), checked before any training.

    Raises:
        ValueError: If an encoder takes another chip size than ``config.image_size``.
    """
    encoders = {}
    for index, path in enumerate(config.simclr_encoders):
        encoder = SAREncoder.from_pretrained(resolve_encoder_dir(path, field="simclr_encoders"))
        if encoder.config.image_size != config.image_size:
            raise ValueError(
                f"simclr_encoders[{index}] {path} takes {encoder.config.image_size} px chips but "
                f"image_size is {config.image_size}"
            )
        encoders[Path(path).name] = encoder
    return encoders


def _train_probes(
    config: TrainEvaluatorsConfig,
    encoders: dict[str, SAREncoder],
    scaling: DecibelScaling,
    class_names: list[str],
    train_set: ChipDataset,
    test_set: ChipDataset,
    output_dir: Path,
) -> dict[str, dict[str, float]]:
    """Table IV probes: each SimCLR encoder frozen under a trained MLP head, keyed ``probe:<folder name>``."""
    results = {}
    for index, (name, encoder) in enumerate(encoders.items()):
        set_seed(config.seed + 2 + index)
        probe = AzimuthRegressor(encoder.config, class_names, scaling, config.mlp_hidden_sizes)
        probe.encoder.load_state_dict(encoder.state_dict())
        probe.encoder.requires_grad_(False)
        results[f"probe:{name}"] = train_model(
            probe, train_set, test_set, output_dir / PROBES_DIR / name,
            training=config.training, epochs=config.probe_epochs, seed=config.seed,
        )  # fmt: skip
    return results


def _train_depression_regressor(
    config: TrainEvaluatorsConfig,
    records: list[ChipRecord],
    encoder_config: SAREncoderConfig,
    scaling: DecibelScaling,
    stage_dir: Path,
    seed: int,
) -> dict[str, float]:
    """The depression regressor, trained on ``records`` but a held-out share (the evaluators' scaling)."""
    depressions = sorted({round(r.depression_deg, 3) for r in records})
    train_records, test_records = hold_out(records, DEPRESSION_TEST_FRACTION, seed)
    train_records = subsample(train_records, config.max_train_chips, seed)
    class_names = sorted({r.target_class for r in records})
    train_set, test_set = (
        _chips(part, config, scaling, class_names) for part in (train_records, test_records)
    )
    logger.info(
        "depression regressor: %d train / %d test chips at depressions %s deg",
        len(train_set), len(test_set), depressions,
    )  # fmt: skip
    set_seed(seed)
    model = DepressionRegressor(encoder_config, class_names, scaling, config.mlp_hidden_sizes)
    return train_model(model, train_set, test_set, stage_dir, training=config.training, epochs=config.epochs,
                       seed=seed)  # fmt: skip
