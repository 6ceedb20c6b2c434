"""Smoke and resume tests of `train/pretrain_simclr.py` on a fabricated chip folder."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from sar_zero123.data import ChipRecord, write_index
from sar_zero123.encoder import SAREncoder
from sar_zero123.runs.manifest import write_manifest
from train import pretrain_simclr

SCRIPT = Path(__file__).resolve().parents[2] / "train" / "pretrain_simclr.py"
TINY_ARGS = [
    "--image_size", "16",
    "--hidden_sizes", "8", "8", "8", "8",
    "--embedding_size", "8",
    "--global_batch_size", "4",
    "--monotonic_q", "16",
]  # fmt: skip


def write_chip_folder(root: Path, per_group: int = 4) -> Path:
    """Two classes x two depressions of 8-bit PNG chips with an index.csv."""
    rng = np.random.default_rng(0)
    records = []
    for target_class in ("A", "B"):
        for depression in (15.0, 17.0):
            for i in range(per_group):
                path = root / f"{target_class}_{int(depression)}_{i}.png"
                image = rng.integers(0, 256, size=(20, 20), dtype=np.uint8)
                Image.fromarray(image).save(path)
                records.append(ChipRecord(path, target_class, "s1", depression, 360.0 * i / per_group))
    write_index(records, root)
    return root


@pytest.fixture(scope="module")
def chip_folder(tmp_path_factory) -> Path:
    return write_chip_folder(tmp_path_factory.mktemp("chips"))


def test_two_steps_write_encoder_metrics_and_logs(chip_folder, tmp_path):
    out = tmp_path / "run"
    metrics = pretrain_simclr.main(
        ["--data", str(chip_folder), "--output_dir", str(out), "--max_train_steps", "2", *TINY_ARGS]
    )
    assert metrics["steps"] == 2 and metrics["train_chips"] == 8  # the 17 deg split only
    assert math.isfinite(metrics["final_loss"]) and metrics["images_per_second"] > 0
    assert 0 < metrics["augment_fraction"] < 1
    assert metrics["collapse_loss"] == pytest.approx(math.log(7))
    assert json.loads((out / "metrics.json").read_text())["steps"] == 2
    saved = json.loads((out / "config.json").read_text())
    assert saved["preset"] == "speckle+monotonic" and saved["learning_rate"] == 0.06
    assert json.loads((out / "decibel_scaling.json").read_text())["min_db"] == -60.0
    assert list((out / "logs").rglob("events.out.tfevents.*")) or list(out.rglob("events.out.tfevents.*"))
    encoder = SAREncoder.from_pretrained(out / "encoder")
    assert encoder(torch.rand(2, 1, 16, 16)).shape == (2, 8)


def test_max_train_minutes_stops_after_the_first_step_past_it_and_saves_the_encoder(chip_folder, tmp_path):
    out = tmp_path / "run"
    argv = ["--data", str(chip_folder), "--output_dir", str(out), "--max_train_steps", "50", *TINY_ARGS]
    metrics = pretrain_simclr.main([*argv, "--max_train_minutes", "1e-9"])
    assert metrics["steps"] == 1 and (out / "encoder" / "model.safetensors").is_file()
    with pytest.raises(ValueError, match="max_train_minutes must be > 0"):
        pretrain_simclr.main([*argv[:3], str(tmp_path / "other"), *argv[4:], "--max_train_minutes", "0"])


def test_resume_from_latest_reproduces_an_uninterrupted_run(chip_folder, tmp_path):
    script = pretrain_simclr
    common = ["--data", str(chip_folder), "--report_to", "none", "--preset", "simclr-full", *TINY_ARGS]
    common += ["--max_train_steps", "3", "--checkpointing_steps", "1"]
    straight = script.main([*common, "--output_dir", str(tmp_path / "a")])
    # emulate a crash right after step 1: keep only the first checkpoint and the unfinished run record
    crashed = tmp_path / "b"
    shutil.copytree(tmp_path / "a" / "checkpoint-1", crashed / "checkpoint-1")
    record = json.loads((tmp_path / "a" / "run.json").read_text())
    for key in ("finished_at", "outputs", "seconds", "results"):
        record.pop(key)
    (crashed / "run.json").write_text(json.dumps({**record, "finished": False}))
    resumed = script.main([*common, "--output_dir", str(crashed), "--resume_from_checkpoint", "latest"])
    assert resumed["start_step"] == 1 and resumed["steps"] == 3
    assert resumed["final_loss"] == pytest.approx(straight["final_loss"], rel=1e-5)
    a = SAREncoder.from_pretrained(tmp_path / "a" / "encoder").state_dict()
    b = SAREncoder.from_pretrained(crashed / "encoder").state_dict()
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    ("flag", "value", "field"),
    [
        ("--preset", "rotate", "preset"),
        ("--global_batch_size", "0", "global_batch_size"),
        ("--speckle_sigma", "-1", "sigma"),
    ],
)
def test_bad_config_names_the_field(flag, value, field):
    with pytest.raises(ValueError, match=field):
        pretrain_simclr.main([flag, value])


@pytest.mark.slow
def test_two_process_run_gathers_negatives_from_the_global_batch(
    chip_folder, tmp_path, run_two_process, rendezvous_port
):
    out = tmp_path / "ddp"
    command = [
        "accelerate", "launch", "--multi_gpu", "--num_processes", "2", "--num_machines", "1",
        "--mixed_precision", "no", "--dynamo_backend", "no", "--main_process_ip", "127.0.0.1",
        "--main_process_port", str(rendezvous_port), str(SCRIPT),
        "--data", str(chip_folder), "--output_dir", str(out), "--report_to", "none",
        "--max_train_steps", "2", *TINY_ARGS,
    ]  # fmt: skip
    run_two_process(command, marker=str(out), timeout=180)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_processes"] == 2 and metrics["steps"] == 2
    # 2 chips per process, but each anchor is contrasted with all 2 x 4 - 1 = 7 other global views
    assert metrics["collapse_loss"] == pytest.approx(math.log(7))
    assert math.isfinite(metrics["final_loss"])
    assert SAREncoder.from_pretrained(out / "encoder")(torch.rand(2, 1, 16, 16)).shape == (2, 8)


def test_diverging_run_stops_with_a_clear_error_and_writes_no_encoder(chip_folder, tmp_path):
    out = tmp_path / "diverge"
    argv = ["--data", str(chip_folder), "--output_dir", str(out), "--report_to", "none", *TINY_ARGS]
    with pytest.raises(FloatingPointError, match=r"training diverged at step \d+: loss=(nan|inf)"):
        pretrain_simclr.main([*argv, "--max_train_steps", "6", "--learning_rate", "1e30"])
    assert not (out / "encoder").exists()


@pytest.mark.parametrize(
    ("argv", "error", "match"),
    [
        (
            ["--global_batch_size", "1"],
            ValueError,
            r"global_batch_size must be >= 2 \(NT-Xent needs negatives\), got 1",
        ),
        (["--output_dir", "{file}"], NotADirectoryError, r"output_dir: .*is a file; expected a folder"),
    ],
    ids=["batch-1-gives-loss-0", "output-dir-is-a-file"],
)
def test_degenerate_settings_are_refused_before_any_work(tmp_path, argv, error, match):
    (tmp_path / "file").write_text("x")
    argv = [a.replace("{file}", str(tmp_path / "file")) for a in argv]
    with pytest.raises(error, match=match):
        pretrain_simclr.main(argv)


def test_resume_with_another_learning_rate_is_refused_and_config_json_kept(chip_folder, tmp_path):
    out = tmp_path / "run"
    common = ["--data", str(chip_folder), "--output_dir", str(out), "--report_to", "none", *TINY_ARGS]
    pretrain_simclr.main([*common, "--max_train_steps", "2", "--checkpointing_steps", "1"])
    with pytest.raises(ValueError, match=r"learning_rate: checkpoint 0.06, this run 0.5"):
        pretrain_simclr.main([*common, "--max_train_steps", "2", "--learning_rate", "0.5",
                            "--resume_from_checkpoint", "latest"])  # fmt: skip
    assert json.loads((out / "config.json").read_text())["learning_rate"] == 0.06


def test_checkpoint_written_with_the_old_batch_size_name_resumes(chip_folder, tmp_path):
    """Checkpoints written before issue 12 store `batch_size`; it is compared as `global_batch_size`."""
    out = tmp_path / "run"
    common = ["--data", str(chip_folder), "--output_dir", str(out), "--report_to", "none", *TINY_ARGS]
    common += ["--max_train_steps", "2", "--checkpointing_steps", "1"]
    pretrain_simclr.main(common)
    checkpoint = out / "checkpoint-1"
    state = json.loads((checkpoint / "run_state.json").read_text())
    state["config"]["batch_size"] = state["config"].pop("global_batch_size")
    (checkpoint / "run_state.json").write_text(json.dumps(state))
    write_manifest(checkpoint)
    resumed = ["--output_dir", str(tmp_path / "resumed"), "--resume_from_checkpoint", str(checkpoint)]
    metrics = pretrain_simclr.main([*common, *resumed])
    assert metrics["start_step"] == 1 and metrics["steps"] == 2
    with pytest.raises(ValueError, match=r"global_batch_size: checkpoint 4, this run 2"):
        pretrain_simclr.main([*common, "--global_batch_size", "2", "--resume_from_checkpoint", "latest"])


def test_reusing_a_finished_run_is_refused_and_restart_moves_it_aside(chip_folder, tmp_path):
    out = tmp_path / "run"
    common = ["--data", str(chip_folder), "--output_dir", str(out), "--report_to", "none", *TINY_ARGS]
    common += ["--max_train_steps", "1"]
    first = pretrain_simclr.main(common)
    before = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    with pytest.raises(ValueError, match=r"already holds a finished simclr run.*--restart"):
        pretrain_simclr.main(common)
    differs = r"Differences: .*preset: folder 'speckle\+monotonic', this run 'simclr-full'"
    with pytest.raises(ValueError, match=differs):
        pretrain_simclr.main([*common, "--preset", "simclr-full", "--resume_from_checkpoint", "latest"])
    # a continued finished run does no work and returns its metrics
    assert pretrain_simclr.main([*common, "--resume_from_checkpoint", "latest"]) == first
    assert {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before
    pretrain_simclr.main([*common, "--restart"])
    (aside,) = tmp_path.glob("run.replaced-*")
    assert {p.relative_to(aside): p.read_bytes() for p in sorted(aside.rglob("*")) if p.is_file()} == before
    assert json.loads((out / "run.json").read_text())["finished"] is True
