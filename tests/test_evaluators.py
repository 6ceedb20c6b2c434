"""Tests for sar_zero123.evaluators and train/train_evaluators.py (fabricated chips, tiny ResNets)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from sar_zero123.data import ChipRecord, write_index
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluators import (
    AzimuthRegressor,
    SARClassifier,
    azimuth_regression_loss,
    load_evaluator,
    load_evaluators,
)
from train import train_evaluators

TINY_ENCODER = {
    "image_size": 16,
    "in_channels": 1,
    "cifar_stem": True,
    "depths": (1, 1),
    "hidden_sizes": (8, 16),
}


def write_chip_folder(
    root: Path,
    classes: tuple[str, ...] = ("A", "B"),
    azimuths_deg: tuple[float, ...] = tuple(range(0, 360, 30)),
    depressions_deg: tuple[float, ...] = (15.0, 17.0),
    size: int = 16,
) -> Path:
    """Writes `.npy` magnitude chips + `index.csv`: a class-dependent shape rotated to the azimuth."""
    root.mkdir(parents=True, exist_ok=True)
    records = []
    yy, xx = np.mgrid[:size, :size].astype(np.float32) - (size - 1) / 2
    for class_index, name in enumerate(classes):
        for depression in depressions_deg:
            for azimuth in azimuths_deg:
                angle = math.radians(azimuth)
                along = xx * math.cos(angle) + yy * math.sin(angle)
                across = -xx * math.sin(angle) + yy * math.cos(angle)
                length = 2.0 + 2.0 * class_index
                chip = np.exp(-(along**2) / (2 * length**2) - across**2 / 2.0) * (0.5 + 0.02 * depression)
                chip[size // 2 + int(3 * math.cos(angle)), size // 2 + int(3 * math.sin(angle))] = 1.0
                path = root / f"{name}_{int(depression)}_{int(azimuth):03d}.npy"
                np.save(path, np.clip(chip, 0.0, 1.0).astype(np.float32))
                records.append(
                    ChipRecord(
                        path=path,
                        target_class=name,
                        serial=f"{name}1",
                        depression_deg=depression,
                        azimuth_deg=float(azimuth),
                        height=size,
                        width=size,
                    )
                )
    write_index(records, root)
    return root


def test_azimuth_regression_loss_is_circular() -> None:
    predicted = torch.tensor([10 / 360, 359 / 360, 0.25, 0.5])
    target_deg = torch.tensor([10.0, 1.0, 0.0, 360.0 + 180.0])
    loss = azimuth_regression_loss(predicted, target_deg)
    expected = torch.tensor([0.0, 1 - math.cos(math.radians(2.0)), 1.0, 0.0])
    torch.testing.assert_close(loss, expected, atol=1e-6, rtol=0)


def test_evaluators_shapes_and_round_trip(tmp_path: Path) -> None:
    torch.manual_seed(0)
    config = SAREncoderConfig(**TINY_ENCODER)
    classifier = SARClassifier(config, ["A", "B", "C"]).eval()
    regressor = AzimuthRegressor(config, ["A", "B", "C"], hidden_sizes=(32, 32)).eval()
    images = torch.rand(4, 1, 16, 16, generator=torch.Generator().manual_seed(1))
    assert classifier(images).shape == (4, 3)
    assert classifier.features(images).shape == (4, 16)
    fraction = regressor(images)
    assert fraction.shape == (4,) and ((fraction > 0) & (fraction < 1)).all()
    degrees = regressor.predict_azimuth_deg(images)
    torch.testing.assert_close(degrees, fraction * 360.0)
    assert len(regressor.head) == 2 * 2 + 2  # Linear-ReLU x2, Linear, Sigmoid

    regressor.metrics = {"test_azimuth_error_deg": 12.5}
    regressor.save_pretrained(tmp_path / "regressor")
    loaded = load_evaluator(tmp_path / "regressor", class_names=["A", "B", "C"])
    assert isinstance(loaded, AzimuthRegressor) and loaded.hidden_sizes == [32, 32]
    assert loaded.metrics == {"test_azimuth_error_deg": 12.5}
    torch.testing.assert_close(loaded(images), fraction)


def test_load_evaluator_rejects_other_class_list(tmp_path: Path) -> None:
    torch.manual_seed(0)
    SARClassifier(SAREncoderConfig(**TINY_ENCODER), ["A", "B"]).save_pretrained(tmp_path / "classifier")
    with pytest.raises(ValueError, match=r"trained on classes \['A', 'B'\] but the data uses \['A', 'C'\]"):
        load_evaluator(tmp_path / "classifier", class_names=["A", "C"])
    with pytest.raises(FileNotFoundError, match="evaluator checkpoint not found"):
        load_evaluator(tmp_path / "missing")


def test_train_evaluators_smoke_and_reproducible(tmp_path: Path) -> None:
    data = write_chip_folder(tmp_path / "data")
    args = [
        "--data", str(data), "--image_size", "16", "--depths", "1", "1", "--hidden_sizes", "8", "16",
        "--mlp_hidden_sizes", "16", "16", "--epochs", "2", "--train_batch_size", "8", "--seed", "3",
    ]  # fmt: skip
    results = train_evaluators.main(["--output_dir", str(tmp_path / "run1"), *args])
    assert set(results) == {"classifier", "regressor"}
    assert 0.0 <= results["classifier"]["test_accuracy"] <= 1.0
    assert results["classifier"]["n_test"] == 24 and results["regressor"]["n_train"] == 24
    assert 0.0 <= results["regressor"]["test_azimuth_error_deg"] <= 180.0
    written = json.loads((tmp_path / "run1" / "metrics.json").read_text())
    assert written["class_names"] == ["A", "B"]
    evaluators = load_evaluators(tmp_path / "run1", class_names=["A", "B"])
    assert evaluators.image_size == 16 and list(evaluators.azimuth_regressors()) == ["scratch"]

    # Same seed, same bytes.
    train_evaluators.main(["--output_dir", str(tmp_path / "run2"), *args])
    for name in ("classifier", "regressor"):
        first = load_file(str(tmp_path / "run1" / name / "model.safetensors"))
        second = load_file(str(tmp_path / "run2" / name / "model.safetensors"))
        assert all(torch.equal(first[key], second[key]) for key in first)

    # Table IV probe on a frozen encoder: the encoder weights stay untouched.
    encoder_dir = tmp_path / "simclr" / "encoder"
    evaluators.classifier.encoder.save_pretrained(encoder_dir)
    probe_results = train_evaluators.main(
        ["--output_dir", str(tmp_path / "run1"), *args, "--simclr_encoders", str(tmp_path / "simclr")]
    )
    assert "probe:simclr" in probe_results
    probe = load_evaluators(tmp_path / "run1").probes["simclr"]
    for key, value in evaluators.classifier.encoder.state_dict().items():
        torch.testing.assert_close(probe.encoder.state_dict()[key], value)


def test_single_class_classifier_warns_that_its_accuracy_means_nothing() -> None:
    config = SAREncoderConfig(image_size=16, depths=(1,), hidden_sizes=(8,), embedding_size=8)
    with pytest.warns(UserWarning, match=r"classifier of a single class \['T72'\]: its accuracy is 100%"):
        SARClassifier(config, ["T72"])
