"""Tests for the evaluate stage (sar_zero123.stages.evaluate, train/evaluate.py), the Table III protocol and
scoring.score_views, on a tiny pipeline and fabricated chips."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path

import pytest
import torch
from chip_folders import TINY_ENCODER, write_chip_folder
from dummies import get_dummy_components

from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import load_chip
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluation.evaluators import (
    AzimuthRegressor,
    DepressionRegressor,
    Evaluators,
    SARClassifier,
    load_evaluators,
)
from sar_zero123.evaluation.protocol import (
    INPUT_COPY,
    REAL_TARGET,
    VAE_ROUND_TRIP,
    add_gap_closed,
    build_pair_sets,
    gap_closed,
)
from sar_zero123.evaluation.scoring import score_views
from sar_zero123.evaluation.speed import pareto_front
from sar_zero123.evaluation.tables import table3_markdown
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.runs.folder import data_identity, finish_run, open_run_folder, read_run_record
from sar_zero123.stages import evaluate as stage
from sar_zero123.stages.evaluate import EvaluateConfig, evaluation_pairs
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig
from train import evaluate


def _evaluators(directory: Path, image_size: int = 32, depression: bool = False) -> Evaluators:
    """Untrained tiny evaluators saved the way train_evaluators.py saves them (with a depression
    regressor when `depression`)."""
    config = SAREncoderConfig(**{**TINY_ENCODER, "image_size": image_size})
    torch.manual_seed(0)
    classifier = SARClassifier(config, ["A", "B"])
    regressor = AzimuthRegressor(config, ["A", "B"], hidden_sizes=(16, 16))
    classifier.save_pretrained(directory / "classifier")
    regressor.save_pretrained(directory / "regressor")
    depression_regressor = None
    if depression:
        depression_regressor = DepressionRegressor(config, ["A", "B"], hidden_sizes=(16,)).eval()
        depression_regressor.save_pretrained(directory / "depression_regressor")
    return Evaluators(classifier.eval(), regressor.eval(), depression_regressor=depression_regressor)


def test_score_views_identical_images(tmp_path: Path) -> None:
    evaluators = _evaluators(tmp_path, image_size=32)
    generator = torch.Generator().manual_seed(0)
    targets = torch.rand(6, 1, 32, 32, generator=generator)
    labels = torch.tensor([0, 1, 0, 1, 0, 1])
    with torch.no_grad():
        predicted_deg = evaluators.regressor.predict_azimuth_deg(targets).double()
        predicted_class = evaluators.classifier(targets).argmax(dim=1)
    with pytest.warns(UserWarning, match="n=6 samples for D=16"):
        scores = score_views(targets, targets, labels, predicted_deg, evaluators, crop_size=32, batch_size=4)
    for key in ("ms_ssim", "kuan_ssim", "ms_ssim_corrected", "kuan_ssim_corrected"):
        assert scores[key] == pytest.approx(1.0)
    assert scores["sfd"] == pytest.approx(0.0, abs=1e-6)
    assert scores["azimuth_error_deg"] == pytest.approx(0.0, abs=1e-3)
    assert scores["accuracy"] == pytest.approx(100.0 * (predicted_class == labels).double().mean().item())
    assert scores["n"] == 6 and scores["azimuth_error_deg/scratch"] == scores["azimuth_error_deg"]
    # where the views went: the share of each predicted class, summing to 100
    shares = [scores[f"predicted/{name}"] for name in evaluators.class_names]
    counts = torch.bincount(predicted_class, minlength=len(shares))
    assert shares == pytest.approx((100.0 * counts / 6).tolist()) and sum(shares) == pytest.approx(100.0)
    # Paper-comparable (8-bit, 256 px, authors' windows) and corrected values differ on unlike views.
    others = torch.rand(6, 1, 32, 32, generator=generator)
    with pytest.warns(UserWarning, match="rank-deficient"):
        scores = score_views(others, targets, labels, predicted_deg, evaluators, crop_size=32, batch_size=4)
    assert abs(scores["kuan_ssim"] - scores["kuan_ssim_corrected"]) > 1e-3
    assert abs(scores["ms_ssim"] - scores["ms_ssim_corrected"]) > 1e-3
    with pytest.raises(ValueError, match="differ in size"):
        score_views(targets[..., :16, :16], targets, labels, predicted_deg, evaluators, crop_size=16)
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        score_views(targets + 1.0, targets, labels, predicted_deg, evaluators, crop_size=32)


def test_score_views_depression_overshoot_closed_form(tmp_path: Path) -> None:
    evaluators = _evaluators(tmp_path, image_size=32, depression=True)
    targets = torch.rand(6, 1, 32, 32, generator=torch.Generator().manual_seed(1))
    labels = torch.tensor([0, 1, 0, 1, 0, 1])
    with torch.no_grad():
        azimuth = evaluators.regressor.predict_azimuth_deg(targets).double()
        predicted = evaluators.depression_regressor.predict_depression_deg(targets).double()
    # requests up, down and none: a view's overshoot is its offset from the target, signed along the request
    inputs = torch.tensor([17.0, 17.0, 40.0, 40.0, 20.0, 20.0], dtype=torch.float64)
    goals = predicted + torch.tensor([-2.0, 3.0, -1.0, 4.0, 0.0, 0.0], dtype=torch.float64)
    goals[4:] = inputs[4:]  # no depression change: not counted
    kwargs = {"target_depression_deg": goals, "crop_size": 32, "batch_size": 4}
    views = (targets, targets, labels, azimuth, evaluators)
    with pytest.warns(UserWarning):
        scores = score_views(*views, input_depression_deg=inputs, **kwargs)
    along = torch.sign(goals - inputs)[:4]
    expected = ((predicted - goals)[:4] * along).tolist()
    assert scores["depression_overshoot_deg_n"] == 4
    assert scores["depression_overshoot_deg"] == pytest.approx(sum(expected) / 4, rel=1e-6)
    se = torch.tensor(expected).std().item() / 2
    assert scores["depression_overshoot_deg_se"] == pytest.approx(se, rel=1e-5)
    error = (predicted - goals).abs().mean().item()
    assert scores["depression_error_deg"] == pytest.approx(error, rel=1e-6)
    with pytest.warns(UserWarning):  # without the input's depression: the unsigned error only
        assert "depression_overshoot_deg" not in score_views(*views, **kwargs)
    with pytest.raises(ValueError, match="input_depression_deg"):
        score_views(*views, input_depression_deg=inputs[:3], **kwargs)


def _snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under `folder` with its bytes and modification time."""
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns) for p in files}


