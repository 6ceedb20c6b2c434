"""The trained frozen-feature probes of a SAR encoder (Table I): a linear classifier and an MLP azimuth
regressor, and :func:`run_probes`, which adds the 1-NN probe of :mod:`sar_zero123.evaluation.probes`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn

from sar_zero123.evaluation.probes import FeatureSet, azimuth_summary, check_same_dim, nearest_neighbor_probe

__all__ = ["linear_probe", "mlp_azimuth_probe", "run_probes"]

AzimuthLoss = Literal["circular", "mse"]


def _standardize(train: torch.Tensor, test: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Z-scores both sets with the train statistics (probe optimisation is then scale-free)."""
    mean = train.mean(dim=0, keepdim=True)
    std = train.std(dim=0, keepdim=True, unbiased=False).clamp_min(1e-6)
    return (train - mean) / std, (test - mean) / std


def _init_linear(layer: nn.Linear, generator: torch.Generator | None) -> nn.Linear:
    """PyTorch's default Linear initialisation, drawn from `generator` instead of the global RNG."""
    nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
    bound = 1.0 / math.sqrt(layer.in_features)
    nn.init.uniform_(layer.bias, -bound, bound, generator=generator)
    return layer


def _check_training_args(epochs: int, batch_size: int, lr: float, weight_decay: float) -> None:
    if epochs < 1:
        raise ValueError(f"epochs must be >= 1, got {epochs}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if not lr > 0:
        raise ValueError(f"lr must be > 0, got {lr}")
    if weight_decay < 0:
        raise ValueError(f"weight_decay must be >= 0, got {weight_decay}")


def _fit(
    model: nn.Module,
    inputs: torch.Tensor,
    loss_fn: Any,
    targets: torch.Tensor,
    epochs: int,
    batch_size: int,
    lr: float,
    weight_decay: float,
    generator: torch.Generator | None,
) -> nn.Module:
    """Mini-batch Adam on (inputs, targets), shuffled with `generator` each epoch."""
    optimizer = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs)
    n = inputs.shape[0]
    model.train()
    with torch.enable_grad():
        for _ in range(epochs):
            order = torch.randperm(n, generator=generator).to(inputs.device)
            for start in range(0, n, batch_size):
                index = order[start : start + batch_size]
                loss = loss_fn(model(inputs[index]), targets[index]).mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
            scheduler.step()
    return model.eval()


def linear_probe(
    train: FeatureSet,
    test: FeatureSet,
    num_classes: int | None = None,
    epochs: int = 100,
    batch_size: int = 256,
    lr: float = 1e-3,
    weight_decay: float = 0.0,
    generator: torch.Generator | None = None,
) -> dict[str, float]:
    """Linear classifier on standardised frozen features (Table I, classification, "MLP" column).

    Trained with Adam and cosine learning-rate decay; ``num_classes`` defaults to 1 + the largest label.

    Returns:
        ``{"accuracy": percent of test samples classified correctly}``.

    Raises:
        ValueError: For bad optimisation arguments or feature dimensions that differ between the sets.
    """
    _check_training_args(epochs, batch_size, lr, weight_decay)
    check_same_dim(train, test)
    if num_classes is None:
        num_classes = int(max(train.labels.max(), test.labels.max())) + 1
    x_train, x_test = _standardize(train.features, test.features)
    head = _init_linear(nn.Linear(x_train.shape[1], num_classes), generator).to(x_train.device)
    labels = train.labels.to(x_train.device)
    _fit(head, x_train, F.cross_entropy, labels, epochs, batch_size, lr, weight_decay, generator)
    with torch.no_grad():
        predictions = head(x_test).argmax(dim=1)
    return {"accuracy": 100.0 * (predictions.cpu() == test.labels.cpu()).double().mean().item()}


