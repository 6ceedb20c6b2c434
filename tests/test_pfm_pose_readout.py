"""Tests for ``benchmarks/pfm_pose_readout.py``: what PFM's encoder reads from generated views, on a tiny
pipeline, tiny evaluators and fabricated chips."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from chip_folders import TINY_ENCODER, write_chip_folder
from dummies import get_dummy_components

from benchmarks.pfm_pose_readout import encode, main, without_chips
from sar_zero123.data import ChipDataset, load_index, split_records
from sar_zero123.encoder import SAREncoder, SAREncoderConfig
from sar_zero123.evaluation.evaluators import AzimuthRegressor, SARClassifier, load_evaluators
from sar_zero123.evaluation.probes import extract_features, nearest_neighbor_probe
from sar_zero123.evaluation.protocol import build_pair_sets
from sar_zero123.model.pipeline import SARZero123Pipeline


def _setup(tmp_path: Path) -> dict[str, Path]:
    data = write_chip_folder(tmp_path / "data", azimuths_deg=tuple(range(0, 360, 30)), size=32)
    config = SAREncoderConfig(**{**TINY_ENCODER, "image_size": 32})
    torch.manual_seed(0)
    SARClassifier(config, ["A", "B"]).save_pretrained(tmp_path / "evaluators" / "classifier")
    regressor = AzimuthRegressor(config, ["A", "B"], hidden_sizes=(16, 16))
    regressor.save_pretrained(tmp_path / "evaluators" / "regressor")
    SAREncoder(config).save_pretrained(tmp_path / "encoder")
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(tmp_path / "pipeline")
    return {"data": data, "evaluators": tmp_path / "evaluators", "encoder": tmp_path / "encoder",
            "pipeline": tmp_path / "pipeline"}  # fmt: skip


def test_readout_rows_floor_ceiling_and_models_by_hand(tmp_path: Path) -> None:
    paths = _setup(tmp_path)
    out = tmp_path / "readout" / "readout.json"
    argv = ["--pipeline", str(paths["pipeline"]), "--pipeline_names", "tiny", "--encoder",
            str(paths["encoder"]), "--evaluators", str(paths["evaluators"]), "--data", str(paths["data"]),
            "--protocol", "ood-B", "--n", "4", "--num_inference_steps", "1", "--projection_dim", "3",
            "--epochs", "2", "--out", str(out)]  # fmt: skip
    result = main(argv)
    rows = result["rows"]
    keys = [(row["model"], row["group"], row["features"]) for row in rows]
    assert keys == [(model, group, features)
                    for model in ("input copy (floor)", "real target (ceiling)", "tiny")
                    for group in ("seen", "unseen")
                    for features in ("features", "projected 3-d")]  # fmt: skip
    assert all(row["n"] == 2 for row in rows)
    assert json.loads(out.read_text())["rows"] == rows
    # the ceiling's 1-NN read-out by hand: target features against the extended train split's
    encoder = SAREncoder.from_pretrained(paths["encoder"]).eval()
    records = split_records(load_index(paths["data"]), "extended")["train"]
    train = extract_features(encoder, ChipDataset(records, size=32))
    evaluators = load_evaluators(paths["evaluators"])
    pairs = build_pair_sets(evaluators, data=paths["data"], protocol="ood-B", n=4, seed=0, image_size=32,
                            work_dir=tmp_path, evaluators_name=str(paths["evaluators"]))  # fmt: skip
    chips = [encode(encoder, images, group.labels, group.target_azimuth_deg)
             for group in pairs.values() for images in (group.inputs, group.targets)]  # fmt: skip
    kept = without_chips(train, *chips)
    assert 0 < len(kept.labels) < len(train.labels) and result["n_train"] == len(kept.labels)
    assert result["n_excluded"] == len(train.labels) - len(kept.labels)  # the unseen pairs' chips
    assert torch.cdist(kept.features, torch.cat([c.features for c in chips])).min() > 1e-6
    seen = pairs["seen"]
    targets = encode(encoder, seen.targets, seen.labels, seen.target_azimuth_deg)
    expected = nearest_neighbor_probe(kept, targets)
    ceiling = rows[4]
    assert ceiling["model"] == "real target (ceiling)" and ceiling["group"] == "seen"
    assert ceiling["knn_accuracy"] == pytest.approx(expected["accuracy"])
    assert ceiling["knn_azimuth_error_deg"] == pytest.approx(expected["azimuth_error_deg"])


def test_readout_refuses_unmatched_names(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        main(["--pipeline", "a", "b", "--pipeline_names", "one", "--encoder", "e", "--evaluators", "v",
              "--data", "d", "--out", str(tmp_path / "o.json")])
