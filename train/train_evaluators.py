"""Train the evaluator models that score generated views (Table III, Table IV).

    python train/train_evaluators.py --output_dir runs/evaluators --data /path/to/mstar

writes `classifier/` (ResNet-18 from scratch, linear head), `regressor/` (ResNet-18 + MLP 256-256, sigmoid,
azimuth / 2pi), optionally `probes/<name>/` (frozen SimCLR encoder + MLP, Table IV) and
`depression_regressor/` (ResNet-18 + MLP, sigmoid, depression / 90 deg; with `--depression_data`), and
`metrics.json` with test accuracy, circular test azimuth error and test depression error.

Evaluators always train on the train split of the `extended` protocol, i.e. real chips of ALL classes at
17 deg: for MSTAR-OOD the classifier must still know the held-out class (T72), as in the paper. They exist
only to score generated images. The depression regressor needs chips at many depressions, which the
protocols' splits (17 and 15 deg) lack: it trains on every chip of `--depression_data` except a seeded,
held-out `--depression_test_fraction` of them, which give its test error.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from accelerate.utils import set_seed
from torch.utils.data import DataLoader
from tqdm.auto import tqdm

from sar_zero123.config import check_minimum, parse_config, save_config, write_json_atomic
from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, load_index, prepare_splits
from sar_zero123.encoder import SAREncoder, SAREncoderConfig, resolve_encoder_dir
from sar_zero123.evaluators import (
    CLASSIFIER_DIR,
    DEPRESSION_REGRESSOR_DIR,
    EVALUATOR_CONFIG_NAME,
    PROBES_DIR,
    REGRESSOR_DIR,
    AzimuthRegressor,
    DepressionRegressor,
    SARClassifier,
    azimuth_regression_loss,
    depression_regression_loss,
    load_evaluator,
)
from sar_zero123.metrics import azimuth_error_deg, classification_accuracy
from sar_zero123.run_state import load_checkpoint, resolve_resume_checkpoint, save_checkpoint
from sar_zero123.runs import start_run

logger = logging.getLogger(__name__)

Evaluator = SARClassifier | AzimuthRegressor | DepressionRegressor


@dataclass
class TrainEvaluatorsConfig:
    """Train the scratch ResNet-18 classifier, azimuth regressor (SimCLR probes, depression regressor)."""

    output_dir: str = "runs/evaluators"  # folder for classifier/, regressor/, probes/, metrics.json
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
    depression_data: str | None = None  # chip folder (index.csv) at many depressions: depression_regressor/
    depression_test_fraction: float = 0.2  # share of depression_data's chips held out for its test error
    work_dir: str | None = None  # where the simulated dataset is cached (default: output_dir)
    scaling: str = "unit"  # decibel bounds: "unit" (8-bit images, simulator), "mstar_raw" or "fit"
    image_size: int = 128  # chip side in pixels fed to the evaluators
    chip_crop_size: int | None = None  # centre crop before resizing (None keeps the pixel spacing)
    cifar_stem: bool = True  # 3x3 stride-1 stem without max-pool (reference setting for SAR chips)
    depths: tuple[int, ...] = (2, 2, 2, 2)  # ResNet-18 blocks per stage
    hidden_sizes: tuple[int, ...] = (64, 128, 256, 512)  # ResNet-18 stage widths
    mlp_hidden_sizes: tuple[int, ...] = (256, 256)  # azimuth MLP widths (paper: 256-256)
    epochs: int = 30  # passes over the train split per scratch model
    probe_epochs: int = 30  # passes for the MLP heads of the SimCLR probes
    train_batch_size: int = 64  # chips per process per step (also the scoring batch)
    learning_rate: float = 1e-3  # AdamW peak learning rate (cosine decay to 0)
    weight_decay: float = 5e-4  # AdamW weight decay
    simclr_encoders: list[str] = field(default_factory=list)  # SimCLR encoder folders to probe (Table IV)
    max_train_chips: int | None = None  # subsample the train split (quick runs); None uses all
    checkpointing_epochs: int = 5  # save a resumable checkpoint every this many epochs
    resume_from_checkpoint: str | None = "latest"  # "latest", a checkpoint folder, or None
    num_workers: int = 0  # DataLoader worker processes
    mixed_precision: str = "no"  # accelerate mixed precision: "no", "fp16" or "bf16"
    seed: int = 0  # seeds the split, the initialisation and the shuffling

    def __post_init__(self) -> None:
        if self.scaling not in ("unit", "mstar_raw", "fit"):
            raise ValueError(f"scaling must be 'unit', 'mstar_raw' or 'fit', got {self.scaling!r}")
        counts = ("image_size", "epochs", "train_batch_size", "checkpointing_epochs", "probe_epochs")
        check_minimum(self, *counts, minimum=1)
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        check_minimum(self, "weight_decay", minimum=0)
        check_minimum(self, "max_train_chips", minimum=1, optional=True)
        if not 0.0 < self.depression_test_fraction < 1.0:
            raise ValueError(
                f"depression_test_fraction must lie in (0, 1), got {self.depression_test_fraction}"
            )
        if len(self.mlp_hidden_sizes) == 0 or min(self.mlp_hidden_sizes) < 1:
            raise ValueError(f"mlp_hidden_sizes must be positive widths, got {self.mlp_hidden_sizes}")
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")
        names = [Path(p).name for p in self.simclr_encoders]
        if len(set(names)) != len(names):
            raise ValueError(f"simclr_encoders must have distinct folder names (probe names), got {names}")


def _loader(dataset: ChipDataset, config: TrainEvaluatorsConfig, shuffle: bool, seed: int) -> DataLoader:
    generator = torch.Generator().manual_seed(seed)
    return DataLoader(
        dataset,
        batch_size=config.train_batch_size,
        shuffle=shuffle,
        num_workers=config.num_workers,
        generator=generator,
        drop_last=False,
    )


def training_loss(
    model: torch.nn.Module, evaluator: Evaluator, batch: dict[str, torch.Tensor]
) -> torch.Tensor:
    """Mean training loss of a batch: cross-entropy, circular azimuth or depression squared error.

    `model` is what runs the forward pass (maybe a data-parallel wrapper), `evaluator` the bare model whose
    kind picks the loss.
    """
    outputs = model(batch["image"])
    if isinstance(evaluator, SARClassifier):
        return F.cross_entropy(outputs, batch["label"].long())
    if isinstance(evaluator, DepressionRegressor):
        return depression_regression_loss(outputs, batch["depression_deg"].float()).mean()
    return azimuth_regression_loss(outputs, batch["azimuth_deg"].float()).mean()


@torch.no_grad()
def score_on_split(model: Evaluator, loader: DataLoader, device: torch.device) -> dict[str, float]:
    """Test accuracy (classifier), mean/median circular azimuth error (azimuth regressor) or mean/median
    absolute depression error (depression regressor) on a split."""
    model.eval()
    outputs, truths = [], []
    for batch in loader:
        images = batch["image"].to(device)
        if isinstance(model, SARClassifier):
            outputs.append(model(images).argmax(dim=1).cpu())
            truths.append(batch["label"])
        elif isinstance(model, DepressionRegressor):
            outputs.append(model.predict_depression_deg(images).cpu())
            truths.append(batch["depression_deg"].float())
        else:
            outputs.append(model.predict_azimuth_deg(images).cpu())
            truths.append(batch["azimuth_deg"].float())
    predictions, truth = torch.cat(outputs), torch.cat(truths)
    if isinstance(model, SARClassifier):
        return {"test_accuracy": classification_accuracy(predictions, truth), "n_test": len(predictions)}
    if isinstance(model, DepressionRegressor):
        name, errors = "depression", (predictions - truth).abs()
    else:
        name, errors = "azimuth", azimuth_error_deg(predictions, truth)
    return {
        f"test_{name}_error_deg": errors.mean().item(),
        f"test_{name}_error_median_deg": errors.median().item(),
        "n_test": len(predictions),
    }


def train_model(
    model: Evaluator,
    train_set: ChipDataset,
    test_set: ChipDataset,
    stage_dir: Path,
    config: TrainEvaluatorsConfig,
    epochs: int,
    seed: int,
) -> dict[str, float]:
    """Trains one evaluator (its trainable parameters), saves it to `stage_dir` and returns test metrics.

    A finished stage (its `evaluator.json` exists) is loaded instead of retrained; an interrupted one
    resumes from its latest epoch checkpoint.
    """
    if (stage_dir / EVALUATOR_CONFIG_NAME).is_file():
        logger.info("%s already trained; skipping", stage_dir)
        return load_evaluator(stage_dir).metrics
    # the loaders keep their own seeded generators: a stage resumes at epoch boundaries only
    accelerator = start_run(None, seed=seed, mixed_precision=config.mixed_precision, seedable_sampler=False)
    parameters = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(parameters, lr=config.learning_rate, weight_decay=config.weight_decay)
    train_loader = _loader(train_set, config, shuffle=True, seed=seed)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs * len(train_loader))
    model, optimizer, train_loader, scheduler = accelerator.prepare(model, optimizer, train_loader, scheduler)
    checkpoint_dir = stage_dir / "checkpoints"
    start_epoch = 0
    resume = resolve_resume_checkpoint(checkpoint_dir, config.resume_from_checkpoint)
    if resume is not None:
        start_epoch = int(load_checkpoint(accelerator, resume)["epoch"])
        logger.info("resumed %s at epoch %d", stage_dir.name, start_epoch)
    unwrapped = accelerator.unwrap_model(model)
    frozen_encoder = not any(p.requires_grad for p in unwrapped.encoder.parameters())
    for epoch in range(start_epoch, epochs):
        model.train()
        if frozen_encoder:
            unwrapped.encoder.eval()  # probes: frozen BatchNorm statistics of the SimCLR encoder
        total, count = 0.0, 0
        for batch in tqdm(train_loader, desc=f"{stage_dir.name} epoch {epoch + 1}/{epochs}", leave=False):
            loss = training_loss(model, unwrapped, batch)
            optimizer.zero_grad(set_to_none=True)
            accelerator.backward(loss)
            optimizer.step()
            scheduler.step()
            total += loss.item() * len(batch["image"])
            count += len(batch["image"])
        logger.info("%s epoch %d/%d: train loss %.4f", stage_dir.name, epoch + 1, epochs, total / count)
        if (epoch + 1) % config.checkpointing_epochs == 0 and epoch + 1 < epochs:
            save_checkpoint(
                accelerator, checkpoint_dir, epoch + 1, total_limit=1, extra_state={"epoch": epoch + 1}
            )
    metrics = score_on_split(unwrapped, _loader(test_set, config, False, seed), accelerator.device)
    metrics["n_train"] = len(train_set)
    unwrapped.metrics = metrics
    unwrapped.save_pretrained(stage_dir)
    logger.info("%s: %s", stage_dir.name, json.dumps(metrics))
    return metrics


def subsample(records: list[ChipRecord], max_chips: int | None, seed: int) -> list[ChipRecord]:
    """At most `max_chips` of the records (a seeded draw, in record order); all when `max_chips` is None."""
    if max_chips is None or len(records) <= max_chips:
        return records
    keep = torch.randperm(len(records), generator=torch.Generator().manual_seed(seed))
    return [records[i] for i in sorted(keep[:max_chips].tolist())]


def hold_out(
    records: list[ChipRecord], fraction: float, seed: int
) -> tuple[list[ChipRecord], list[ChipRecord]]:
    """Splits the records into `(train, test)` with `round(fraction * n)` (at least 1) seeded test chips.

    Raises:
        ValueError: If fewer than two records are given.
    """
    if len(records) < 2:
        raise ValueError(f"a train/test split needs at least 2 chips, got {len(records)}")
    count = min(max(1, round(fraction * len(records))), len(records) - 1)
    order = torch.randperm(len(records), generator=torch.Generator().manual_seed(seed)).tolist()
    test = set(order[:count])
    train = [record for i, record in enumerate(records) if i not in test]
    return train, [records[i] for i in sorted(test)]


def chip_dataset(
    records: list[ChipRecord], config: TrainEvaluatorsConfig, scaling: DecibelScaling, class_names: list[str]
) -> ChipDataset:
    """The evaluators' view of some chips: `config.image_size` px, `config.chip_crop_size` crop, `scaling`."""
    return ChipDataset(
        records,
        size=config.image_size,
        scaling=scaling,
        class_names=class_names,
        crop_size=config.chip_crop_size,
    )


