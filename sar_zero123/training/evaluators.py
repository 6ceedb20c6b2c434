"""Training one evaluator model (classifier, azimuth or depression regressor, or a probe): AdamW with cosine
decay, resumable epoch checkpoints, then its test metrics and ``save_pretrained``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader

from sar_zero123.data import ChipDataset
from sar_zero123.evaluation.evaluators import (
    EVALUATOR_CONFIG_NAME,
    AzimuthRegressor,
    DepressionRegressor,
    SARClassifier,
    azimuth_regression_loss,
    depression_regression_loss,
    load_evaluator,
)
from sar_zero123.evaluation.scoring import score_on_split
from sar_zero123.progress import progress_bar
from sar_zero123.runs.checkpoints import load_checkpoint, resolve_resume_checkpoint, save_checkpoint
from sar_zero123.runs.launch import start_run

logger = logging.getLogger(__name__)

__all__ = ["EvaluatorTraining", "evaluator_loader", "train_model", "training_loss"]

Evaluator = SARClassifier | AzimuthRegressor | DepressionRegressor


@dataclass(frozen=True)
class EvaluatorTraining:
    """How every evaluator model trains (AdamW, cosine decay to 0, epoch checkpoints)."""

    batch_size: int  # chips per process per step (also the scoring batch)
    learning_rate: float  # AdamW peak learning rate
    weight_decay: float  # AdamW weight decay
    checkpointing_epochs: int  # save a resumable checkpoint every this many epochs
    resume_from_checkpoint: str | None  # "latest", a checkpoint folder, or None
    num_workers: int  # DataLoader worker processes
    mixed_precision: str  # accelerate mixed precision: "no", "fp16" or "bf16"


def evaluator_loader(
    dataset: ChipDataset, training: EvaluatorTraining, shuffle: bool, seed: int
) -> DataLoader:
    """A loader of ``dataset`` in ``training``'s batches, shuffled by its own seeded generator."""
    return DataLoader(
        dataset,
        batch_size=training.batch_size,
        shuffle=shuffle,
        num_workers=training.num_workers,
        generator=torch.Generator().manual_seed(seed),
        drop_last=False,
    )


def training_loss(
    model: torch.nn.Module, evaluator: Evaluator, batch: dict[str, torch.Tensor]
) -> torch.Tensor:
    """Mean training loss of a batch: cross-entropy, circular azimuth or depression squared error.

    ``model`` runs the forward (maybe a data-parallel wrapper); the bare ``evaluator``'s kind picks the loss.
    """
    outputs = model(batch["image"])
    if isinstance(evaluator, SARClassifier):
        return F.cross_entropy(outputs, batch["label"].long())
    if isinstance(evaluator, DepressionRegressor):
        return depression_regression_loss(outputs, batch["depression_deg"].float()).mean()
    return azimuth_regression_loss(outputs, batch["azimuth_deg"].float()).mean()


def train_model(
    model: Evaluator,
    train_set: ChipDataset,
    test_set: ChipDataset,
    stage_dir: Path,
    *,
    training: EvaluatorTraining,
    epochs: int,
    seed: int,
) -> dict[str, float]:
    """Trains one evaluator, saves it to ``stage_dir`` and returns its test metrics.

    A finished model (its ``evaluator.json`` exists) is loaded instead; an interrupted one resumes from its
    latest epoch checkpoint.
    """
    if (stage_dir / EVALUATOR_CONFIG_NAME).is_file():
        logger.info("%s already trained; skipping", stage_dir)
        return load_evaluator(stage_dir).metrics
    # the loaders keep their own seeded generators: a model resumes at epoch boundaries only
    accelerator = start_run(None, seed=seed, mixed_precision=training.mixed_precision, seedable_sampler=False)
    parameters = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(parameters, lr=training.learning_rate, weight_decay=training.weight_decay)
    train_loader = evaluator_loader(train_set, training, shuffle=True, seed=seed)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs * len(train_loader))
    model, optimizer, train_loader, scheduler = accelerator.prepare(model, optimizer, train_loader, scheduler)
    checkpoint_dir = stage_dir / "checkpoints"
    start_epoch = 0
    resume = resolve_resume_checkpoint(checkpoint_dir, training.resume_from_checkpoint)
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
        description = f"{stage_dir.name} epoch {epoch + 1}/{epochs}"
        for batch in progress_bar(train_loader, desc=description, leave=False):
            loss = training_loss(model, unwrapped, batch)
            optimizer.zero_grad(set_to_none=True)
            accelerator.backward(loss)
            optimizer.step()
            scheduler.step()
            total += loss.item() * len(batch["image"])
            count += len(batch["image"])
        logger.info("%s epoch %d/%d: train loss %.4f", stage_dir.name, epoch + 1, epochs, total / count)
        if (epoch + 1) % training.checkpointing_epochs == 0 and epoch + 1 < epochs:
            save_checkpoint(
                accelerator, checkpoint_dir, epoch + 1, total_limit=1, extra_state={"epoch": epoch + 1}
            )
    metrics = score_on_split(unwrapped, evaluator_loader(test_set, training, False, seed), accelerator.device)
    metrics["n_train"] = len(train_set)
    unwrapped.metrics = metrics
    unwrapped.save_pretrained(stage_dir)
    logger.info("%s: %s", stage_dir.name, json.dumps(metrics))
    return metrics
