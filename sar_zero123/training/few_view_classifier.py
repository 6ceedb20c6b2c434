"""The augmentation-benefit protocol's classifier: a small ResNet trained a fixed number of AdamW steps on
random shifts of a few chips (``sar_zero123.augmentation_benefit``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from sar_zero123.data import DecibelScaling
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluation.evaluators import SARClassifier

__all__ = ["random_shift", "train_classifier"]


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
    """The benchmark's classifier trained ``steps`` AdamW steps (cosine to 0) on random shifts of the chips.

    Every arm trains the same number of steps, so an arm with more chips gets no more compute.
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