def _no_work(*args, **kwargs):
    raise AssertionError("a finished evaluation was redone")


def test_evaluate_end_to_end_on_dummy_pipeline(tmp_path: Path, monkeypatch, caplog) -> None:
    data = write_chip_folder(tmp_path / "data", azimuths_deg=tuple(range(0, 360, 60)), size=32)
    _evaluators(tmp_path / "evaluators")
    pipe = SARZero123Pipeline(**get_dummy_components())
    pipe.save_pretrained(tmp_path / "lambda0")
    pipe.save_pretrained(tmp_path / "lambda4")
    out = tmp_path / "eval"
    argv = [
        "--pipeline", str(tmp_path / "lambda0"), "--pipeline", str(tmp_path / "lambda4"),
        "--lambdas", "0", "4",
        "--evaluators", str(tmp_path / "evaluators"), "--data", str(data), "--protocol", "ood-B",
        "--n", "4", "--num-inference-steps", "2", "--guidance-scale", "3.0", "--crop_size", "32",
        "--steps", "1", "2", "--schedulers", "ddim", "euler", "--speed_n", "2", "--eval_batch_size", "2",
        "--num_figure_pairs", "1", "--output_dir", str(out), "--device", "cpu",
    ]  # fmt: skip
    caplog.set_level(logging.INFO, logger="sar_zero123.evaluation.protocol")
    with pytest.warns(UserWarning, match="rank-deficient"):
        result = evaluate.main(argv)
    # every batch of generation logs its progress: a long evaluation is never silent
    for line in ("lambda0 seen: 2/2 views generated", "lambda4 unseen: 2/2 views generated",
                 "lambda4 euler 2 steps: 2/2 views generated"):  # fmt: skip
        assert line in caplog.text
    table3 = json.loads((out / "table3.json").read_text())["results"]
    floor, target = "input copy (unturned, keeps identity)", "real target (ceiling)"
    round_trip = "VAE round trip (ceiling)"
    assert set(table3) == {floor, target, round_trip, "lambda0", "lambda4"}  # both share one VAE: one row
    for group in ("seen", "unseen"):
        # the real target scored against itself: perfect structure; its regressor error is the regressor's own
        assert table3[target][group]["ms_ssim"] == pytest.approx(1.0, abs=1e-6)
        assert table3[target][group]["sfd"] == pytest.approx(0.0, abs=1e-6)
        values, low, high = (table3[m][group] for m in ("lambda0", floor, round_trip))
        key = "azimuth_error_deg"
        gap_se = math.hypot(low[f"{key}_se"], high[f"{key}_se"])
        expected = gap_closed(values[key], low[key], high[key], gap_se=gap_se)
        assert values["azimuth_gap_closed"] == pytest.approx(expected, nan_ok=True)
        assert "azimuth_gap_closed" not in low and values["azimuth_error_deg_se"] >= 0.0
    for method in ("lambda0", "lambda4"):
        assert set(table3[method]) == {"seen", "unseen"}
        for group in ("seen", "unseen"):
            values = table3[method][group]
            assert values["n"] == 2
            assert 0.0 <= values["ms_ssim"] <= 1.0 and 0.0 <= values["azimuth_error_deg"] <= 180.0
            assert all(math.isfinite(values[key]) for key in ("sfd", "kuan_ssim", "accuracy"))
            assert 0.0 <= values["ms_ssim_corrected"] <= 1.0 and math.isfinite(values["kuan_ssim_corrected"])
    # Same weights, same pairs, same seeds -> identical scores.
    for key in ("ms_ssim", "sfd", "azimuth_error_deg", "accuracy"):
        assert table3["lambda0"]["unseen"][key] == table3["lambda4"]["unseen"][key]
    markdown = (out / "table3.md").read_text()
    assert "paper: PFM (lambda=4)" in markdown
    assert "| 89.0 | 23.5 | - | 1.84 | 0.6720 | 0.7374 | - | - |" in markdown  # the paper gives no axis error
    assert "MS-SSIM corr." in markdown
    assert "Az. err. (deg), scratch" in (out / "table4.md").read_text()
    for name in ("views.png", "lambda_sweep.png", "speed_error.png", "speed_error.md"):
        assert (out / name).stat().st_size > 0
    rows = result["speed_error"]
    assert len(rows) == 2 * 2 * 2 and {row["scheduler"] for row in rows} == {"ddim", "euler"}
    assert all(row["images_per_s"] > 0 and row["n"] == 2 for row in rows)
    # each row: its cost in UNet evaluations counted (guidance 3: two per step), its peak memory, its
    # errors' standard errors and whether it is on the front; below 256 pairs the table says indicative
    for row in rows:
        assert row["unet_evaluations_per_image"] == 2 * row["steps"] and row["batch_size"] == 2
        assert row["peak_memory_mib"] > 0 and row["azimuth_error_deg_se"] >= 0 and row["accuracy_se"] >= 0
    assert [row["pareto"] for row in rows] == pareto_front(rows) and any(row["pareto"] for row in rows)
    assert json.loads((out / "speed_error.json").read_text())["indicative"] is True
    assert "Indicative: fewer than 256 pairs per row" in (out / "speed_error.md").read_text()
    assert isinstance(pipe.scheduler, type(get_dummy_components()["scheduler"]))

    # the run folder records what made it and is finished only with its last output
    record = read_run_record(out)
    assert record["stage"] == "evaluate" and record["finished"] and "speed_error.png" in record["outputs"]
    assert record["data"]["pipelines"][1]["path"] == str((tmp_path / "lambda4").resolve())
    before = _snapshot(out)
    with pytest.raises(ValueError, match="already holds a finished evaluate run with these settings"):
        evaluate.main(argv)
    with pytest.raises(ValueError, match="Differences: n: folder 4, this run 6"):
        evaluate.main([*argv, "--n", "6", "--resume"])
    # --resume returns the finished run as it is (on another device setting), without loading a model
    monkeypatch.setattr(stage, "load_evaluators", _no_work)
    resumed = evaluate.main([*argv, "--resume", "--device", "cpu"])
    assert json.dumps(resumed, sort_keys=True) == json.dumps(result, sort_keys=True)
    assert _snapshot(out) == before
    # --restart moves the old run aside, untouched, and starts over
    monkeypatch.undo()
    with pytest.warns(UserWarning, match="rank-deficient"):
        evaluate.main([*argv, "--num_figure_pairs", "0", "--restart"])
    moved = [p for p in tmp_path.iterdir() if p.name.startswith("eval.replaced-")]
    assert len(moved) == 1 and _snapshot(moved[0]) == before
    assert read_run_record(out)["finished"] and read_run_record(out)["config"]["num_figure_pairs"] == 0
    assert not (out / "views.png").exists() and (out / "table3.json").is_file()


