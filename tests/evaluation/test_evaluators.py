"""Tests for sar_zero123.evaluation.evaluators and the evaluators stage (sar_zero123.stages.evaluators,
train/train_evaluators.py), on fabricated chips and tiny ResNets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from chip_folders import TINY_ENCODER, write_chip_folder
from safetensors.torch import load_file

from sar_zero123.config import parse_config
from sar_zero123.data import ChipDataset, DecibelScaling, load_index
from sar_zero123.data.selection import hold_out
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluation.evaluators import (
    AzimuthRegressor,
    DepressionRegressor,
    SARClassifier,
    azimuth_regression_loss,
    depression_regression_loss,
    load_evaluator,
    load_evaluators,
)
from sar_zero123.evaluation.scoring import closer_to_target_depression
from sar_zero123.runs.folder import read_run_record
from sar_zero123.stages import evaluators as stage
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig, run_evaluators
from train import train_evaluators


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


def _snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under `folder` with its bytes and modification time."""
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns) for p in files}


def _no_work(*args, **kwargs):
    raise AssertionError("finished evaluators were trained again")


def test_train_evaluators_smoke_and_reproducible(tmp_path: Path, monkeypatch) -> None:
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
    assert evaluators.depression_regressor is None  # no --depression_data

    # Same seed, same bytes.
    train_evaluators.main(["--output_dir", str(tmp_path / "run2"), *args])
    for name in ("classifier", "regressor"):
        first = load_file(str(tmp_path / "run1" / name / "model.safetensors"))
        second = load_file(str(tmp_path / "run2" / name / "model.safetensors"))
        assert all(torch.equal(first[key], second[key]) for key in first)

    # The run folder: the same settings again are refused; --resume returns the finished run untouched.
    record = read_run_record(tmp_path / "run1")
    assert record["stage"] == "evaluators" and record["finished"] and record["outputs"] == ["metrics.json"]
    before = _snapshot(tmp_path / "run1")
    with pytest.raises(ValueError, match="already holds a finished evaluators run with these settings"):
        train_evaluators.main(["--output_dir", str(tmp_path / "run1"), *args])
    with pytest.raises(ValueError, match="Differences: epochs: folder 2, this run 3"):
        train_evaluators.main(["--output_dir", str(tmp_path / "run1"), *args, "--epochs", "3", "--resume"])
    monkeypatch.setattr(stage, "prepare_splits", _no_work)
    resumed = train_evaluators.main(["--output_dir", str(tmp_path / "run1"), *args, "--resume"])
    assert resumed == results and _snapshot(tmp_path / "run1") == before
    monkeypatch.undo()

    # Table IV probe on a frozen encoder: the encoder weights stay untouched. Another setting in the same
    # folder is a new run: --restart moves the first one aside, whole.
    encoder_dir = tmp_path / "simclr" / "encoder"
    evaluators.classifier.encoder.save_pretrained(encoder_dir)
    probe_argv = ["--simclr_encoders", str(tmp_path / "simclr"), "--restart"]
    probe_results = train_evaluators.main(["--output_dir", str(tmp_path / "run1"), *args, *probe_argv])
    assert "probe:simclr" in probe_results
    moved = [p for p in tmp_path.iterdir() if p.name.startswith("run1.replaced-")]
    assert len(moved) == 1 and _snapshot(moved[0]) == before
    assert read_run_record(tmp_path / "run1")["data"]["simclr_encoders"][0]["files"] == 2  # config, weights
    probe = load_evaluators(tmp_path / "run1").probes["simclr"]
    for key, value in evaluators.classifier.encoder.state_dict().items():
        torch.testing.assert_close(probe.encoder.state_dict()[key], value)


def test_single_class_classifier_warns_that_its_accuracy_means_nothing() -> None:
    config = SAREncoderConfig(image_size=16, depths=(1,), hidden_sizes=(8,), embedding_size=8)
    with pytest.warns(UserWarning, match=r"classifier of a single class \['T72'\]: its accuracy is 100%"):
        SARClassifier(config, ["T72"])


