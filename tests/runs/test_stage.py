"""A stage's setup that fails leaves nothing behind in a folder it opened empty (issue 39 item 11)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sar_zero123.runs.folder import RUN_RECORD, finish_run, release_output_folder
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails


def _open(path: Path, batch: int, resume: bool = False):
    return open_stage_folder(
        path, "finetune", {"batch": batch}, data={"data": None}, resume=resume, restart=False
    )


def test_a_failed_setup_of_a_new_run_withdraws_its_record_and_files_and_the_corrected_run_starts(tmp_path):
    run = tmp_path / "run"
    folder = _open(run, batch=100000)
    assert folder.status == "new" and (run / RUN_RECORD).is_file()
    with pytest.raises(ValueError, match="fewer than a global batch"), withdrawn_if_setup_fails(folder):
        (run / "data" / "sim_data").mkdir(parents=True)  # the simulated data cache, then the refusal
        (run / "data" / "sim_data" / "index.csv").write_text("path\n")
        (run / "logs").mkdir()
        raise ValueError("data: 1152 training pairs, fewer than a global batch of 100000")
    assert run.is_dir() and list(run.iterdir()) == []
    release_output_folder(run)
    corrected = _open(run, batch=4)  # not refused for differing from a run that never began
    assert corrected.status == "new"
    assert json.loads((run / RUN_RECORD).read_text())["config"] == {"batch": 4}
    release_output_folder(run)


def test_a_failed_setup_of_a_continued_run_keeps_everything(tmp_path):
    run = tmp_path / "run"
    _open(run, batch=4)
    (run / "checkpoint-1").mkdir()
    (run / "checkpoint-1" / "model.safetensors").write_bytes(b"weights")
    release_output_folder(run)
    folder = _open(run, batch=4, resume=True)
    assert folder.status == "continued"
    with pytest.raises(KeyboardInterrupt), withdrawn_if_setup_fails(folder):
        raise KeyboardInterrupt
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint-1", RUN_RECORD]
    finish_run(folder, ["checkpoint-1"])
