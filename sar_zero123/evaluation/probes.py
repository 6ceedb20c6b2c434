"""Frozen-feature probes of a SAR encoder (Table I): linear, MLP azimuth, 1-NN class and azimuth.

Probes train on frozen features of the train split without augmentation and report on the test
split. Features are extracted once with `extract_features`; every probe then works on the small
`(N, D)` feature matrices on any device. Results are plain dicts of Python floats so scripts can
write them to JSON directly.

Azimuth probes predict a number in [0, 1) read as azimuth / 360 deg (the paper's target
azimuth / 2pi); the error is circular, min(|a - b|, 360 - |a - b|), in degrees.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import DataLoader, Dataset

from sar_zero123.encoder import SAREncoder
from sar_zero123.evaluation.metrics import azimuth_error_deg

__all__ = [
    "FeatureSet",
    "extract_features",
    "linear_probe",
    "mlp_azimuth_probe",
    "nearest_neighbor_probe",
    "run_probes",
]

AzimuthLoss = Literal["circular", "mse"]
NeighborMetric = Literal["cosine", "euclidean"]


@dataclass
class FeatureSet:
    """Frozen features of a split with their targets.

    Attributes:
        features: Encoder features h = f(x), float32, shape (N, D).
        labels: Class indices, int64, shape (N,).
        azimuth_deg: Azimuths in degrees in [0, 360), float32, shape (N,).
    """

    features: torch.Tensor
    labels: torch.Tensor
    azimuth_deg: torch.Tensor

    def __post_init__(self) -> None:
        if self.features.ndim != 2:
            raise ValueError(f"features must be (N, D), got shape {tuple(self.features.shape)}")
        n = self.features.shape[0]
        if n == 0:
            raise ValueError("features must hold at least one sample")
        if self.labels.shape != (n,) or self.azimuth_deg.shape != (n,):
            raise ValueError(
                f"labels and azimuth_deg must be ({n},), got {tuple(self.labels.shape)} and "
                f"{tuple(self.azimuth_deg.shape)}"
            )
        if not torch.isfinite(self.features).all():
            raise ValueError("features must be finite")

    def to(self, device: torch.device | str) -> FeatureSet:
        """Returns the set on `device`."""
        return FeatureSet(self.features.to(device), self.labels.to(device), self.azimuth_deg.to(device))


@torch.no_grad()
def extract_features(
    encoder: SAREncoder,
    dataset: Dataset,
    batch_size: int = 256,
    num_workers: int = 0,
) -> FeatureSet:
    """Encodes a dataset with a frozen encoder, batched on the encoder's device.

    The encoder runs in eval mode (BatchNorm running statistics) and its previous mode is restored.

    Args:
        encoder: The SAR encoder.
        dataset: Items are dicts with `"image"` (1, S, S) normalised dB, `"label"` and `"azimuth_deg"`
            (as `sar_zero123.data.ChipDataset` returns them).
        batch_size: Images per forward pass.
        num_workers: DataLoader workers reading the files.

    Returns:
        Features, labels and azimuths on the CPU, in dataset order.

    Raises:
        ValueError: If `batch_size` < 1 or the dataset is empty.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if len(dataset) == 0:  # type: ignore[arg-type]
        raise ValueError("dataset must hold at least one item")
    was_training = encoder.training
    encoder.eval()
    device = encoder.device
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, num_workers=num_workers)
    features, labels, azimuths = [], [], []
    try:
        for batch in loader:
            image = batch["image"].to(device=device, dtype=encoder.dtype, non_blocking=True)
            features.append(encoder(image).float().cpu())
            labels.append(torch.as_tensor(batch["label"]).long())
            azimuths.append(torch.as_tensor(batch["azimuth_deg"]).float())
    finally:
        encoder.train(was_training)
    return FeatureSet(torch.cat(features), torch.cat(labels), torch.cat(azimuths) % 360.0)


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

    Args:
        train: Features the probe is fitted on.
        test: Features it is scored on.
        num_classes: Number of classes (default: 1 + the largest label in either set).
        epochs: Passes over the train features (Adam, cosine learning-rate decay).
        batch_size: Features per step.
        lr: Adam learning rate.
        weight_decay: Adam L2 penalty.
        generator: Source of the initialisation and the shuffling.

    Returns:
        `{"accuracy": percent of test samples classified correctly}`.

    Raises:
        ValueError: For non-positive `epochs`, `batch_size`, `lr`, negative `weight_decay`, or
            feature dimensions that differ between the sets.
    """
    _check_training_args(epochs, batch_size, lr, weight_decay)
    _check_same_dim(train, test)
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

    The network is Linear(D, hidden) - ReLU - Linear(hidden, 1) - sigmoid. With `loss="circular"`
    (default) it minimises 1 - cos(2pi(p - t)), which treats 359 deg and 1 deg as 2 deg apart; the
    paper's plain regression (`loss="mse"`) penalises that pair as 358 deg apart and so pulls
    predictions for near-north chips towards 180 deg. Either way a scalar sigmoid output must jump
    from 1 to 0 at north, so chips within a few degrees of 0/360 remain the hardest for this probe.

    Args:
        train: Features the probe is fitted on.
        test: Features it is scored on.
        hidden_dim: Hidden width (256 in the paper).
        loss: `"circular"` or `"mse"` on the [0, 1) target.
        epochs: Passes over the train features (Adam, cosine learning-rate decay).
        batch_size: Features per step.
        lr: Adam learning rate.
        weight_decay: Adam L2 penalty.
        generator: Source of the initialisation and the shuffling.

    Returns:
        `{"azimuth_error_deg": mean circular error, "azimuth_error_median_deg": median}` on test.

    Raises:
        ValueError: For an unknown `loss`, `hidden_dim` < 1, bad optimisation arguments or
            feature dimensions that differ between the sets.
    """
    _check_training_args(epochs, batch_size, lr, weight_decay)
    _check_same_dim(train, test)
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
    return _azimuth_summary(predicted_deg, test.azimuth_deg.cpu())


