"""Weight interpolation of a fine-tuned pipeline with its start (WiSE-FT): closed forms and refusals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from sar_zero123.interpolate import interpolate_pipelines, interpolate_state, main


def _pipeline(folder: Path, unet: dict[str, torch.Tensor], width: int = 4) -> Path:
    """A pipeline folder as interpolate_pipelines reads it: model_index.json, configs and weights."""
    (folder / "unet").mkdir(parents=True)
    (folder / "scheduler").mkdir()
    (folder / "model_index.json").write_text(json.dumps({"_class_name": "SARZero123Pipeline"}))
    (folder / "unet" / "config.json").write_text(json.dumps({"width": width, "_name_or_path": str(folder)}))
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps({"source": folder.name}))
    save_file(unet, folder / "unet" / "diffusion_pytorch_model.safetensors")
    return folder


def test_interpolated_weights_are_the_convex_mix_and_the_rest_is_the_fine_tune(tmp_path: Path) -> None:
    half = torch.float16
    start_weights = {"w": torch.zeros(2, 3), "h": torch.full((2,), 2.0, dtype=half), "n": torch.tensor([1])}
    tuned_weights = {"w": torch.ones(2, 3), "h": torch.full((2,), 4.0, dtype=half), "n": torch.tensor([7])}
    start = _pipeline(tmp_path / "start", start_weights)
    tuned = _pipeline(tmp_path / "tuned", tuned_weights)
    out = interpolate_pipelines(start, tuned, 0.25, tmp_path / "mix")
    mixed = load_file(out / "unet" / "diffusion_pytorch_model.safetensors")
    assert torch.equal(mixed["w"], torch.full((2, 3), 0.25))
    assert mixed["h"].dtype == torch.float16 and torch.equal(
        mixed["h"], torch.full((2,), 2.5, dtype=torch.float16)
    )
    assert torch.equal(mixed["n"], torch.tensor([7]))  # integers: the fine-tune's
    # every other file is the fine-tune's; nothing else is left beside the output
    assert json.loads((out / "scheduler" / "scheduler_config.json").read_text()) == {"source": "tuned"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mix", "start", "tuned"]
    # the endpoints: alpha = 1 is the fine-tune, alpha = 0 the start (as floats)
    ends = {a: load_file(interpolate_pipelines(start, tuned, a, tmp_path / f"a{a}") / "unet" /
                         "diffusion_pytorch_model.safetensors") for a in (0.0, 1.0)}  # fmt: skip
    assert torch.equal(ends[1.0]["w"], torch.ones(2, 3)) and torch.equal(ends[0.0]["w"], torch.zeros(2, 3))
    # the command: output_dir/pipeline under the run-folder rule (the same command again is refused,
    # --resume returns the finished folder untouched)
    flags = [
        "--start",
        str(start),
        "--finetuned",
        str(tuned),
        "--alpha",
        "0.5",
        "--output_dir",
        str(tmp_path / "cli"),
    ]
    assert main(flags) == tmp_path / "cli" / "pipeline"
    record = json.loads((tmp_path / "cli" / "run.json").read_text())
    assert record["finished"] and record["stage"] == "interpolate" and record["config"]["alpha"] == 0.5
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "cli").rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match="already holds a finished interpolate run"):
        main(flags)
    assert main([*flags, "--resume"]) == tmp_path / "cli" / "pipeline"
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "cli").rglob("*") if p.is_file()} == before


def test_interpolate_state_matches_a_float64_reference() -> None:
    generator = torch.Generator().manual_seed(0)
    a, b = torch.randn(5, 7, generator=generator), torch.randn(5, 7, generator=generator)
    mixed = interpolate_state({"x": a}, {"x": b}, 0.3)["x"]
    torch.testing.assert_close(mixed, (0.7 * a.double() + 0.3 * b.double()).float())


def test_pipelines_of_other_architectures_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    start = _pipeline(tmp_path / "start", {"w": torch.zeros(2, 3)})
    with pytest.raises(
        ValueError, match=r"unet: tensor 'w' is \(2, 3\) torch.float32 in the start and \(3, 2\)"
    ):
        interpolate_pipelines(start, _pipeline(tmp_path / "t1", {"w": torch.ones(3, 2)}), 0.5, tmp_path / "o")
    with pytest.raises(ValueError, match="unet: the two pipelines do not hold the same tensors"):
        interpolate_pipelines(start, _pipeline(tmp_path / "t2", {"v": torch.ones(2, 3)}), 0.5, tmp_path / "o")
    with pytest.raises(ValueError, match=r"unet: the two pipelines' configs differ in \['width'\]"):
        interpolate_pipelines(start, _pipeline(tmp_path / "t3", {"w": torch.ones(2, 3)}, width=8), 0.5,
                              tmp_path / "o")  # fmt: skip
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".o.*"))
    tuned = _pipeline(tmp_path / "t4", {"w": torch.ones(2, 3)})
    with pytest.raises(ValueError, match=r"alpha must lie in \[0, 1\]"):
        interpolate_pipelines(start, tuned, 1.5, tmp_path / "o")
    with pytest.raises(ValueError, match="output_dir: .* exists"):
        interpolate_pipelines(start, tuned, 0.5, tmp_path / "t4")
    with pytest.raises(FileNotFoundError, match="start: expected a pipeline folder with model_index.json"):
        interpolate_pipelines(tmp_path / "nowhere", tuned, 0.5, tmp_path / "o")


def test_a_start_the_fine_tune_did_not_start_from_is_refused_before_any_write(tmp_path: Path) -> None:
    from sar_zero123.runs.folder import weights_identity

    start = _pipeline(tmp_path / "start", {"w": torch.zeros(2)})
    other = _pipeline(tmp_path / "other", {"w": torch.full((2,), 5.0)})
    tuned = _pipeline(tmp_path / "tuned", {"w": torch.ones(2)})
    index = {"_class_name": "SARZero123Pipeline",
             "lineage": {"start": str(start), "start_weights": weights_identity(start)}}  # fmt: skip
    (tuned / "model_index.json").write_text(json.dumps(index))
    out = tmp_path / "cli"
    flags = ["--finetuned", str(tuned), "--alpha", "0.5", "--output_dir", str(out)]
    with pytest.raises(ValueError, match=r"start: the fine-tune .* started from .*start.*, not from .*other"):
        main(["--start", str(other), *flags])
    assert not out.exists()  # refused before the folder is opened: the corrected command runs
    # a model card edited beside the weights is the same start
    (start / "README.md").write_text("a model card")
    assert main(["--start", str(start), *flags]) == out / "pipeline"
    # a killed run's scratch folder is removed when the run is redone
    shutil.rmtree(out / "pipeline")  # killed before the rename: only the scratch folder is left
    (out / ".pipeline.abc123").mkdir()
    (out / ".pipeline.abc123" / "partial.safetensors").write_bytes(b"x" * 100)
    record = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**record, "finished": False}))
    assert main(["--start", str(start), *flags, "--resume"]) == out / "pipeline"
    assert sorted(p.name for p in out.iterdir()) == ["pipeline", "run.json"]


def test_a_truncated_weight_file_is_refused_by_name_and_the_corrected_command_runs(tmp_path: Path) -> None:
    start = _pipeline(tmp_path / "start", {"w": torch.zeros(64)})
    tuned = _pipeline(tmp_path / "tuned", {"w": torch.ones(64)})
    weights = tuned / "unet" / "diffusion_pytorch_model.safetensors"
    good = weights.read_bytes()
    weights.write_bytes(good[: len(good) // 2])
    out = tmp_path / "cli"
    flags = ["--start", str(start), "--finetuned", str(tuned), "--alpha", "0.5", "--output_dir", str(out)]
    with pytest.raises(ValueError, match=r"finetuned: '.*diffusion_pytorch_model.safetensors' is not a"):
        main(flags)
    assert not out.exists()
    weights.write_bytes(good)
    assert main(flags) == out / "pipeline"


def test_a_fine_tune_recording_its_estimator_mixes_with_its_start_and_the_mix_loads(tmp_path: Path) -> None:
    from sar_zero123 import SARZero123Pipeline
    from sar_zero123.data import DecibelScaling
    from sar_zero123.model.build import build_sar_zero123
    from sar_zero123.runs.folder import weights_identity
    from sar_zero123.training.finetuning import export_finetuned

    pipe = build_sar_zero123("tiny", estimate_input_azimuth=True, seed=3)
    pipe.save_pretrained(tmp_path / "start")
    with torch.no_grad():  # the fine-tune moved the estimator
        next(pipe.azimuth_estimator.parameters()).add_(0.5)
    lineage = {"start": str(tmp_path / "start"), "start_weights": weights_identity(tmp_path / "start")}
    export_finetuned(tmp_path / "tuned", pipe, DecibelScaling(), lineage=lineage)
    assert SARZero123Pipeline.from_pretrained(tmp_path / "tuned").pose_projection.config.trained_estimator
    out = main(["--start", str(tmp_path / "start"), "--finetuned", str(tmp_path / "tuned"), "--alpha", "0.5",
                "--output_dir", str(tmp_path / "mix")])  # fmt: skip
    mixed = SARZero123Pipeline.from_pretrained(out)  # the record of neither run's estimator is kept
    assert mixed.pose_projection.config.trained_estimator is None
    first = next(iter(pipe.azimuth_estimator.state_dict()))
    start_file = tmp_path / "start" / "azimuth_estimator" / "diffusion_pytorch_model.safetensors"
    expected = load_file(start_file)[first] + 0.25  # halfway to the fine-tune's estimator
    torch.testing.assert_close(mixed.azimuth_estimator.state_dict()[first], expected)
