"""The run-folder rule: nothing overwritten, every difference named, restarts move the old run aside."""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from sar_zero123.runs.folder import (
    RUN_RECORD,
    data_identity,
    finish_run,
    open_run_folder,
    read_run_record,
)
from sar_zero123.runs.lock import is_lock_file


@dataclass
class _Config:
    learning_rate: float = 1e-3
    max_train_steps: int = 10
    seed: int = 0
    log_every: int = 5


def _snapshot(folder):
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in files}


def test_new_folder_writes_the_record(tmp_path):
    run = open_run_folder(tmp_path / "run", "finetune", _Config(), data=None)
    assert run.status == "new"
    record = json.loads((tmp_path / "run" / RUN_RECORD).read_text())
    assert record["stage"] == "finetune"
    assert record["config"] == {"learning_rate": 1e-3, "max_train_steps": 10, "seed": 0, "log_every": 5}
    assert record["data"] == {"source": "built-in simulator"}
    assert record["finished"] is False
    assert record["code_version"].startswith("0.")


def test_same_settings_without_resume_is_refused_and_nothing_changes(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "finetune", _Config())
    (folder / "model.safetensors").write_bytes(b"weights")
    finish_run(folder, ["model.safetensors"], seconds=3.0)
    before = _snapshot(folder)
    with pytest.raises(ValueError, match="already holds a finished finetune run.*--restart"):
        open_run_folder(folder, "finetune", _Config())
    assert _snapshot(folder) == before


def test_other_settings_are_refused_naming_each_difference(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "finetune", _Config())
    before = _snapshot(folder)
    with pytest.raises(ValueError) as error:
        open_run_folder(folder, "finetune", _Config(learning_rate=2e-3, seed=1), resume=True)
    message = str(error.value)
    assert "learning_rate: folder 0.001, this run 0.002" in message
    assert "seed: folder 0, this run 1" in message
    assert "max_train_steps" not in message
    with pytest.raises(ValueError, match="stage: folder 'finetune', this run 'vae'"):
        open_run_folder(folder, "vae", _Config(), resume=True)
    assert _snapshot(folder) == before


def test_a_field_the_record_lacks_counts_as_its_default(tmp_path):
    # a folder written before `log_every` existed was made with its default: it resumes at the default
    folder = tmp_path / "run"
    open_run_folder(folder, "finetune", _Config())
    record = json.loads((folder / RUN_RECORD).read_text())
    del record["config"]["log_every"]
    (folder / RUN_RECORD).write_text(json.dumps(record))
    assert open_run_folder(folder, "finetune", _Config(), resume=True).status == "continued"
    with pytest.raises(ValueError, match="log_every: folder 5, this run 7"):
        open_run_folder(folder, "finetune", _Config(log_every=7), resume=True)


def test_other_data_is_refused(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "index.csv").write_text("path,target_class\na.png,TANK\n")
    folder = tmp_path / "run"
    open_run_folder(folder, "evaluate", _Config(), data=data)
    open_run_folder(folder, "evaluate", _Config(), data=data, resume=True)  # same data: accepted
    (data / "index.csv").write_text("path,target_class\na.png,APC\n")
    with pytest.raises(ValueError, match="data: folder .*index_sha256"):
        open_run_folder(folder, "evaluate", _Config(), data=data, resume=True)


def test_data_identity_of_an_index_and_of_a_raw_tree(tmp_path):
    (tmp_path / "index.csv").write_text("x\n")
    identity = data_identity(tmp_path)
    assert identity["index_sha256"] == hashlib.sha256(b"x\n").hexdigest()
    raw = tmp_path / "raw"
    (raw / "T72").mkdir(parents=True)
    (raw / "T72" / "a.026").write_bytes(b"12345")
    first = data_identity(raw)
    assert first["files"] == 1
    (raw / "T72" / "b.026").write_bytes(b"1")
    assert data_identity(raw)["files_sha256"] != first["files_sha256"]
    with pytest.raises(FileNotFoundError, match="data: .*does not exist"):
        data_identity(tmp_path / "missing")


def test_a_foreign_non_empty_folder_is_refused(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="is not empty and holds no run.json"):
        open_run_folder(folder, "vae", _Config())
    assert _snapshot(folder) == {"notes.txt": b"mine"}