def test_evaluate_into_an_evaluators_folder_is_refused_and_changes_nothing(tmp_path: Path) -> None:
    data = write_chip_folder(tmp_path / "data", azimuths_deg=(0.0, 120.0, 240.0), size=32)
    evaluators_dir = tmp_path / "evaluators"
    trained = TrainEvaluatorsConfig(output_dir=str(evaluators_dir), data=str(data), image_size=32)
    open_run_folder(evaluators_dir, "evaluators", trained, data={"data": data_identity(data)})
    save_config(trained, evaluators_dir)
    _evaluators(evaluators_dir)
    finish_run(evaluators_dir, ["classifier", "regressor"])
    (tmp_path / "pipe").mkdir()
    before = _snapshot(evaluators_dir)
    argv = ["--pipeline", str(tmp_path / "pipe"), "--evaluators", str(evaluators_dir), "--data", str(data),
            "--n", "2", "--output_dir", str(evaluators_dir), "--device", "cpu"]  # fmt: skip
    for extra in ([], ["--resume"]):
        with pytest.raises(ValueError, match="Differences: stage: folder 'evaluators', this run 'evaluate'"):
            evaluate.main([*argv, *extra])
    assert _snapshot(evaluators_dir) == before
    # a folder without a record (written before the run-folder rule, or by hand) is refused too
    (evaluators_dir / "run.json").unlink()
    with pytest.raises(ValueError, match="is not empty and holds no run.json"):
        evaluate.main(argv)
    assert (evaluators_dir / "config.json").read_bytes() == before["config.json"][0]


