"""Smoke tests of `train/table1.py` (Table I) and `train/synth_to_real.py` (Table II) on fabricated data,
and of the run-folder rule of their stages (`run_table1`, `run_synth_to_real`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import sar_zero123.stages.simclr as simclr_stage
import sar_zero123.stages.synth_to_real as synth_to_real_stage
import sar_zero123.stages.table1 as table1_stage
from sar_zero123.data import ChipRecord, write_index
from sar_zero123.encoder import SAREncoder, SAREncoderConfig
from train import synth_to_real, table1

TINY_MODEL = ["--hidden_sizes", "8", "8", "8", "8", "--embedding_size", "8"]


def snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under `folder` with its bytes and modification time."""
    return {
        p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def no_work(*args, **kwargs):
    raise AssertionError("a finished folder continued with --resume must not be worked on")


def write_chip_folder(root: Path, per_group: int = 6) -> Path:
    """Two classes (bright/dark blobs) x two depressions of 8-bit PNG chips with an index.csv."""
    rng = np.random.default_rng(0)
    root.mkdir(parents=True)
    records = []
    for k, target_class in enumerate(("A", "B")):
        for depression in (15.0, 17.0):
            for i in range(per_group):
                image = rng.integers(0, 60, size=(20, 20))
                image[5:15, 5:15] += 150 if k == 0 else 40
                path = root / f"{target_class}_{int(depression)}_{i}.png"
                Image.fromarray(image.astype(np.uint8)).save(path)
                records.append(ChipRecord(path, target_class, "s1", depression, 360.0 * i / per_group))
    write_index(records, root)
    return root


def test_table1_trains_probes_and_writes_tables_and_tsne(tmp_path):
    data = write_chip_folder(tmp_path / "chips")
    out = tmp_path / "table1"
    args = ["--data", str(data), "--output_dir", str(out), "--image-size", "16", "--global_batch_size", "4"]
    args += ["--presets", "simclr-full", "speckle+monotonic", "--max_train_steps", "1", "--probe_epochs", "2"]
    result = table1.main([*args, *TINY_MODEL, "--tsne_points", "12"])
    assert set(result["rows"]) == {"simclr-full", "speckle+monotonic", table1_stage.FLOOR_ROW}
    assert (result["train_chips"], result["test_chips"]) == (12, 12)
    for name, row in result["rows"].items():
        assert 0.0 <= row["linear_accuracy"] <= 100.0 and 0.0 <= row["knn_accuracy"] <= 100.0
        assert 0.0 <= row["mlp_azimuth_error_deg"] <= 180.0 and 0.0 <= row["knn_azimuth_error_deg"] <= 180.0
        if name != table1_stage.FLOOR_ROW:
            assert row["pretrain"]["steps"] == 1 and math.isfinite(row["pretrain"]["final_loss"])
    # the floor: an untrained encoder of the first row's architecture, probed the same way
    floor = result["rows"][table1_stage.FLOOR_ROW]
    assert floor["pretrain"] is None and floor["encoder"] == "untrained"
    assert floor["architecture"]["hidden_sizes"] == [8, 8, 8, 8] and floor["architecture"]["image_size"] == 16
    assert json.loads((out / "table1.json").read_text())["paper"]["speckle+monotonic"]["knn_accuracy"] == 99.7
    markdown = (out / "table1.md").read_text()
    assert "| speckle+monotonic |" in markdown and "98.7 / 9.8 | 99.7 / 3.1" in markdown
    assert f"| {table1_stage.FLOOR_ROW} |" in markdown
    assert (out / "tsne.png").stat().st_size > 10_000
    # existing encoders are probed, not retrained: same numbers
    again = table1.main(
        [*args, *TINY_MODEL, "--no-tsne", "--output_dir", str(tmp_path / "again"),
         "--encoders", str(out / "simclr-full"), str(out / "speckle+monotonic" / "encoder")]
    )  # fmt: skip
    # the table says the encoders were given, not which SimCLR epochs this config would have trained
    again_markdown = (tmp_path / "again" / "table1.md").read_text()
    assert "(trained elsewhere)" in again_markdown and "SimCLR epochs" not in again_markdown
    assert "| preset | linear acc. % |" in again_markdown
    for preset, row in result["rows"].items():
        assert again["rows"][preset]["knn_accuracy"] == row["knn_accuracy"]
        assert again["rows"][preset]["linear_accuracy"] == pytest.approx(row["linear_accuracy"])


def test_table1_reports_both_speckle_presets_beside_the_paper_row():
    script = table1
    assert {"speckle+monotonic", "speckle+monotonic-as-run"} <= set(script.Table1Config().presets)
    row = {"linear_accuracy": 90.0, "mlp_azimuth_error_deg": 12.5, "knn_accuracy": 95.0,
           "knn_azimuth_error_deg": 4.0}
    rows = {"speckle+monotonic": row, "speckle+monotonic-as-run": {**row, "knn_accuracy": 96.0}}
    markdown = script.format_markdown(rows, script.Table1Config())
    assert "| speckle+monotonic | 90.0 | 12.5 | 95.0 | 4.0 | 98.7 / 9.8 | 99.7 / 3.1 |" in markdown
    assert "| speckle+monotonic-as-run | 90.0 | 12.5 | 96.0 | 4.0 | 98.7 / 9.8 | 99.7 / 3.1 |" in markdown
    assert "probability 0.95" in markdown


def test_table1_rejects_mismatched_encoders(tmp_path):
    with pytest.raises(ValueError, match="encoders"):
        table1.main(["--presets", "speckle", "monotonic", "--encoders", str(tmp_path)])
    with pytest.raises(ValueError, match="presets"):
        table1.main(["--presets", "rotate"])


def write_sample_folder(root: Path) -> Path:
    """SAMPLE layout: png_images/qpm/{real,synth}/<class>/<name>.png, two classes, four poses each."""
    rng = np.random.default_rng(0)
    for target, level in (("2s1", 200), ("m1", 60)):
        for az in (10, 20, 30, 40):
            for kind, offset in (("real", 0), ("synth", 20)):
                folder = root / "png_images" / "qpm" / kind / target
                folder.mkdir(parents=True, exist_ok=True)
                image = rng.integers(0, 30, size=(16, 16)) + offset
                image[4:12, 4:12] += level - offset
                name = f"{target}_{kind}_A_elevDeg_017_azCenter_{az:03d}_00_serial_s1.png"
                Image.fromarray(np.clip(image, 0, 255).astype(np.uint8)).save(folder / name)
    return root


def test_synth_to_real_writes_table2_and_classifiers(tmp_path):
    sample = write_sample_folder(tmp_path / "SAMPLE")
    out = tmp_path / "table2"
    args = ["--sample", str(sample), "--output_dir", str(out), "--image_size", "16", "--epochs", "2"]
    args += ["--train_batch_size", "4", "--rows", "none", "speckle+monotonic", *TINY_MODEL]
    result = synth_to_real.main(args)
    assert result["pairs"] == 8 and result["class_names"] == ["2S1", "M1"]
    assert set(result["rows"]) == {"none", "speckle+monotonic"}
    for row in result["rows"].values():
        assert row["real_accuracy"] in {0.0, 12.5, 25.0, 37.5, 50.0, 62.5, 75.0, 87.5, 100.0}
    assert "| speckle+monotonic |" in (out / "table2.md").read_text()
    assert (out / "none" / "classifier" / "evaluator.json").is_file()


def test_synth_to_real_requires_sample():
    with pytest.raises(ValueError, match="sample"):
        synth_to_real.main([])


def test_table1_folder_refuses_other_settings_returns_with_resume_and_moves_aside_with_restart(
    tmp_path, monkeypatch
):
    data = write_chip_folder(tmp_path / "chips", per_group=3)
    torch.manual_seed(0)
    encoder = SAREncoder(SAREncoderConfig(image_size=16, hidden_sizes=(8, 8, 8, 8), embedding_size=8))
    encoder.save_pretrained(tmp_path / "encoder")
    out = tmp_path / "table1"
    args = ["--data", str(data), "--output_dir", str(out), "--image_size", "16", "--presets", "simclr-full",
            "--encoders", str(tmp_path / "encoder"), "--probe_epochs", "2", "--no-tsne"]  # fmt: skip
    first = table1.main(args)
    record = json.loads((out / "run.json").read_text())
    assert (record["stage"], record["finished"]) == ("table1", True)
    assert record["outputs"] == ["table1.json", "table1.md"]
    assert len(record["data"]["encoders"]) == 1 and len(record["data"]["data"]["index_sha256"]) == 64
    before = snapshot(out)
    other = r"holds a table1 run made with other settings.*probe_epochs: folder 2, this run 3.*--restart"
    with pytest.raises(ValueError, match=other):
        table1.main([*args, "--probe_epochs", "3"])
    same = r"already holds a finished table1 run with these settings; continue it explicitly \(--resume\)"
    with pytest.raises(ValueError, match=same):
        table1.main(args)
    assert snapshot(out) == before
    # --resume: the finished table as it is, without any work
    monkeypatch.setattr(table1_stage, "run_probes", no_work)
    assert table1.main([*args, "--resume"]) == first
    assert snapshot(out) == before
    monkeypatch.undo()
    # --restart: the old table moved aside untouched, a new one built in its place
    table1.main([*args, "--probe_epochs", "3", "--restart"])
    (aside,) = tmp_path.glob("table1.replaced-*")
    assert snapshot(aside) == before
    assert json.loads((out / "run.json").read_text())["config"]["probe_epochs"] == 3


def test_table1_resumed_keeps_each_finished_simclr_run(tmp_path, monkeypatch):
    data = write_chip_folder(tmp_path / "chips", per_group=3)
    out = tmp_path / "table1"
    args = ["--data", str(data), "--output_dir", str(out), "--image_size", "16", "--global_batch_size", "4",
            "--presets", "simclr-full", "--max_train_steps", "1", "--probe_epochs", "2"]  # fmt: skip
    args += TINY_MODEL

    def killed(*args, **kwargs):
        raise RuntimeError("killed after pretraining")

    # a session killed after the preset's SimCLR run: the table is unfinished, the SimCLR run finished
    monkeypatch.setattr(table1_stage, "extract_features", killed)
    with pytest.raises(RuntimeError, match="killed"):
        table1.main(args)
    assert json.loads((out / "simclr-full" / "run.json").read_text())["finished"] is True
    assert json.loads((out / "run.json").read_text())["finished"] is False
    monkeypatch.undo()
    with pytest.raises(ValueError, match=r"already holds an? unfinished table1 run .*\(--resume\)"):
        table1.main(args)
    # --resume: the SimCLR run is taken as finished (its training loop is never entered), the probes run
    monkeypatch.setattr(simclr_stage, "train_simclr_steps", no_work)
    result = table1.main([*args, "--resume"])
    assert result["rows"]["simclr-full"]["pretrain"]["steps"] == 1
    assert json.loads((out / "run.json").read_text())["finished"] is True


def test_synth_to_real_folder_refuses_other_settings_resumes_rows_and_moves_aside_with_restart(
    tmp_path, monkeypatch
):
    sample = write_sample_folder(tmp_path / "SAMPLE")
    out = tmp_path / "table2"
    args = ["--sample", str(sample), "--output_dir", str(out), "--image_size", "16", "--epochs", "1",
            "--train_batch_size", "4", "--rows", "none", "speckle+monotonic", *TINY_MODEL]  # fmt: skip
    train_row, trained = synth_to_real_stage.train_row, []

    def recorded(row, *rest):
        trained.append(row)
        if len(trained) == 2:
            raise RuntimeError("killed during the second row")
        return train_row(row, *rest)

    # a session killed during the second row: --resume keeps the first row's classifier
    monkeypatch.setattr(synth_to_real_stage, "train_row", recorded)
    with pytest.raises(RuntimeError, match="killed"):
        synth_to_real.main(args)
    with pytest.raises(ValueError, match=r"already holds an? unfinished synth_to_real run .*\(--resume\)"):
        synth_to_real.main(args)
    first = synth_to_real.main([*args, "--resume"])
    assert trained == ["none", "speckle+monotonic", "speckle+monotonic"]
    assert set(first["rows"]) == {"none", "speckle+monotonic"}
    record = json.loads((out / "run.json").read_text())
    assert (record["stage"], record["finished"]) == ("synth_to_real", True)
    before = snapshot(out)
    # other settings or other SAMPLE files: refused, naming the difference, nothing on disk changed
    with pytest.raises(ValueError, match=r"epochs: folder 1, this run 2.*--restart"):
        synth_to_real.main([*args, "--epochs", "2"])
    (sample / "png_images" / "qpm" / "real" / "m1" / "notes.txt").write_text("added")
    with pytest.raises(ValueError, match=r"data: folder .*'sample'"):
        synth_to_real.main([*args, "--resume"])
    (sample / "png_images" / "qpm" / "real" / "m1" / "notes.txt").unlink()
    assert snapshot(out) == before
    # --resume: the finished table as it is, without any work; --restart: moved aside untouched
    monkeypatch.setattr(synth_to_real_stage, "train_row", no_work)
    monkeypatch.setattr(synth_to_real_stage, "load_chips", no_work)
    assert synth_to_real.main([*args, "--resume"]) == first
    assert snapshot(out) == before
    monkeypatch.undo()
    assert synth_to_real.main([*args, "--restart"])["rows"].keys() == first["rows"].keys()
    (aside,) = tmp_path.glob("table2.replaced-*")
    assert snapshot(aside) == before
