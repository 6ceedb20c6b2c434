"""Train the evaluator models that score generated views (Table III, Table IV).

    python train/train_evaluators.py --output_dir runs/evaluators --data /path/to/mstar

writes `classifier/` (ResNet-18 from scratch, linear head), `regressor/` (ResNet-18 + MLP 256-256, sigmoid,
azimuth / 2pi), optionally `probes/<name>/` (frozen SimCLR encoder + MLP, Table IV) and `metrics.json`
with test accuracy and circular test azimuth error.

Evaluators always train on the train split of the `extended` protocol, i.e. real chips of ALL classes at
17 deg: for MSTAR-OOD the classifier must still know the held-out class (T72), as in the paper. They exist
only to score generated images.
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
from sar_zero123.data import ChipDataset, DecibelScaling, prepare_splits
from sar_zero123.encoder import SAREncoder, SAREncoderConfig, resolve_encoder_dir
from sar_zero123.evaluators import (
    CLASSIFIER_DIR,
    EVALUATOR_CONFIG_NAME,
    PROBES_DIR,
    REGRESSOR_DIR,
    AzimuthRegressor,
    SARClassifier,
    azimuth_regression_loss,
    load_evaluator,
)
from sar_zero123.metrics import azimuth_error_deg, classification_accuracy
from sar_zero123.run_state import load_checkpoint, resolve_resume_checkpoint, save_checkpoint
from sar_zero123.runs import start_run

logger = logging.getLogger(__name__)


@dataclass
class TrainEvaluatorsConfig:
    """Train the scratch ResNet-18 classifier and azimuth regressor (and SimCLR probes) that score views."""

    output_dir: str = "runs/evaluators"  # folder for classifier/, regressor/, probes/, metrics.json
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
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


@torch.no_grad()
def score_on_split(
    model: SARClassifier | AzimuthRegressor, loader: DataLoader, device: torch.device
) -> dict[str, float]:
    """Test accuracy (classifier) or mean/median circular azimuth error (regressor) on a split."""
    model.eval()
    outputs, labels, azimuths = [], [], []
    for batch in loader:
        images = batch["image"].to(device)
        if isinstance(model, SARClassifier):
            outputs.append(model(images).argmax(dim=1).cpu())
        else:
            outputs.append(model.predict_azimuth_deg(images).cpu())
        labels.append(batch["label"])
        azimuths.append(batch["azimuth_deg"].float())
    predictions = torch.cat(outputs)
    if isinstance(model, SARClassifier):
        return {
            "test_accuracy": classification_accuracy(predictions, torch.cat(labels)),
            "n_test": len(predictions),
        }
    errors = azimuth_error_deg(predictions, torch.cat(azimuths))
    return {
        "test_azimuth_error_deg": errors.mean().item(),
        "test_azimuth_error_median_deg": errors.median().item(),
        "n_test": len(predictions),
    }


def train_model(
    model: SARClassifier | AzimuthRegressor,
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
            images = batch["image"]
            if isinstance(unwrapped, SARClassifier):
                loss = F.cross_entropy(model(images), batch["label"].long())
            else:
                loss = azimuth_regression_loss(model(images), batch["azimuth_deg"].float()).mean()
            optimizer.zero_grad(set_to_none=True)
            accelerator.backward(loss)
            optimizer.step()
            scheduler.step()
            total += loss.item() * len(images)
            count += len(images)
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


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    """Trains classifier, regressor and probes; returns `{model name: test metrics}`."""
    config = parse_config(TrainEvaluatorsConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    output_dir = Path(config.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, output_dir)

    # 1. data: the extended protocol's train split holds every class (the OOD class included).
    work_dir = Path(config.work_dir) if config.work_dir is not None else output_dir
    splits = prepare_splits(config.data, "extended", work_dir, seed=config.seed)
    train_records, test_records = splits["train"], splits["test"]
    if config.max_train_chips is not None and len(train_records) > config.max_train_chips:
        keep = torch.randperm(len(train_records), generator=torch.Generator().manual_seed(config.seed))
        train_records = [train_records[i] for i in sorted(keep[: config.max_train_chips].tolist())]
    scaling = DecibelScaling.from_choice(config.scaling, train_records)
    class_names = sorted({r.target_class for r in splits["train"] + splits["test"]})
    dataset_kwargs = {"size": config.image_size, "scaling": scaling, "class_names": class_names}
    dataset_kwargs["crop_size"] = config.chip_crop_size
    train_set = ChipDataset(train_records, **dataset_kwargs)
    test_set = ChipDataset(test_records, **dataset_kwargs)
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

    write_json_atomic(
        {
            "class_names": class_names,
            "scaling": scaling.to_dict(),
            "trained_on": "extended/train (all classes)",
            "models": results,
        },
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