def test_evaluate_bounds_what_a_user_can_size(tmp_path: Path) -> None:
    assert stage.MAX_EVALUATION_PAIRS == 100_000
    with pytest.raises(ValueError, match="n must be <= 100,000, got 100,000,000"):
        EvaluateConfig(pipeline=["a"], n=100_000_000)
    with pytest.raises(ValueError, match=r"num_inference_steps must be an integer in \[1, 1,000\], got 5000"):
        EvaluateConfig(pipeline=["a"], num_inference_steps=5000)
    with pytest.raises(ValueError, match="eval_batch_size must be <= 1,024"):
        EvaluateConfig(pipeline=["a"], eval_batch_size=4096)
    with pytest.raises(ValueError, match="num_figure_pairs must be <= 32, got 5,000"):
        EvaluateConfig(pipeline=["a"], num_figure_pairs=5000)
    with pytest.raises(ValueError, match=r"heading_guidance_scale must lie in \[0, 100\], got -2.0"):
        EvaluateConfig(pipeline=["a"], heading_guidance_scale=-2.0)
    with pytest.raises(ValueError, match=r"depression_guidance_scale must lie in \[0, 100\], got inf"):
        EvaluateConfig(pipeline=["a"], depression_guidance_scale=float("inf"))
    with pytest.raises(ValueError, match=r"strength must lie in \(0, 1\], got 1.5"):
        EvaluateConfig(pipeline=["a"], strength=1.5)
    with pytest.raises(ValueError, match="strength 0.01 x num_inference_steps 50 leaves no denoising step"):
        EvaluateConfig(pipeline=["a"], strength=0.01, num_inference_steps=50)
    # the speed/error sweep's step counts too, before any pipeline is loaded
    with pytest.raises(ValueError, match="strength 0.5 x steps 1 leaves no denoising step"):
        EvaluateConfig(pipeline=["a"], strength=0.5, steps=[1, 20], schedulers=["ddim"])
    with pytest.raises(ValueError, match=r"start_from must be one of .*turned_input.*, got 'noise'"):
        EvaluateConfig(pipeline=["a"], start_from="noise")
    with pytest.raises(ValueError, match="steps: at most 16 step counts, got 17"):
        EvaluateConfig(pipeline=["a"], steps=list(range(1, 18)), schedulers=["ddim"])
    with pytest.raises(ValueError, match=r"steps: each value once, got \[5, 5\]"):
        EvaluateConfig(pipeline=["a"], steps=[5, 5], schedulers=["ddim"])
    with pytest.raises(ValueError, match=r"steps must lie in \[1, 1000\]"):
        EvaluateConfig(pipeline=["a"], steps=[2000], schedulers=["ddim"])
    with pytest.raises(ValueError, match="speed_n must be <= the 2 seen pairs"):
        EvaluateConfig(pipeline=["a"], protocol="ood-B", n=4, steps=[1], schedulers=["ddim"], speed_n=3)
    # what the data can give: two chips of an object at one depression admit two distinct pairs
    data = write_chip_folder(tmp_path / "data", azimuths_deg=(0.0, 90.0), size=32)
    evaluators = _evaluators(tmp_path / "evaluators")
    kwargs = {"data": data, "protocol": "extended", "image_size": 32, "work_dir": tmp_path}
    with pytest.raises(ValueError, match="n: the seen group needs 5 distinct pairs .* 4 chips admit only 4"):
        build_pair_sets(evaluators, n=5, **kwargs)
    assert len(build_pair_sets(evaluators, n=4, **kwargs)["seen"]) == 4


