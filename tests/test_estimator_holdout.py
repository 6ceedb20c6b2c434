"""benchmarks/estimator_holdout.py on a tiny simulated set and a tiny random VAE."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from diffusers import AutoencoderKL

from benchmarks import estimator_holdout
from benchmarks.azimuth_estimator_error import error_summary
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.orientation import azimuth_vector
from sar_zero123.sim import simulate_dataset


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("holdout")
    data = simulate_dataset(
        root / "data", classes=("TANK", "APC", "TRUCK"), instances=1, azimuth_step_deg=60.0, size=32, seed=0
    )
    vae = AutoencoderKL(**SAR_ZERO123_SIZES["tiny"]["vae"], sample_size=32)
    vae.save_pretrained(root / "vae")
    (root / "vae" / SCALING_FILE).write_text(json.dumps(DecibelScaling().to_dict()))
    return data, root / "vae"


def test_one_row_per_held_out_class_and_seed_with_the_others_as_training_set(setup, tmp_path: Path) -> None:
    data, vae = setup
    out = tmp_path / "holdout.json"
    argv = ["--vae", str(vae), "--data", str(data), "--held_out", "TANK", "TRUCK",
            "--training_classes", "TANK", "APC", "TRUCK", "--steps", "3", "--seeds", "0", "1",
            "--image_size", "32", "--out", str(out)]  # fmt: skip
    result = estimator_holdout.main(argv)
    assert json.loads(out.read_text()) == result
    rows = result["rows"]
    expected = [("TANK", 0), ("TANK", 1), ("TRUCK", 0), ("TRUCK", 1)]
    assert [(r["held_out"], r["seed"]) for r in rows] == expected
    assert rows[0]["training_classes"] == ["APC", "TRUCK"] and rows[2]["training_classes"] == ["TANK", "APC"]
    for row in rows:
        # 6 azimuths x 2 depressions per object: every chip of the held-out class is a test chip
        assert row["test"]["chips"] == 12
        for split in ("val", "test"):
            assert 0.0 <= row[split]["median_deg"] <= 180.0 and 0.0 <= row[split]["mean_deg"] <= 180.0
            assert 0.0 <= row[split]["above_135_deg_percent"] <= 100.0
    assert rows[0]["test"] != rows[1]["test"]  # the seed changes the estimator


def test_unknown_held_out_class_is_refused(setup, tmp_path: Path) -> None:
    data, vae = setup
    with pytest.raises(ValueError, match=r"held_out / training_classes: no chips of \['SPG'\]"):
        estimator_holdout.main(["--vae", str(vae), "--data", str(data), "--held_out", "SPG",
                                "--training_classes", "TANK", "--out", str(tmp_path / "x.json")])  # fmt: skip


def test_error_summary_of_exact_and_back_to_front_estimates() -> None:
    truth = torch.tensor([0.0, 90.0, 200.0, 359.0], dtype=torch.float64)
    exact = error_summary(azimuth_vector(truth), truth)
    assert exact["chips"] == 4 and exact["mean_deg"] == pytest.approx(0.0, abs=1e-4)
    assert exact["above_135_deg_percent"] == 0.0
    # three chips read back to front (180 deg off), one 30 deg off
    flipped = error_summary(azimuth_vector(truth + torch.tensor([180.0, 180.0, 180.0, 30.0])), truth)
    assert flipped["mean_deg"] == pytest.approx((3 * 180.0 + 30.0) / 4, abs=1e-4)
    assert flipped["above_135_deg_percent"] == pytest.approx(75.0)