def _circular_loss(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1 - cos(2 pi (p - t)): zero at the target, periodic, so 359 deg vs 1 deg costs as 2 deg."""
    return 1.0 - torch.cos(2.0 * math.pi * (prediction - target))


def _mse_loss(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (prediction - target).square()


def mlp_azimuth_probe(
    train: FeatureSet,
    test: FeatureSet,
    hidden_dim: int = 256,
    loss: AzimuthLoss = "circular",
    epochs: int = 100,
    batch_size: int = 256,
    lr: float = 1e-3,
    weight_decay: float = 0.0,
    generator: torch.Generator | None = None,
) -> dict[str, float]:
    """Two-layer MLP azimuth regressor with sigmoid output = azimuth / 2pi (Table I, azimuth, "MLP").

    ``loss="circular"`` minimises 1 - cos(2pi(p - t)), so 359 deg and 1 deg are 2 deg apart; the paper's
    ``"mse"`` counts them 358 deg apart and pulls near-north chips towards 180 deg.

    Returns:
        ``{"azimuth_error_deg": mean circular error, "azimuth_error_median_deg": median}`` on test.

    Raises:
        ValueError: For an unknown ``loss``, ``hidden_dim`` < 1, bad optimisation arguments or feature
            dimensions that differ between the sets.
    """
    _check_training_args(epochs, batch_size, lr, weight_decay)
    check_same_dim(train, test)
    if hidden_dim < 1:
        raise ValueError(f"hidden_dim must be >= 1, got {hidden_dim}")
    losses = {"circular": _circular_loss, "mse": _mse_loss}
    if loss not in losses:
        raise ValueError(f"loss must be one of {sorted(losses)}, got {loss!r}")
    x_train, x_test = _standardize(train.features, test.features)
    mlp = nn.Sequential(
        _init_linear(nn.Linear(x_train.shape[1], hidden_dim), generator),
        nn.ReLU(),
        _init_linear(nn.Linear(hidden_dim, 1), generator),
        nn.Sigmoid(),
        nn.Flatten(0),  # (B, 1) -> (B,)
    ).to(x_train.device)
    targets = (train.azimuth_deg.to(x_train.device) % 360.0) / 360.0
    _fit(mlp, x_train, losses[loss], targets, epochs, batch_size, lr, weight_decay, generator)
    with torch.no_grad():
        predicted_deg = mlp(x_test).cpu() * 360.0
    return azimuth_summary(predicted_deg, test.azimuth_deg.cpu())


def run_probes(
    train: FeatureSet,
    test: FeatureSet,
    num_classes: int | None = None,
    epochs: int = 100,
    generator: torch.Generator | None = None,
    probe_kwargs: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, float]:
    """All four probes of Table I on one pair of feature sets; ``probe_kwargs`` keyed ``"linear"``, ``"mlp"``,
    ``"knn"``.

    Returns:
        ``{"linear_accuracy", "mlp_azimuth_error_deg", "knn_accuracy", "knn_azimuth_error_deg"}`` (percent,
        degrees) plus the two medians.
    """
    extra = {key: dict(value) for key, value in (probe_kwargs or {}).items()}
    unknown = sorted(set(extra) - {"linear", "mlp", "knn"})
    if unknown:
        raise ValueError(f"probe_kwargs keys must be 'linear', 'mlp' or 'knn', got {unknown}")
    linear = linear_probe(
        train, test, num_classes, epochs=epochs, generator=generator, **extra.get("linear", {})
    )
    mlp = mlp_azimuth_probe(train, test, epochs=epochs, generator=generator, **extra.get("mlp", {}))
    knn = nearest_neighbor_probe(train, test, **extra.get("knn", {}))
    return {
        "linear_accuracy": linear["accuracy"],
        "mlp_azimuth_error_deg": mlp["azimuth_error_deg"],
        "mlp_azimuth_error_median_deg": mlp["azimuth_error_median_deg"],
        "knn_accuracy": knn["accuracy"],
        "knn_azimuth_error_deg": knn["azimuth_error_deg"],
        "knn_azimuth_error_median_deg": knn["azimuth_error_median_deg"],
    }