def test_evaluate_rejects_bad_config() -> None:
    with pytest.raises(ValueError, match="n must be >= 4 for an ood protocol"):
        EvaluateConfig(pipeline=["a"], protocol="ood-T72", n=3)
    with pytest.raises(ValueError, match="n must be >= 2"):
        EvaluateConfig(pipeline=["a"], n=1)
    with pytest.raises(ValueError, match="lambdas has 1 values for 2 pipelines"):
        EvaluateConfig(pipeline=["a", "b"], lambdas=[0.0])
    with pytest.raises(ValueError, match="schedulers: unknown"):
        EvaluateConfig(pipeline=["a"], steps=[10], schedulers=["heun"])
    with pytest.raises(ValueError, match=r"pipeline_names: each row needs its own name, got \['runs/a', 'r"):
        EvaluateConfig(pipeline=["runs/a", "runs/a"])  # one row would overwrite the other


def test_evaluate_rejects_evaluators_for_other_classes(tmp_path: Path) -> None:
    data = write_chip_folder(tmp_path / "data", classes=("A", "C"), azimuths_deg=(0.0, 90.0), size=32)
    evaluators = _evaluators(tmp_path / "evaluators")
    with pytest.raises(
        ValueError, match=r"evaluators/ was trained on classes \['A', 'B'\] but the data uses"
    ):
        build_pair_sets(evaluators, data=data, protocol="extended", n=2, image_size=32, work_dir=tmp_path,
                        evaluators_name="evaluators/")  # fmt: skip


def test_pareto_front_keeps_the_rows_no_other_row_beats_on_both_speed_and_error() -> None:
    rows = [{"images_per_s": v, "azimuth_error_deg": e} for v, e in
            ((1.0, 10.0), (2.0, 12.0), (2.0, 15.0), (4.0, 12.0), (8.0, 30.0), (0.5, 10.0))]  # fmt: skip
    # (2, 12) is beaten by (4, 12): as accurate and faster; (0.5, 10) by (1, 10)
    assert pareto_front(rows) == [True, False, False, True, True, False]
    assert pareto_front(rows[:1]) == [True] and pareto_front([rows[0], dict(rows[0])]) == [True, True]


def test_gap_closed_is_the_fraction_between_floor_and_ceiling() -> None:
    assert gap_closed(55.0, floor=90.0, ceiling=20.0) == pytest.approx(0.5)
    assert gap_closed(20.0, floor=90.0, ceiling=20.0) == pytest.approx(1.0)
    assert gap_closed(100.0, floor=90.0, ceiling=20.0) == pytest.approx(-1 / 7)
    assert gap_closed(60.0, floor=40.0, ceiling=80.0, higher_is_better=True) == pytest.approx(0.5)
    assert math.isnan(gap_closed(50.0, floor=90.0, ceiling=90.0))
    assert math.isnan(gap_closed(50.0, floor=20.0, ceiling=30.0))  # the floor beats the ceiling
    # a gap the pairs do not resolve (95.3 vs 96.1 % at a standard error of 2.6) is no gap, not -11,500 %
    assert math.isnan(gap_closed(3.1, floor=95.3, ceiling=96.1, higher_is_better=True, gap_se=2.6))
    assert gap_closed(55.0, floor=90.0, ceiling=20.0, gap_se=6.0) == pytest.approx(0.5)
    assert math.isnan(gap_closed(85.0, floor=100.0, ceiling=70.0, higher_is_better=True))


def test_depression_gap_closed_and_columns_on_hand_made_numbers() -> None:
    floor, target, round_trip = INPUT_COPY, REAL_TARGET, VAE_ROUND_TRIP

    def row(azimuth: float, accuracy: float, depression: float | None, se: float = 1.0) -> dict[str, float]:
        values = {"azimuth_error_deg": azimuth, "azimuth_error_deg_se": se, "accuracy": accuracy,
                  "accuracy_se": se, "n": 8.0}  # fmt: skip
        if depression is not None:
            values.update(depression_error_deg=depression, depression_error_deg_se=se)
        return values

    results = {
        floor: {"seen": row(90.0, 50.0, 20.0), "unseen": row(90.0, 50.0, 5.0)},
        target: {"seen": row(10.0, 95.0, 2.0), "unseen": row(10.0, 95.0, 2.0)},
        round_trip: {"seen": row(20.0, 90.0, 4.0), "unseen": row(20.0, 90.0, 4.0)},
        "model": {"seen": row(55.0, 70.0, 8.0), "unseen": row(55.0, 70.0, 3.0)},
    }
    add_gap_closed(results, floor=floor, ceiling=round_trip)
    seen, unseen = results["model"]["seen"], results["model"]["unseen"]
    assert seen["depression_gap_closed"] == pytest.approx((20.0 - 8.0) / (20.0 - 4.0))  # 0.75
    assert seen["azimuth_gap_closed"] == pytest.approx(0.5) and seen["accuracy_gap_closed"] == pytest.approx(
        0.5
    )
    # floor 5 vs ceiling 4 deg at a standard error of 1 each: a gap the pairs do not resolve
    assert math.isnan(unseen["depression_gap_closed"])
    assert "depression_gap_closed" not in results[floor]["seen"]

    results["model"]["seen"]["closer_to_target_depression"] = 0.625
    markdown = table3_markdown(results, include_paper=True)
    header = markdown.splitlines()[0]
    assert "Dep. err. (deg) ↓ | Closer to target dep. ↑ | Az. gap closed ↑ | Acc. gap closed ↑ | " in header
    assert header.endswith("| Dep. gap closed ↑ | n |")
    assert "| model | seen | " in markdown and "| 8.0 ± 1.0 | 0.62 | 50 % | 50 % | 75 % | 8 |" in markdown
    assert "| model | unseen | " in markdown and "| 3.0 ± 1.0 | - | 50 % | 50 % | no gap | 8 |" in markdown
    assert "| 89.0 | 23.5 | - | 1.84 | 0.6720 | 0.7374 | - | - | - | - |" in markdown  # paper: no dep.

    # without a depression regressor (older evaluator folders) the table keeps its columns
    plain = {method: {g: row(50.0, 50.0, None) for g in ("seen",)} for method in (floor, round_trip, "model")}
    add_gap_closed(plain, floor=floor, ceiling=round_trip)
    assert "depression_gap_closed" not in plain["model"]["seen"]
    assert "Dep." not in table3_markdown(plain, include_paper=False).splitlines()[0]