def test_restart_never_moves_a_folder_that_is_not_a_run(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"restart: output_dir '.*photos' holds no run.json: it is not"):
        open_run_folder(folder, "vae", _Config(), restart=True)
    assert _snapshot(folder) == {"notes.txt": b"mine"}
    assert sorted(p.name for p in tmp_path.iterdir() if not is_lock_file(p)) == ["photos"]  # nothing moved


def test_restart_never_moves_another_commands_run(tmp_path):
    """``generate --output_dir <a simulated dataset> --restart``: the dataset is a run folder, but of another
    command; --restart moves aside only this command's own runs."""
    folder = tmp_path / "dataset"
    open_run_folder(folder, "simulate", _Config())
    (folder / "index.csv").write_text("path\n")
    message = r"restart: output_dir '.*dataset' holds a simulate run, not a vae run"
    with pytest.raises(ValueError, match=message):
        open_run_folder(folder, "vae", _Config(), restart=True)
    assert (folder / "index.csv").read_text() == "path\n"
    assert sorted(p.name for p in tmp_path.iterdir() if not is_lock_file(p)) == ["dataset"]  # nothing moved


def test_restart_moves_the_old_run_aside(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "vae", _Config())
    (folder / "old.txt").write_text("old")
    run = open_run_folder(folder, "vae", _Config(seed=3), restart=True)
    assert run.status == "new"
    moved = [p for p in tmp_path.iterdir() if p.name.startswith("run.replaced-")]
    assert len(moved) == 1 and (moved[0] / "old.txt").read_text() == "old"
    assert read_run_record(moved[0])["config"]["seed"] == 0
    assert read_run_record(folder)["config"]["seed"] == 3
    assert not (folder / "old.txt").exists()
    with pytest.raises(ValueError, match="resume and restart: choose one"):
        open_run_folder(folder, "vae", _Config(), resume=True, restart=True)


def test_restart_of_a_folder_holding_the_inputs_is_refused_before_moving_anything(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "vae", _Config())
    data = folder / "chips"  # the data a user then put in the run folder
    data.mkdir()
    (data / "index.csv").write_text("path\n")
    message = r"restart: output_dir '.*run' holds this run's inputs \(data: .*chips\)"
    with pytest.raises(ValueError, match=message):
        open_run_folder(folder, "vae", _Config(seed=3), data=data, restart=True)
    with pytest.raises(ValueError, match=r"holds this run's inputs \(pretrained: .*chips\)"):
        open_run_folder(folder, "vae", {"seed": 3, "pretrained": str(data)}, restart=True)
    assert sorted(p.name for p in tmp_path.iterdir() if not is_lock_file(p)) == ["run"]  # nothing moved
    open_run_folder(folder, "vae", {"seed": 3, "output_dir": str(folder)}, restart=True)  # outputs are fine


def test_restart_of_a_folder_inside_an_input_or_the_package_is_refused_before_moving_anything(tmp_path):
    """``--output_dir D/chips --data D`` or ``--output_dir P/unet --pipeline P``: moving the output aside
    would move part of the input; the package's own folder (its bundled pipelines) is never moved from."""
    import sar_zero123

    data = tmp_path / "dataset"
    (data / "chips").mkdir(parents=True)
    (data / "chips" / "a.npy").write_bytes(b"0")
    with pytest.raises(ValueError, match=r"lies inside this run's inputs \(pipeline: .*dataset\)"):
        open_run_folder(data / "chips", "vae", {"seed": 3, "pipeline": str(data)}, restart=True)
    with pytest.raises(ValueError, match=r"lies inside this run's inputs \(data: .*dataset\)"):
        open_run_folder(data / "chips", "vae", _Config(), data=data, restart=True)
    assert (data / "chips" / "a.npy").read_bytes() == b"0"  # nothing moved
    bundled = Path(sar_zero123.__file__).resolve().parent / "pretrained" / "sim_prior_rotated"
    with pytest.raises(ValueError, match=r"lies inside this run's inputs \(the sar_zero123 package: "):
        config = {"start": "sar-zero123/sim-prior-rotated"}
        open_run_folder(bundled, "interpolate", config, restart=True, write=False)  # no lock in the package
    assert (bundled / "model_index.json").is_file()