def test_depression_regressor_head_is_bounded_and_round_trips(tmp_path: Path) -> None:
    torch.manual_seed(0)
    regressor = DepressionRegressor(SAREncoderConfig(**TINY_ENCODER), ["A", "B"], hidden_sizes=(8,)).eval()
    images = torch.rand(4, 1, 16, 16, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        degrees = regressor.predict_depression_deg(images)
        torch.testing.assert_close(degrees, regressor(images) * 90.0)
        assert ((degrees > 0.0) & (degrees < 90.0)).all()
        # a saturated sigmoid reaches the bounds, never beyond
        last = regressor.head[-2]
        bias = last.bias.clone()
        last.bias.fill_(60.0)
        torch.testing.assert_close(regressor.predict_depression_deg(images), torch.full((4,), 90.0))
        last.bias.fill_(-60.0)
        torch.testing.assert_close(
            regressor.predict_depression_deg(images), torch.zeros(4), atol=1e-12, rtol=0
        )
        last.bias.copy_(bias)
    loss = depression_regression_loss(torch.tensor([17 / 90, 0.5, 0.0]), torch.tensor([17.0, 0.0, 45.0]))
    torch.testing.assert_close(loss, torch.tensor([0.0, 0.25, 0.25]), atol=1e-7, rtol=0)

    regressor.save_pretrained(tmp_path / "depression_regressor")
    loaded = load_evaluator(tmp_path / "depression_regressor")
    assert isinstance(loaded, DepressionRegressor) and loaded.hidden_sizes == [8]
    torch.testing.assert_close(loaded.predict_depression_deg(images), degrees)

    # in an evaluator folder it must share the classifier's decibel scaling: it scores the same views
    SARClassifier(SAREncoderConfig(**TINY_ENCODER), ["A", "B"]).save_pretrained(tmp_path / "classifier")
    AzimuthRegressor(SAREncoderConfig(**TINY_ENCODER), ["A", "B"]).save_pretrained(tmp_path / "regressor")
    assert isinstance(load_evaluators(tmp_path).depression_regressor, DepressionRegressor)
    other = DepressionRegressor(SAREncoderConfig(**TINY_ENCODER), ["A"], DecibelScaling(-40.0, 0.0))
    other.save_pretrained(tmp_path / "depression_regressor")
    with pytest.raises(ValueError, match="depression regressor was trained with decibel scaling"):
        load_evaluators(tmp_path)


def test_train_evaluators_trains_a_depression_regressor(tmp_path: Path) -> None:
    data = write_chip_folder(tmp_path / "data")
    depression_data = write_chip_folder(
        tmp_path / "depressions", depressions_deg=(10.0, 17.0, 30.0, 45.0), spot_px_per_depression_deg=0.1
    )
    out = tmp_path / "run"
    args = [
        "--data", str(data), "--depression_data", str(depression_data), "--output_dir", str(out),
        "--image_size", "16", "--depths", "1", "1", "--hidden_sizes", "8", "16", "--mlp_hidden_sizes", "8",
        "--epochs", "1", "--train_batch_size", "8", "--max_train_chips", "16", "--seed", "3",
    ]  # fmt: skip
    results = train_evaluators.main(args)  # 2 steps per model: 16 chips, 8 a batch
    metrics = results["depression_regressor"]
    assert metrics["n_train"] == 16 and metrics["n_test"] == round(0.2 * 96)  # 2 classes x 4 dep. x 12 az.
    written = json.loads((out / "metrics.json").read_text())
    assert written["models"]["depression_regressor"] == metrics
    assert (
        written["depression_regressor_trained_on"] == f"{depression_data} except a held-out 0.2 of its chips"
    )

    # the reported test error is the mean |prediction - depression| over the held-out chips
    evaluators = load_evaluators(out, class_names=["A", "B"])
    regressor = evaluators.depression_regressor
    assert isinstance(regressor, DepressionRegressor) and regressor.metrics == metrics
    _, test_records = hold_out(load_index(depression_data), 0.2, seed=3 + 2)
    chips = ChipDataset(test_records, size=16, scaling=evaluators.classifier.scaling)
    images = torch.stack([chips[i]["image"] for i in range(len(chips))])
    with torch.no_grad():
        predicted = regressor.predict_depression_deg(images)
    truth = torch.tensor([r.depression_deg for r in test_records])
    assert metrics["test_depression_error_deg"] == pytest.approx(
        (predicted - truth).abs().mean().item(), rel=1e-5
    )

    # depression data at one depression is refused before any work: no folder, no simulated data
    single = write_chip_folder(tmp_path / "single", depressions_deg=(15.0,))
    config = TrainEvaluatorsConfig(depression_data=str(single), output_dir=str(tmp_path / "refused"))
    with pytest.raises(ValueError, match=r"holds chips at depressions \[15.0\] deg; a depression regressor"):
        run_evaluators(config)
    assert not (tmp_path / "refused").exists()
    with pytest.raises(ValueError, match=r"--set depression_test_fraction: \w+ was removed"):
        parse_config(TrainEvaluatorsConfig, ["--set", "depression_test_fraction=0.5"])
    for name, value, bound in (("epochs", 100_000_000, "10000"), ("image_size", 100_000, "1024")):
        with pytest.raises(ValueError, match=f"{name} must be <= {bound}, got {value}"):
            TrainEvaluatorsConfig(**{name: value})


def test_hold_out_is_a_seeded_partition() -> None:
    records = list(range(10))
    train, test = hold_out(records, 0.25, seed=0)
    assert len(test) == 2 and sorted(train + test) == records  # round(2.5) = 2
    assert hold_out(records, 0.25, seed=0) == (train, test)
    assert hold_out(records, 0.25, seed=1) != (train, test)
    assert len(hold_out(records[:2], 0.01, seed=0)[1]) == 1  # at least one test chip


def _pearson_reference(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def test_closer_to_target_depression_on_hand_made_views() -> None:
    size = 16
    target = np.zeros((1, 1, size, size))
    target[0, 0, 8, 8] = 1.0
    input_depression = np.zeros((1, 1, size, size))
    input_depression[0, 0, 8, 12] = 1.0
    near_target = np.zeros((1, 1, size, size))
    near_target[0, 0, 8, 9] = 1.0  # one pixel off the target's spot, three off the other's
    generated = np.concatenate(
        [
            near_target,
            np.roll(input_depression, 1, axis=-1),  # one pixel off the input depression's spot
            0.8 * target + 0.2 * input_depression,
            np.full_like(target, 0.5),  # constant: correlates 0 with both, a tie is not "closer"
        ]
    )
    targets = np.repeat(target, 4, axis=0)
    references = np.repeat(input_depression, 4, axis=0)
    closer = closer_to_target_depression(generated, targets, references, sigma_px=1.5)
    assert closer.tolist() == [True, False, True, False]
    assert closer.double().mean().item() == 0.5
    # without the blur the off-by-one spot overlaps neither truth: equal correlations, a tie
    assert closer_to_target_depression(near_target, target, input_depression, sigma_px=0.0).tolist() == [
        False
    ]

    # a naive reference: np.corrcoef of the blurred views, one pair at a time
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(0)
    views = rng.random((3, 6, 1, size, size))
    fast = closer_to_target_depression(*views, sigma_px=1.5)
    blurred = [[gaussian_filter(v[i, 0], 1.5) for i in range(6)] for v in views]
    naive = [
        _pearson_reference(blurred[0][i], blurred[1][i]) > _pearson_reference(blurred[0][i], blurred[2][i])
        for i in range(6)
    ]
    assert fast.tolist() == naive and 0 < sum(naive) < 6
    with pytest.raises(ValueError, match="must share one"):
        closer_to_target_depression(views[0], views[1][:, :, :8], views[2])