def test_evaluate_depression_protocol_passes_input_depression(tmp_path: Path, monkeypatch) -> None:
    data = write_chip_folder(
        tmp_path / "data",
        azimuths_deg=tuple(range(0, 360, 60)),
        depressions_deg=(10.0, 17.0, 30.0, 45.0),
        size=32,
        spot_px_per_depression_deg=0.2,
    )
    _evaluators(tmp_path / "evaluators", depression=True)
    pipe = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
    pipe.save_pretrained(tmp_path / "pipe")
    requested: list[torch.Tensor] = []
    call = SARZero123Pipeline.__call__

    def spy(self, *args, **kwargs):
        requested.append(torch.as_tensor(kwargs["input_depression_deg"]).cpu())
        return call(self, *args, **kwargs)

    monkeypatch.setattr(SARZero123Pipeline, "__call__", spy)
    out = tmp_path / "eval"
    argv = [
        "--pipeline", str(tmp_path / "pipe"), "--evaluators", str(tmp_path / "evaluators"),
        "--data", str(data), "--protocol", "ood-B", "--input_depression_deg", "17",
        "--target_depressions_deg", "10", "30", "45",
        "--no-same_depression", "--n", "6", "--num-inference-steps", "1", "--crop_size", "32",
        "--steps", "1", "--schedulers", "ddim", "--speed_n", "2", "--eval_batch_size", "3",
        "--num_figure_pairs", "1", "--output_dir", str(out), "--device", "cpu",
    ]  # fmt: skip
    with pytest.warns(UserWarning, match="rank-deficient"):
        evaluate.main(argv)
    # Table III: 2 groups x 1 batch of 3; the sweep: a warm-up of 1 pair, then 2 pairs
    assert [len(r) for r in requested] == [3, 3, 1, 2] and all((r == 17.0).all() for r in requested)

    written = json.loads((out / "table3.json").read_text())
    table3 = written["results"]
    assert written["input_depression_deg"] == 17.0 and written["target_depressions_deg"] == [10.0, 30.0, 45.0]
    for group in ("seen", "unseen"):
        assert set(written["pairs_per_d_el_deg"][group]) <= {"-7", "+13", "+28"}
        assert sum(written["pairs_per_d_el_deg"][group].values()) == 3
    # the same pairs again: the real target's depression error is the regressor's own on the targets
    config = EvaluateConfig(**json.loads((out / "config.json").read_text()))
    evaluators = load_evaluators(tmp_path / "evaluators")
    pair_sets = evaluation_pairs(config, evaluators, image_size=32)
    floor, target, round_trip = INPUT_COPY, REAL_TARGET, VAE_ROUND_TRIP
    for group, pairs in pair_sets.items():
        assert (pairs.input_depression_deg == 17.0).all() and pairs.has_reference.all()
        torch.testing.assert_close(pairs.d_el_deg, pairs.target_depression_deg - 17.0)
        for i in range(len(pairs)):  # the reference: same object, target azimuth, input depression
            name = evaluators.class_names[pairs.labels[i]]
            path = data / f"{name}_17_{int(pairs.target_azimuth_deg[i]):03d}.npy"
            reference = evaluators.classifier.scaling.normalize(torch.from_numpy(load_chip(path, 32))[None])
            torch.testing.assert_close(pairs.references[i], reference)
        with torch.no_grad():
            predicted = evaluators.depression_regressor.predict_depression_deg(pairs.targets).double()
        expected = (predicted - pairs.target_depression_deg.double()).abs().mean().item()
        assert table3[target][group]["depression_error_deg"] == pytest.approx(expected, rel=1e-6)
        # signed along the request: past the target > 0, short of it < 0; |overshoot| averages to the error
        along = torch.sign(pairs.target_depression_deg.double() - 17.0)
        expected = ((predicted - pairs.target_depression_deg.double()) * along).mean().item()
        assert table3[target][group]["depression_overshoot_deg"] == pytest.approx(expected, rel=1e-6)
        assert table3[target][group]["depression_overshoot_deg_n"] == 3
        # the true target is always closer to itself than to the view at the input's depression
        assert table3[target][group]["closer_to_target_depression"] == 1.0
        assert table3[target][group]["closer_to_target_depression_n"] == 3
        for method in (floor, round_trip, "pipe"):
            assert 0.0 <= table3[method][group]["closer_to_target_depression"] <= 1.0
            assert 0.0 <= table3[method][group]["depression_error_deg"] <= 90.0
        values, low, high = (table3[m][group] for m in ("pipe", floor, round_trip))
        key = "depression_error_deg"
        expected_gap = gap_closed(
            values[key], low[key], high[key], gap_se=math.hypot(low[f"{key}_se"], high[f"{key}_se"])
        )
        assert values["depression_gap_closed"] == pytest.approx(expected_gap, nan_ok=True)
    markdown = (out / "table3.md").read_text()
    assert "Dep. err. (deg) ↓" in markdown and "Closer to target dep. ↑" in markdown
    assert "Dep. gap closed ↑" in markdown and "Dep. overshoot (deg)" in markdown