def train_depression_regressor(
    config: TrainEvaluatorsConfig,
    encoder_config: SAREncoderConfig,
    scaling: DecibelScaling,
    stage_dir: Path,
    seed: int,
) -> dict[str, float]:
    """Trains the depression regressor on `config.depression_data` (all chips but a held-out share).

    The chips are normalised with the other evaluators' `scaling`: the regressor scores the same views.

    Raises:
        ValueError: If the folder's chips sit at fewer than two depressions.
    """
    records = load_index(config.depression_data)
    depressions = sorted({round(r.depression_deg, 3) for r in records})
    if len(depressions) < 2:
        raise ValueError(
            f"depression_data {config.depression_data} holds chips at depressions {depressions} deg; "
            "a depression regressor needs at least two"
        )
    train_records, test_records = hold_out(records, config.depression_test_fraction, seed)
    train_records = subsample(train_records, config.max_train_chips, seed)
    class_names = sorted({r.target_class for r in records})
    train_set, test_set = (
        chip_dataset(part, config, scaling, class_names) for part in (train_records, test_records)
    )
    logger.info(
        "depression regressor: %d train / %d test chips at depressions %s deg",
        len(train_set), len(test_set), depressions,
    )  # fmt: skip
    set_seed(seed)
    model = DepressionRegressor(encoder_config, class_names, scaling, config.mlp_hidden_sizes)
    return train_model(model, train_set, test_set, stage_dir, config, config.epochs, seed)


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    """Trains classifier, regressor, probes and depression regressor; returns `{name: test metrics}`."""
    config = parse_config(TrainEvaluatorsConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    output_dir = Path(config.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, output_dir)

    # 1. data: the extended protocol's train split holds every class (the OOD class included).
    work_dir = Path(config.work_dir) if config.work_dir is not None else output_dir
    splits = prepare_splits(config.data, "extended", work_dir, seed=config.seed)
    train_records = subsample(splits["train"], config.max_train_chips, config.seed)
    scaling = DecibelScaling.from_choice(config.scaling, train_records)
    class_names = sorted({r.target_class for r in splits["train"] + splits["test"]})
    train_set = chip_dataset(train_records, config, scaling, class_names)
    test_set = chip_dataset(splits["test"], config, scaling, class_names)
    logger.info(
        "evaluators: %d train / %d test chips, classes %s", len(train_set), len(test_set), class_names
    )

    # 2. scratch classifier and regressor.
    encoder_config = SAREncoderConfig(
        image_size=config.image_size,
        in_channels=1,
        cifar_stem=config.cifar_stem,
        depths=config.depths,
        hidden_sizes=config.hidden_sizes,
    )
    results: dict[str, dict[str, float]] = {}
    set_seed(config.seed)
    classifier = SARClassifier(encoder_config, class_names, scaling)
    results["classifier"] = train_model(
        classifier, train_set, test_set, output_dir / CLASSIFIER_DIR, config, config.epochs, config.seed
    )
    set_seed(config.seed + 1)
    regressor = AzimuthRegressor(encoder_config, class_names, scaling, config.mlp_hidden_sizes)
    results["regressor"] = train_model(
        regressor, train_set, test_set, output_dir / REGRESSOR_DIR, config, config.epochs, config.seed + 1
    )

    # 3. Table IV probes: frozen SimCLR encoder, trained MLP head.
    for index, path in enumerate(config.simclr_encoders):
        encoder = SAREncoder.from_pretrained(resolve_encoder_dir(path, field="simclr_encoders"))
        if encoder.config.image_size != config.image_size:
            raise ValueError(
                f"simclr_encoders[{index}] {path} takes {encoder.config.image_size} px chips but "
                f"image_size is {config.image_size}"
            )
        set_seed(config.seed + 2 + index)
        probe = AzimuthRegressor(encoder.config, class_names, scaling, config.mlp_hidden_sizes)
        probe.encoder.load_state_dict(encoder.state_dict())
        probe.encoder.requires_grad_(False)
        name = Path(path).name
        results[f"probe:{name}"] = train_model(
            probe,
            train_set,
            test_set,
            output_dir / PROBES_DIR / name,
            config,
            config.probe_epochs,
            config.seed,
        )

    # 4. depression regressor, on chips at many depressions (the splits above hold 17 and 15 deg only).
    summary: dict[str, object] = {"trained_on": "extended/train (all classes)"}
    if config.depression_data is not None:
        results["depression_regressor"] = train_depression_regressor(
            config,
            encoder_config,
            scaling,
            output_dir / DEPRESSION_REGRESSOR_DIR,
            config.seed + 2 + len(config.simclr_encoders),
        )
        summary["depression_regressor_trained_on"] = (
            f"{config.depression_data} except a held-out {config.depression_test_fraction:g} of its chips"
        )

    write_json_atomic(
        {"class_names": class_names, "scaling": scaling.to_dict(), **summary, "models": results},
        output_dir / "metrics.json",
    )
    for name, metrics in results.items():
        summary = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in metrics.items()
        )
        print(f"{name}: {summary}")
    return results


if __name__ == "__main__":
    main()
