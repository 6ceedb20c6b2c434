"""Frozen-feature probes of a SAR encoder (Table I): the features, and the 1-NN class and azimuth probe.

Probes train on frozen train-split features without augmentation and report on the test split; features
are extracted once (:func:`extract_features`). Azimuth probes predict azimuth / 360 deg (the paper's
azimuth / 2pi) and report the circular error in degrees. The trained probes are
:mod:`sar_zero123.training.probes`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset

from sar_zero123.encoder import SAREncoder
from sar_zero123.evaluation.metrics import azimuth_error_deg

__all__ = [
    "FeatureSet",
    "azimuth_summary",
    "check_same_dim",
    "extract_features",
    "nearest_neighbor_probe",
]

NeighborMetric = Literal["cosine", "euclidean"]


@dataclass
class FeatureSet:
    """Frozen features of a split with their targets.

    Attributes:
        features: Encoder features, float32 ``(N, D)``.
        labels: Class indices, int64 ``(N,)``.
        azimuth_deg: Azimuths in [0, 360), float32 ``(N,)``.
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
    """Encodes a dataset with a frozen encoder in eval mode (its mode restored), batched on its device.

    Args:
        dataset: Items are dicts with `"image"` (1, S, S) normalised dB, `"label"` and `"azimuth_deg"`.

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


def nearest_neighbor_probe(
    train: FeatureSet,
    test: FeatureSet,
    metric: NeighborMetric = "cosine",
    chunk_size: int = 1024,
) -> dict[str, float]:
    """1-NN classification and azimuth regression in feature space (Table I, "1-NN" columns).

    Args:
        metric: `"cosine"` (largest similarity) or `"euclidean"` (smallest distance).
        chunk_size: Test samples per distance block (memory is chunk_size x N_train).

    Returns:
        `{"accuracy": percent, "azimuth_error_deg": mean circular error, "azimuth_error_median_deg"}`.

    Raises:
        ValueError: For an unknown `metric`, `chunk_size` < 1, or differing feature dimensions.
    """
    check_same_dim(train, test)
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
    return {"accuracy": accuracy, **azimuth_summary(train.azimuth_deg.cpu()[index], test.azimuth_deg.cpu())}


def azimuth_summary(predicted_deg: torch.Tensor, target_deg: torch.Tensor) -> dict[str, float]:
    """Mean and median circular error of predicted azimuths (degrees), as every azimuth probe reports them."""
    errors = azimuth_error_deg(predicted_deg.double(), target_deg.double())
    return {"azimuth_error_deg": errors.mean().item(), "azimuth_error_median_deg": errors.median().item()}


def check_same_dim(train: FeatureSet, test: FeatureSet) -> None:
    """Refuse train and test features of different dimensions: a probe fitted on one cannot read the other."""
    if train.features.shape[1] != test.features.shape[1]:
        raise ValueError(
            f"train and test features must have the same dimension, got {train.features.shape[1]} "
            f"and {test.features.shape[1]}"
        )