def test_evaluate_from_the_proxy_gives_each_pairs_input_pose(tmp_path: Path, monkeypatch) -> None:
    """``--start_from proxy``: every call gets each pair's input azimuth (target azimuth minus d_az, a chip's
    own from index.csv) and depression, so that the pipeline fits its simulator proxy itself."""
    data = write_chip_folder(tmp_path / "data", azimuths_deg=tuple(range(0, 360, 60)), size=32)
    _evaluators(tmp_path / "evaluators")
    proxy = {"num_vehicles": 2, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0,
             "min_db": -60.0, "max_db": 0.0, "min_fit_score": -1.0}  # fmt: skip
    SARZero123Pipeline(**get_dummy_components(), proxy=proxy).save_pretrained(tmp_path / "pipe")
    calls: list[dict] = []
    call = SARZero123Pipeline.__call__

    def spy(self, *args, **kwargs):
        calls.append(kwargs)
        return call(self, *args, **kwargs)

    monkeypatch.setattr(SARZero123Pipeline, "__call__", spy)
    out = tmp_path / "eval"
    argv = [
        "--pipeline", str(tmp_path / "pipe"), "--evaluators", str(tmp_path / "evaluators"),
        "--data", str(data), "--protocol", "ood-B", "--n", "4", "--num-inference-steps", "2",
        "--strength", "0.5", "--start_from", "proxy", "--crop_size", "32", "--eval_batch_size", "2",
        "--num_figure_pairs", "1", "--output_dir", str(out), "--device", "cpu",
    ]  # fmt: skip
    with pytest.warns(UserWarning, match="rank-deficient"):
        evaluate.main(argv)
    assert [c["start_from"] for c in calls] == ["proxy"] * 2
    config = EvaluateConfig(**json.loads((out / "config.json").read_text()))
    pair_sets = evaluation_pairs(config, load_evaluators(tmp_path / "evaluators"), image_size=32)
    for kwargs, pairs in zip(calls, pair_sets.values(), strict=True):
        expected = (pairs.target_azimuth_deg - pairs.d_az_deg.double()) % 360.0
        azimuth = torch.as_tensor(kwargs["input_azimuth_deg"]).double()
        torch.testing.assert_close(azimuth, expected, atol=1e-4, rtol=0)  # the chips' 60 deg grid
        assert set(azimuth.round().tolist()) <= {0.0, 60.0, 120.0, 180.0, 240.0, 300.0}
        depression = torch.as_tensor(kwargs["input_depression_deg"])
        torch.testing.assert_close(depression, pairs.input_depression_deg)
    assert json.loads((out / "table3.json").read_text())["start_from"] == "proxy"