def test_restart_of_the_working_directory_is_refused_before_moving_anything(tmp_path, monkeypatch):
    folder = tmp_path / "run"
    open_run_folder(folder, "vae", _Config())
    monkeypatch.chdir(folder)
    for name in (".", str(folder), ".."):  # ".." is no run folder either: refused for that first
        reason = "holds no run.json" if name == ".." else "is the working directory or holds it"
        with pytest.raises(ValueError, match=rf"restart: output_dir '{re.escape(name)}' {reason}"):
            open_run_folder(name, "vae", _Config(seed=3), restart=True)
    assert sorted(p.name for p in tmp_path.iterdir() if not is_lock_file(p)) == ["run"]  # nothing moved
    assert read_run_record(folder)["config"]["seed"] == 0


def test_resume_extends_only_what_may_extend_and_keeps_the_history(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "finetune", _Config())
    (folder / "out").write_text("1")
    finish_run(folder, ["out"], seconds=2.0)
    same = open_run_folder(folder, "finetune", _Config(), resume=True)
    assert same.status == "finished"
    longer = open_run_folder(
        folder, "finetune", _Config(max_train_steps=20), resume=True, may_extend=["max_train_steps"]
    )
    assert longer.status == "continued"
    record = read_run_record(folder)
    assert record["finished"] is False
    assert record["config"]["max_train_steps"] == 20
    assert record["continued"][0]["changed"] == {"max_train_steps": {"from": 10, "to": 20}}
    finish_run(folder, ["out"], seconds=1.5)
    assert read_run_record(folder)["seconds"] == pytest.approx(3.5)
    # may_extend applies to continuing only: a fresh reuse with more steps is still refused
    with pytest.raises(ValueError, match="max_train_steps: folder 20, this run 30"):
        open_run_folder(folder, "finetune", _Config(max_train_steps=30), may_extend=["max_train_steps"])


def test_may_differ_fields_never_block(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "finetune", _Config())
    run = open_run_folder(folder, "finetune", _Config(log_every=1), resume=True, may_differ=["log_every"])
    assert run.status == "continued"


def test_finish_run_refuses_missing_outputs(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "simulate", _Config())
    with pytest.raises(FileNotFoundError, match=r"missing outputs: \['index.csv'\]"):
        finish_run(folder, ["index.csv"])
    assert read_run_record(folder)["finished"] is False


def test_a_corrupt_record_names_the_file(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / RUN_RECORD).write_text("{not json")
    with pytest.raises(ValueError, match="run.json: not a valid run record"):
        open_run_folder(folder, "vae", _Config(), resume=True)


def test_a_finished_record_whose_outputs_are_gone_is_unfinished(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, "finetune", _Config())
    (folder / "pipeline").mkdir()
    finish_run(folder, ["pipeline"])
    (folder / "pipeline").rmdir()
    run = open_run_folder(folder, "finetune", _Config(), resume=True)
    assert run.status == "continued"
    assert read_run_record(folder)["finished"] is False
    with pytest.raises(ValueError, match=r"unfinished finetune run.*\(--resume\)"):
        open_run_folder(folder, "finetune", _Config(), resume_hint="--resume")


def test_an_options_folder_resumes_its_own_options_and_refuses_others(tmp_path):
    from sar_zero123.config.json_io import write_json_atomic
    from sar_zero123.runs.folder import check_options_folder

    out = tmp_path / "out"
    options = {"seed": 0, "weights": "abc", "new_option": 1}
    rule = dict(record="opts.json", what="export", defaults={"new_option": 1}, identity_field="weights")
    assert check_options_folder(out, options, **rule) is False  # absent: a new run
    out.mkdir()
    (out / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match=r"out: .* is not empty and has no opts.json"):
        check_options_folder(out, options, **rule)
    (out / "notes.txt").unlink()
    write_json_atomic({"seed": 0}, out / "opts.json")  # before weights and new_option were recorded
    assert check_options_folder(out, options, **rule) is True
    write_json_atomic({"seed": 0, "weights": "def"}, out / "opts.json")
    with pytest.raises(ValueError, match=r"^weights: 'def' there, 'abc' now$"):
        check_options_folder(out, options, **rule)
    write_json_atomic({"seed": 1, "weights": "abc"}, out / "opts.json")
    with pytest.raises(ValueError, match=r"holds an export made with other options \(seed: 1 there, 0 now\)"):
        check_options_folder(out, options, **rule)
