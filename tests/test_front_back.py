"""Tests for ``benchmarks/front_back.py``: the pixel heading test and its rows, on the tiny pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.front_back import draw_pairs, format_table, main, score, summarise, turn_images
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.model.build import build_sar_zero123


def test_score_prefers_the_image_it_matches_and_summarise_splits_by_turn():
    rng = np.random.default_rng(0)
    truth, flip, at_input = (rng.random((3, 16, 16)).astype(np.float32) for _ in range(3))
    per_pair = score(truth, truth, flip, at_input)  # the truth itself: heading and pose right
    assert per_pair["heading"] == [True] * 3 and per_pair["pose"] == [True] * 3
    assert per_pair["corr_truth"] == pytest.approx([1.0] * 3)
    per_pair = score(flip, truth, flip, at_input)  # the flip: heading wrong
    assert per_pair["heading"] == [False] * 3
    summary = summarise({"heading": [True, False, True], "pose": [1, 1, 0], "corr_truth": [0.5, 0.5, 0.5]},
                        [10.0, -70.0, 170.0])  # fmt: skip
    assert summary["heading"] == pytest.approx(2 / 3) and summary["n"] == 3
    assert summary["heading_abs_d_az_0_60"] == 1.0 and summary["heading_abs_d_az_60_120"] == 0.0
    assert summary["heading_abs_d_az_120_180"] == 1.0 and summary["corr_truth_se"] == 0.0


def test_turn_images_is_the_identity_at_zero_and_a_half_turn_at_180():
    images = np.random.default_rng(1).random((2, 8, 8)).astype(np.float32)
    np.testing.assert_allclose(turn_images(images, [0.0, 360.0], -1), images, atol=1e-6)
    np.testing.assert_allclose(turn_images(images, [180.0, 180.0], -1), images[:, ::-1, ::-1], atol=1e-5)


def test_pairs_are_seeded_and_cover_every_class():
    pairs = draw_pairs(["TANK", "APC"], 3, seed=4)
    assert [p[0] for p in pairs] == ["TANK"] * 3 + ["APC"] * 3 and pairs == draw_pairs(["TANK", "APC"], 3, 4)
    assert all(0.0 <= a < 360.0 and -180.0 <= d < 180.0 for _, a, d in pairs)


def test_main_scores_every_row_and_pipeline_setting(tmp_path):
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    pipe.save_pretrained(tmp_path / "pipeline")
    scaling = DecibelScaling.for_unit_magnitude().to_dict()
    (tmp_path / "pipeline" / SCALING_FILE).write_text(json.dumps(scaling))
    record = main(["--pipeline", str(tmp_path / "pipeline"), "--classes", "TANK", "APC",
                   "--pairs_per_class", "2", "--num_inference_steps", "1",
                   "--heading_guidance_scales", "0", "2", "--out", str(tmp_path / "fb.json")])  # fmt: skip
    names = list(record["rows"])
    assert names[:3] == ["input copy (floor)", "input turned", "VAE round trip (ceiling)"]
    assert names[3:] == [str(tmp_path / "pipeline"), f"{tmp_path / 'pipeline'}, heading guidance 2"]
    assert record["rows"]["input copy (floor)"]["pose"] == 0.0  # the input's own heading, always nearer
    assert all(row["n"] == 4 for row in record["rows"].values())
    assert json.loads((tmp_path / "fb.json").read_text())["rows"] == record["rows"]
    assert format_table(record).count("\n") == 2 + len(names) - 1
    with pytest.raises(ValueError, match="classes: \\['NOPE'\\] are not simulator classes"):
        main(["--classes", "NOPE"])