def test_evaluate_rejects_bad_depression_requests() -> None:
    with pytest.raises(ValueError, match="pass --no-same_depression"):
        EvaluateConfig(pipeline=["a"], input_depression_deg=17.0, target_depressions_deg=[30.0])
    with pytest.raises(ValueError, match=r"target_depressions_deg must lie in \(0, 90\) degrees"):
        EvaluateConfig(pipeline=["a"], target_depressions_deg=[90.0], same_depression=False)
    with pytest.raises(ValueError, match=r"input_depression_deg must lie in \(0, 90\) degrees"):
        EvaluateConfig(pipeline=["a"], input_depression_deg=0.0)
    with pytest.raises(ValueError, match="target_depressions_deg: give at least one"):
        EvaluateConfig(pipeline=["a"], target_depressions_deg=[])
    # one depression for input and target is a same-depression request
    EvaluateConfig(pipeline=["a"], input_depression_deg=17.0, target_depressions_deg=[17.0])


def test_evaluate_whose_setup_fails_leaves_no_record(tmp_path: Path) -> None:
    data = write_chip_folder(tmp_path / "data", azimuths_deg=(0.0, 90.0), size=32)
    _evaluators(tmp_path / "evaluators")
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(tmp_path / "pipe")
    out = tmp_path / "eval"
    config = EvaluateConfig(pipeline=[str(tmp_path / "pipe")], evaluators=str(tmp_path / "evaluators"),
                            data=str(data), n=5, crop_size=32, output_dir=str(out), device="cpu")  # fmt: skip
    with pytest.raises(ValueError, match="the seen group needs 5 distinct pairs"):
        stage.run_evaluate(config)
    # the run never began: the corrected command is not refused for differing from it
    assert not out.exists() or not any(out.iterdir())
    config = dataclasses.replace(config, n=2, num_figure_pairs=0)
    with pytest.warns(UserWarning, match="rank-deficient"):
        stage.run_evaluate(config)
    # a run killed before its last output is redone with --resume, and only then finished
    record = read_run_record(out)
    write_json_atomic({**record, "finished": False}, out / "run.json")
    (out / "table3.json").unlink()
    with pytest.warns(UserWarning, match="rank-deficient"):
        stage.run_evaluate(dataclasses.replace(config, resume=True))
    assert read_run_record(out)["finished"] and json.loads((out / "table3.json").read_text())["results"]


def test_the_retired_evaluation_rows_and_vae_are_refused_by_name(tmp_path: Path) -> None:
    """speckle_looks, blurred_target_sigmas_px and vae were retired: a config file at their old defaults
    reads as before; another value is refused, naming the field."""
    from sar_zero123.config import parse_config

    old = tmp_path / "old.json"
    old.write_text(json.dumps({"pipeline": ["p"], "speckle_looks": None, "blurred_target_sigmas_px": [],
                               "vae": None}))  # fmt: skip
    assert parse_config(EvaluateConfig, ["--config", str(old)]) == EvaluateConfig(pipeline=["p"])
    for name, value in (("speckle_looks", 1), ("blurred_target_sigmas_px", [1.5]), ("vae", "decoder")):
        old.write_text(json.dumps({"pipeline": ["p"], name: value}))
        with pytest.raises(ValueError, match=rf"{name}=.*, but {name} was removed: "):
            parse_config(EvaluateConfig, ["--config", str(old)])


def test_evaluate_takes_a_bundled_pipeline_by_its_name(tmp_path: Path) -> None:
    """``--pipeline sar-zero123/sim-prior-rotated`` is the bundled folder, as for every other command: its
    decibel bounds are read and checked against the evaluators' (here refused: they differ), not reported
    missing."""
    data = write_chip_folder(tmp_path / "data", azimuths_deg=(0.0, 90.0), size=32)
    _evaluators(tmp_path / "evaluators")
    for kind in ("classifier", "regressor"):
        saved = tmp_path / "evaluators" / kind / "evaluator.json"
        record = json.loads(saved.read_text())
        saved.write_text(json.dumps({**record, "scaling": {**record["scaling"], "min_db": -50.0}}))
    config = EvaluateConfig(
        pipeline=["sar-zero123/sim-prior-rotated"], evaluators=str(tmp_path / "evaluators"), data=str(data),
        n=2, crop_size=32, output_dir=str(tmp_path / "eval"), device="cpu",
    )  # fmt: skip
    with pytest.raises(ValueError, match="sim_prior_rotated expects decibel scaling"):
        stage.run_evaluate(config)


def test_a_device_this_machine_cannot_compute_on_is_refused_at_the_config(tmp_path) -> None:
    from sar_zero123.stages.evaluate import EvaluateConfig

    with pytest.raises(ValueError, match=r"device: 'meta' cannot compute here"):
        EvaluateConfig(output_dir=str(tmp_path / "eval"), device="meta")
    with pytest.raises(ValueError, match=r"device: 'gpu0' is not a torch device"):
        EvaluateConfig(output_dir=str(tmp_path / "eval"), device="gpu0")
