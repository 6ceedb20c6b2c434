"""benchmarks/learning_curve.py: chunked training, one row per evaluation, resume from the rows written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from benchmarks import learning_curve


def fake_stages(monkeypatch: pytest.MonkeyPatch, calls: list) -> None:
    """run_finetune writes what a run leaves (UNet weights, a validation record); the evaluation of a chunk
    reads a Table III whose seen error is 100 - steps / 100."""

    def finetune(config) -> Path:
        steps = config.max_train_steps
        run_dir = Path(config.output_dir)
        calls.append(("finetune", config.size, steps, config.resume_from_checkpoint))
        calls.append(("run_dir", run_dir.name, config.learning_rate, config.train_batch_size))
        unet = run_dir / "pipeline" / "unet"
        unet.mkdir(parents=True, exist_ok=True)
        weights = {"a": torch.zeros(3, 4), "b": torch.zeros(5)}
        save_file(weights, str(unet / "diffusion_pytorch_model.safetensors"))
        (run_dir / "validation").mkdir(exist_ok=True)
        record = {"step": steps, "validation/sensitivity_pose_t500": steps / 1e4,
                  "validation/pose_following_error_deg": 90.0 - steps / 100}  # fmt: skip
        with (run_dir / "validation" / "metrics.jsonl").open("a") as handle:
            handle.write(json.dumps(record) + "\n")
        return run_dir

    def evaluate(config) -> Path:
        assert config.resume and config.pipeline == [str(Path(config.output_dir).parent / "pipeline")]
        calls.append(("evaluate", int(Path(config.output_dir).name.split("_")[1])))
        return Path(config.output_dir)

    def load_evaluation(folder: Path) -> dict:
        steps = int(folder.name.split("_")[1])
        views = {"azimuth_error_deg": 100 - steps / 100, "azimuth_error_deg_se": 1.0,
                 "azimuth_gap_closed": steps / 1e4, "accuracy": 50.0, "accuracy_se": 2.0}  # fmt: skip
        return {"table3": {"model": {"seen": views, "unseen": views}}}

    monkeypatch.setattr(learning_curve, "run_finetune", finetune)
    monkeypatch.setattr(learning_curve, "run_evaluate", evaluate)
    monkeypatch.setattr(learning_curve, "load_evaluation", load_evaluation)


def argv_for(tmp_path: Path, *extra: str) -> list[str]:
    for name in ("data", "vae", "evaluators"):
        (tmp_path / name).mkdir(exist_ok=True)
    return ["--data", str(tmp_path / "data"), "--vae", str(tmp_path / "vae"), "--evaluators",
            str(tmp_path / "evaluators"), "--protocol", "ood-TANK", "--work_dir", str(tmp_path / "runs"),
            "--out", str(tmp_path / "curve.jsonl"), *extra]  # fmt: skip


def test_one_row_per_chunk_and_a_rerun_continues_after_the_last_row(tmp_path, monkeypatch) -> None:
    calls: list = []
    fake_stages(monkeypatch, calls)
    chunks = ("--sizes", "micro", "--chunk_steps", "200", "--max_steps")
    rows = learning_curve.main(argv_for(tmp_path, *chunks, "400"))
    assert [(row["size"], row["steps"]) for row in rows] == [("micro", 200), ("micro", 400)]
    run_dir = ("run_dir", "micro_lr0.001_b16", 0.001, 16)
    assert calls == [("finetune", "micro", 200, "latest"), run_dir, ("evaluate", 200),
                     ("finetune", "micro", 400, "latest"), run_dir, ("evaluate", 400)]  # fmt: skip
    assert (rows[1]["learning_rate"], rows[1]["train_batch_size"]) == (1e-3, 16)
    assert rows[1]["seen/azimuth_error_deg"] == pytest.approx(96.0)
    assert rows[1]["pose_following_error_deg"] == pytest.approx(86.0)
    assert rows[1]["unet_parameters"] == 17  # 3 x 4 + 5, from the safetensors header
    chunk_seconds = json.loads((tmp_path / "runs" / "micro_lr0.001_b16" / "chunk_seconds.json").read_text())
    assert set(chunk_seconds) == {"200", "400"}
    assert rows[0]["train_seconds"] == chunk_seconds["200"]
    assert rows[1]["train_seconds"] == pytest.approx(chunk_seconds["200"] + chunk_seconds["400"], abs=0.05)
    # a longer curve keeps the two points written and trains only the new chunk
    calls.clear()
    rows = learning_curve.main(argv_for(tmp_path, *chunks, "600", "--plot", str(tmp_path / "curve.png")))
    assert calls == [("finetune", "micro", 600, "latest"), run_dir, ("evaluate", 600)]
    assert [row["steps"] for row in rows] == [200, 400, 600]
    assert len((tmp_path / "curve.jsonl").read_text().splitlines()) == 3
    assert (tmp_path / "curve.png").stat().st_size > 0
    # another batch size in the same --work_dir and --out is its own curve: own folder, all its chunks
    calls.clear()
    rows = learning_curve.main(argv_for(tmp_path, *chunks, "400", "--train_batch_size", "32"))
    other = ("run_dir", "micro_lr0.001_b32", 0.001, 32)
    assert calls == [("finetune", "micro", 200, "latest"), other, ("evaluate", 200),
                     ("finetune", "micro", 400, "latest"), other, ("evaluate", 400)]  # fmt: skip
    assert [(row["train_batch_size"], row["steps"]) for row in rows] == [(16, 200), (16, 400), (16, 600),
                                                                        (32, 200), (32, 400)]  # fmt: skip


def test_bad_arguments_are_refused_before_any_training(tmp_path, monkeypatch) -> None:
    calls: list = []
    fake_stages(monkeypatch, calls)
    with pytest.raises(SystemExit):
        learning_curve.main(argv_for(tmp_path, "--sizes", "huge"))
    with pytest.raises(SystemExit):
        learning_curve.main(argv_for(tmp_path, "--sizes", "micro", "--chunk_steps", "6", "--max_steps", "3"))
    argv = argv_for(tmp_path, "--sizes", "micro")
    argv[argv.index("--vae") + 1] = str(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="--vae"):
        learning_curve.main(argv)
    assert calls == []


def test_a_chunk_trained_before_a_crash_is_evaluated_without_training_it_again(tmp_path, monkeypatch) -> None:
    calls: list = []
    fake_stages(monkeypatch, calls)
    evaluate = learning_curve.run_evaluate

    def crash(config) -> Path:
        raise KeyboardInterrupt

    monkeypatch.setattr(learning_curve, "run_evaluate", crash)
    argv = argv_for(tmp_path, "--sizes", "micro", "--chunk_steps", "200", "--max_steps", "200")
    with pytest.raises(KeyboardInterrupt):
        learning_curve.main(argv)
    seconds = json.loads((tmp_path / "runs" / "micro_lr0.001_b16" / "chunk_seconds.json").read_text())["200"]
    monkeypatch.setattr(learning_curve, "run_evaluate", evaluate)
    calls.clear()
    rows = learning_curve.main(argv)
    assert calls == [("evaluate", 200)]
    assert rows[0]["train_seconds"] == seconds