def nearest_neighbor_probe(
    train: FeatureSet,
    test: FeatureSet,
    metric: NeighborMetric = "cosine",
    chunk_size: int = 1024,
) -> dict[str, float]:
    """1-NN classification and 1-NN azimuth regression in feature space (Table I, "1-NN" columns).

    Each test sample takes the class and the azimuth of its nearest train sample.

    Args:
        train: Reference features.
        test: Query features.
        metric: `"cosine"` (largest cosine similarity) or `"euclidean"` (smallest L2 distance).
        chunk_size: Test samples per distance block (bounds memory at chunk_size x N_train).

    Returns:
        `{"accuracy": percent, "azimuth_error_deg": mean circular error,
        "azimuth_error_median_deg": median}`.

    Raises:
        ValueError: For an unknown `metric`, `chunk_size` < 1, or differing feature dimensions.
    """
    _check_same_dim(train, test)
    if metric not in ("cosine", "euclidean"):
        raise ValueError(f"metric must be 'cosine' or 'euclidean', got {metric!r}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    reference = train.features
    queries = test.features.to(reference.device)
    if metric == "cosine":
        reference, queries = F.normalize(reference, dim=1), F.normalize(queries, dim=1)
    nearest = []
    for start in range(0, queries.shape[0], chunk_size):
        block = queries[start : start + chunk_size]
        if metric == "cosine":
            nearest.append((block @ reference.T).argmax(dim=1))  # (chunk,)
        else:
            nearest.append(torch.cdist(block, reference).argmin(dim=1))
    index = torch.cat(nearest).cpu()
    accuracy = 100.0 * (train.labels.cpu()[index] == test.labels.cpu()).double().mean().item()
    return {"accuracy": accuracy, **_azimuth_summary(train.azimuth_deg.cpu()[index], test.azimuth_deg.cpu())}


def run_probes(
    train: FeatureSet,
    test: FeatureSet,
    num_classes: int | None = None,
    epochs: int = 100,
    generator: torch.Generator | None = None,
    probe_kwargs: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, float]:
    """All four probes of Table I on one pair of feature sets.

    Args:
        train: Train-split features (no augmentation).
        test: Test-split features.
        num_classes: Passed to `linear_probe`.
        epochs: Epochs of the two trained probes.
        generator: Source of randomness of the trained probes.
        probe_kwargs: Extra keyword arguments per probe, keyed `"linear"`, `"mlp"`, `"knn"`.

    Returns:
        `{"linear_accuracy", "mlp_azimuth_error_deg", "knn_accuracy", "knn_azimuth_error_deg"}`
        (accuracies in percent, errors in degrees) plus the two medians.
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


def _azimuth_summary(predicted_deg: torch.Tensor, target_deg: torch.Tensor) -> dict[str, float]:
    errors = azimuth_error_deg(predicted_deg.double(), target_deg.double())
    return {"azimuth_error_deg": errors.mean().item(), "azimuth_error_median_deg": errors.median().item()}


def _check_same_dim(train: FeatureSet, test: FeatureSet) -> None:
    if train.features.shape[1] != test.features.shape[1]:
        raise ValueError(
            f"train and test features must have the same dimension, got {train.features.shape[1]} "
            f"and {test.features.shape[1]}"
        )
