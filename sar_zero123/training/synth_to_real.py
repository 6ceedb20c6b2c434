"""Training one classifier of Table II on (augmented) synthetic chips and scoring it on real chips."""

from __future__ import annotations

import logging
from typing import Any

import torch
import torch.nn.functional as F

from sar_zero123.augment import augment_batch
from sar_zero123.data import DecibelScaling
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluation.evaluators import SARClassifier
from sar_zero123.progress import progress_bar
from sar_zero123.runs.launch import start_run

logger = logging.getLogger(__name__)

__all__ = ["ADAMW_WEIGHT_DECAY", "NO_AUGMENTATION", "train_row"]

#: AdamW's weight decay for each row's classifier.
ADAMW_WEIGHT_DECAY = 5e-4

#: The row of Table II trained on the synthetic chips as they are.
NO_AUGMENTATION = "none"


def train_row(
    row: str,
    synth: tuple[torch.Tensor, torch.Tensor],
    real: tuple[torch.Tensor, torch.Tensor],
    class_names: list[str],
    scaling: DecibelScaling,
    config: Any,
) -> tuple[SARClassifier, dict[str, float]]:
    """Trains one classifier on synthetic chips augmented by ``row`` (a preset name, or
    :data:`NO_AUGMENTATION`) with ``config``'s (a ``SynthToRealConfig``) model and optimiser settings;
    returns it and its real-chip accuracy."""
    accelerator = start_run(None, seed=config.seed, mixed_precision=config.mixed_precision)
    device = accelerator.device
    encoder_config = SAREncoderConfig(
        image_size=config.image_size,
        cifar_stem=config.cifar_stem,
        hidden_sizes=config.hidden_sizes,
        embedding_size=config.embedding_size,
    )
    model = SARClassifier(encoder_config, class_names, scaling)
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=config.learning_rate, weight_decay=ADAMW_WEIGHT_DECAY
    )
    magnitude, labels = synth[0].to(device), synth[1].to(device)
    steps_per_epoch = -(-len(labels) // config.train_batch_size)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.epochs * steps_per_epoch)
    model, optimizer = accelerator.prepare(model, optimizer)
    order_generator = torch.Generator().manual_seed(config.seed)
    aug_generator = torch.Generator(device=device).manual_seed(config.seed)
    model.train()
    for epoch in progress_bar(range(config.epochs), desc=row, disable=not accelerator.is_local_main_process):
        order = torch.randperm(len(labels), generator=order_generator).to(device)
        for start in range(0, len(labels), config.train_batch_size):
            index = order[start : start + config.train_batch_size]
            if row == NO_AUGMENTATION:
                images = scaling.normalize(magnitude[index])
            else:
                images = augment_batch(magnitude[index], row, scaling, generator=aug_generator)
            loss = F.cross_entropy(model(images), labels[index])
            optimizer.zero_grad(set_to_none=True)
            accelerator.backward(loss)
            optimizer.step()
            scheduler.step()
        logger.info("%s epoch %d: last loss %.4f", row, epoch + 1, loss.item())
    model = accelerator.unwrap_model(model).eval()
    predictions = []
    with torch.no_grad():
        for chunk in real[0].split(256):
            predictions.append(model(scaling.normalize(chunk.to(device))).argmax(dim=1).cpu())
    accuracy = 100.0 * (torch.cat(predictions) == real[1]).double().mean().item()
    return model, {"real_accuracy": accuracy, "final_train_loss": loss.item()}
