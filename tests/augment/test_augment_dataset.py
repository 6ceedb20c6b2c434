"""Tests for ``python -m sar_zero123.augment_dataset`` on the tiny pipeline and a tiny simulated dataset."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from dummies import read_the_pose

from sar_zero123.augment_dataset import (
    AUGMENT_FILE,
    PIPELINE_DIGEST,
    PROVENANCE_COLUMNS,
    PROVENANCE_FILE,
    AugmentConfig,
    main,
)
from sar_zero123.augment_dataset.plan import plan_views, select_records, view_generator
from sar_zero123.data import SCALING_FILE, ChipRecord, DecibelScaling, load_index
from sar_zero123.generate import GenerateConfig, load_input_chip
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.runs.folder import content_identity
from sar_zero123.sim import INDEX_COLUMNS, simulate_dataset

# 2 classes x 4 azimuths (0, 90, 180, 270) at 17 deg; d_el 2 keeps 19 deg inside the trained [10, 20]
CHIPS = 8
D_AZ = ["-90", "90"]


@pytest.fixture(scope="module")
def pipeline_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pipeline")
    pipe = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
    pipe.pose_projection.register_to_config(trained_d_el_deg=[-5.0, 5.0], trained_depression_deg=[10.0, 20.0])
    pipe.save_pretrained(folder)
    (folder / SCALING_FILE).write_text(json.dumps(DecibelScaling.for_unit_magnitude().to_dict()))
    return folder


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("data")
    return simulate_dataset(
        folder, classes=("TANK", "APC"), instances=1, azimuth_step_deg=90, depressions_deg=(17.0,), size=32
    )


def run_args(data_dir, pipeline_dir, out, *extra):
    return ["--data", str(data_dir), "--pipeline", str(pipeline_dir), "--out", str(out), "--d_az", *D_AZ,
            "--d_el", "2", "--num_inference_steps", "2", *extra]


@pytest.fixture(scope="module")
def augmented(data_dir, pipeline_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("augmented") / "out"
    assert main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3")) == out
    return out


def read_csv(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def view_files(out):
    return sorted(path.relative_to(out) for path in (out / "views").rglob("*.npy"))


def test_output_is_a_dataset_with_one_row_per_chip_and_request(augmented, data_dir, pipeline_dir):
    records = load_index(augmented)
    assert len(records) == CHIPS * len(D_AZ) == len(view_files(augmented))
    with open(augmented / "index.csv", newline="") as handle:
        assert next(csv.reader(handle)) == list(INDEX_COLUMNS)
    provenance = read_csv(augmented / PROVENANCE_FILE)
    assert list(provenance[0]) == [*INDEX_COLUMNS, *PROVENANCE_COLUMNS]
    sources = {(r.path.relative_to(data_dir.resolve()).as_posix()): r for r in load_index(data_dir)}
    for record, row in zip(records, provenance):
        source = sources[row["source_path"]]
        d_az = float(row["d_az_deg"])
        assert record.path == (augmented / row["path"]).resolve()
        assert (record.target_class, record.serial) == (source.target_class, source.serial)
        assert record.target_type == source.target_type
        assert record.depression_deg == 19.0 and float(row["d_el_deg"]) == 2.0
        assert record.azimuth_deg == (source.azimuth_deg + d_az) % 360.0
        assert (record.height, record.width) == (32, 32)
        assert row["generated"] == "1" and row["seed"] == "0" and row["pipeline"] == str(pipeline_dir)
        view = np.load(record.path)
        assert view.shape == (32, 32) and view.dtype == np.float32
        assert 0.0 <= view.min() and view.max() <= 1.0
    # hand-computed wraps: 270 + 90 -> 0 and 0 - 90 -> 270
    pairs = {(sources[row["source_path"]].azimuth_deg, float(row["d_az_deg"])): float(row["azimuth_deg"])
             for row in provenance}
    assert pairs[(270.0, 90.0)] == 0.0 and pairs[(0.0, -90.0)] == 270.0
    assert sorted({float(row["d_az_deg"]) for row in provenance}) == [-90.0, 90.0]
    assert json.loads((augmented / AUGMENT_FILE).read_text())["d_az"] == [-90.0, 90.0]
    described = json.loads((augmented / "views.json").read_text())  # what the arrays hold, beside them
    assert described["domain"].startswith("magnitude") and set(described["scaling"]) >= {"min_db", "max_db"}


def test_target_azimuths_selection_and_real_rows(data_dir, pipeline_dir, tmp_path):
    out = tmp_path / "out"
    main(["--data", str(data_dir), "--pipeline", str(pipeline_dir), "--out", str(out),
          "--target_azimuths_deg", "10", "350", "--classes", "TANK", "--max_chips_per_class", "2",
          "--num_inference_steps", "1", "--include_real"])
    records = load_index(out)  # real rows by absolute path, views relative
    provenance = read_csv(out / PROVENANCE_FILE)
    real = [row for row in provenance if row["generated"] == "0"]
    # 2 of the 4 TANK chips, evenly spaced in index order: azimuths 0 and 270
    assert [float(row["azimuth_deg"]) for row in real] == [0.0, 270.0]
    assert all(records[i].path == (data_dir / row["source_path"]).resolve() for i, row in enumerate(real))
    views = [row for row in provenance if row["generated"] == "1"]
    assert len(records) == 2 + 2 * 2 == len(provenance)
    # d_az = wrap(target - input) in (-180, 180]: from 0 -> +10, -10; from 270 -> +100, +80
    assert [float(row["d_az_deg"]) for row in views] == [10.0, -10.0, 100.0, 80.0]
    assert [float(row["azimuth_deg"]) for row in views] == [10.0, 350.0, 10.0, 350.0]


def test_views_agree_across_batch_sizes_up_to_float_rounding(augmented, data_dir, pipeline_dir, tmp_path):
    # Same per-view noise; PyTorch's CPU kernels round differently per batch size (about 1e-6 in
    # normalised dB here), so bytes are equal only for equal batches (test_resume_...).
    out = main(run_args(data_dir, pipeline_dir, tmp_path / "out", "--batch_size", "1"))
    assert view_files(out) == view_files(augmented)
    scaling = DecibelScaling.for_unit_magnitude()
    for path in view_files(out):
        one, three = (scaling.normalize(np.load(folder / path)) for folder in (out, augmented))
        np.testing.assert_allclose(one, three, rtol=0, atol=1e-5)
    assert (out / "index.csv").read_bytes() == (augmented / "index.csv").read_bytes()


def test_resume_generates_only_what_is_missing(augmented, data_dir, pipeline_dir, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(augmented, out)
    deleted = view_files(out)[5]
    (out / deleted).unlink()
    (out / "index.csv").unlink()
    kept = {path: (out / path).stat().st_mtime_ns for path in view_files(out)}
    main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3"))
    assert {path: (out / path).stat().st_mtime_ns for path in kept} == kept
    assert (out / deleted).read_bytes() == (augmented / deleted).read_bytes()
    assert (out / "index.csv").read_bytes() == (augmented / "index.csv").read_bytes()
    assert not list(out.rglob(".*.tmp"))
    # a folder written before strength and depression guidance resumes with their defaults, and one holding
    # the retired speckle options at their old defaults as before
    options = json.loads((out / AUGMENT_FILE).read_text())
    added = ("strength", "depression_guidance_scale")
    retired = {"speckle": False, "speckle_sigma": 10.0, "speckle_looks": None}
    old = {**{k: v for k, v in options.items() if k not in added}, **retired}
    (out / AUGMENT_FILE).write_text(json.dumps(old))
    (out / "index.csv").unlink()
    main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3"))
    assert (out / "index.csv").read_bytes() == (augmented / "index.csv").read_bytes()
    with pytest.raises(ValueError, match=r"other options \(strength: None there, 0.5 now\)"):
        main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3", "--strength", "0.5"))
    (out / AUGMENT_FILE).write_text(json.dumps({**old, "speckle_looks": 1}))  # speckled views: refused
    with pytest.raises(ValueError, match=r"speckle_looks=1, but speckle_looks was removed: "):
        main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3"))


def test_strength_starts_from_the_chip_and_is_recorded(augmented, data_dir, pipeline_dir, tmp_path):
    selection = ["--classes", "APC", "--max_chips_per_class", "1", "--num_inference_steps", "4"]
    clean = main(run_args(data_dir, pipeline_dir, tmp_path / "clean", *selection))
    kept = main(run_args(data_dir, pipeline_dir, tmp_path / "kept", *selection, "--strength", "0.25"))
    assert json.loads((kept / AUGMENT_FILE).read_text())["strength"] == 0.25
    # each view is the pipeline called with strength on its chip, with the view's own generator
    pipe = SARZero123Pipeline.from_pretrained(pipeline_dir)
    pipe.set_progress_bar_config(disable=True)
    scaling = DecibelScaling.for_unit_magnitude()
    for row in read_csv(kept / PROVENANCE_FILE):
        chip_config = GenerateConfig(pipeline=str(pipeline_dir), image=str(data_dir / row["source_path"]))
        chip = torch.from_numpy(load_input_chip(chip_config, pipe.default_image_size))[None, None]
        row_index, request = (int(part[1:]) for part in Path(row["path"]).stem.split("_")[-2:])
        expected = pipe(chip, d_az=float(row["d_az_deg"]), d_el=float(row["d_el_deg"]),
                        input_depression_deg=17.0, num_inference_steps=4, strength=0.25,
                        generator=view_generator(0, row_index, request), output_type="np").images[0, ..., 0]
        view = scaling.normalize(np.load(kept / row["path"]).astype(np.float64))
        np.testing.assert_allclose(view, expected, atol=1e-4)
        assert np.abs(view - scaling.normalize(np.load(clean / row["path"]).astype(np.float64))).max() > 1e-3
    with pytest.raises(ValueError, match=r"^strength must lie in \(0, 1\], got 0.0"):
        main(run_args(data_dir, pipeline_dir, tmp_path / "zero", "--strength", "0"))
    with pytest.raises(ValueError, match=r"^strength 0.1 x num_inference_steps 2 leaves no denoising step"):
        main(run_args(data_dir, pipeline_dir, tmp_path / "few", "--strength", "0.1"))


def test_a_proxy_pipeline_fits_a_datasets_chips_through_a_shortlist(data_dir, tmp_path, monkeypatch):
    """A pipeline that records an exhaustive proxy fit: augment fits its chips in two stages
    (DATASET_SHORTLIST, at most the bank), at each chip's index pose, and records it; each view is the
    pipeline's call with those settings."""
    from sar_zero123.model import proxy as proxy_module
    from sar_zero123.model.proxy import DATASET_SHORTLIST, with_shortlist

    proxy = {"num_vehicles": 3, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0,
             "min_db": -60.0, "max_db": 0.0, "min_fit_score": -1.0}  # fmt: skip
    folder = tmp_path / "proxy_pipeline"
    pipe = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
    SARZero123Pipeline(**pipe.components, proxy=proxy,
                       sampler={"start_from": "proxy", "strength": 0.5}).save_pretrained(folder)  # fmt: skip
    (folder / SCALING_FILE).write_text(json.dumps(DecibelScaling.for_unit_magnitude().to_dict()))
    fits = []
    original = proxy_module._fit

    def spy(settings, *args):
        fits.append(settings)
        return original(settings, *args)

    monkeypatch.setattr(proxy_module, "_fit", spy)
    out = main(["--data", str(data_dir), "--pipeline", str(folder), "--out", str(tmp_path / "out"),
                "--d_az", "90", "--classes", "APC", "--max_chips_per_class", "1",
                "--num_inference_steps", "2"])  # fmt: skip
    assert json.loads((out / AUGMENT_FILE).read_text())["proxy_shortlist"] == DATASET_SHORTLIST
    assert fits and {settings[5] for settings in fits} == {3}  # the shortlist, at most the bank's 3 vehicles
    monkeypatch.undo()
    assert with_shortlist(proxy)["shortlist"] == 3 and with_shortlist(None) is None
    assert with_shortlist({**proxy, "shortlist": 2})["shortlist"] == 2  # a recorded shortlist is kept
    loaded = SARZero123Pipeline.from_pretrained(folder)
    loaded.set_progress_bar_config(disable=True)
    loaded.register_to_config(proxy=with_shortlist(loaded.config.proxy))
    (row,) = read_csv(out / PROVENANCE_FILE)
    record = next(r for r in read_csv(data_dir / "index.csv") if r["path"] == row["source_path"])
    chip_config = GenerateConfig(pipeline=str(folder), image=str(data_dir / row["source_path"]))
    chip = torch.from_numpy(load_input_chip(chip_config, loaded.default_image_size))[None, None]
    row_index, request = (int(part[1:]) for part in Path(row["path"]).stem.split("_")[-2:])
    expected = loaded(chip, d_az=90.0, d_el=0.0, input_depression_deg=17.0, num_inference_steps=2,
                      input_azimuth_deg=float(record["azimuth_deg"]),
                      generator=view_generator(0, row_index, request),
                      output_type="np").images[0, ..., 0]  # fmt: skip
    view = DecibelScaling.for_unit_magnitude().normalize(np.load(out / row["path"]).astype(np.float64))
    np.testing.assert_allclose(view, expected, atol=1e-4)


def test_refuses_a_folder_of_other_options_or_other_files(augmented, data_dir, pipeline_dir, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(augmented, out)
    with pytest.raises(ValueError, match=r"out: .*other options \(seed: 0 there, 1 now\)"):
        main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3", "--seed", "1"))
    with pytest.raises(ValueError, match=r"out: .*other options \(batch_size: 3 there, 8 now\)"):
        main(run_args(data_dir, pipeline_dir, out))
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match=f"out: .*has no {AUGMENT_FILE}"):
        main(run_args(data_dir, pipeline_dir, other))


def test_no_resume_refuses_and_restart_moves_the_folder_aside(augmented, data_dir, pipeline_dir, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(augmented, out)
    with pytest.raises(
        ValueError, match=r"already holds this augmentation; continue it \(--resume, the default\)"
    ):
        main(run_args(data_dir, pipeline_dir, out, "--batch_size", "3", "--no-resume"))
    assert main(run_args(data_dir, pipeline_dir, out, "--seed", "1", "--restart")) == out  # other options
    (moved,) = tmp_path.glob("out.replaced-*")
    assert (moved / "index.csv").read_bytes() == (augmented / "index.csv").read_bytes()
    assert json.loads((out / AUGMENT_FILE).read_text())["seed"] == 1
    inside = tmp_path / "inside"
    shutil.copytree(augmented, inside)
    shutil.copytree(data_dir, inside / "data")
    with pytest.raises(ValueError, match=r"restart: out .* holds this run's inputs \(data: "):
        main(run_args(inside / "data", pipeline_dir, inside, "--restart"))
    assert (inside / "data" / "index.csv").is_file()
    # the other way round: an out folder inside the data (its chips/) is not moved aside either
    data = tmp_path / "data_copy"
    shutil.copytree(data_dir, data)
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    with pytest.raises(ValueError, match=r"restart: out .* lies inside this run's inputs \(data: "):
        main(run_args(data, pipeline_dir, data / "chips", "--restart"))
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before
    # a folder that is not an augmentation is never moved aside
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"restart: out .*mine' holds no augment.json: it is not an"):
        main(run_args(data_dir, pipeline_dir, mine, "--restart"))
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]


def test_refuses_to_resume_onto_a_pipeline_whose_weights_changed(augmented, data_dir, pipeline_dir, tmp_path):
    pipeline = tmp_path / "pipeline"
    shutil.copytree(pipeline_dir, pipeline)
    out = tmp_path / "out"
    shutil.copytree(augmented, out)
    record = json.loads((out / AUGMENT_FILE).read_text())
    assert record[PIPELINE_DIGEST] == content_identity(pipeline_dir)  # the weights, recorded
    record["pipeline"] = str(pipeline.resolve())
    (out / AUGMENT_FILE).write_text(json.dumps(record))
    args = run_args(data_dir, pipeline, out, "--batch_size", "3")
    assert main(args) == out  # the same weights under another name: a resume
    other = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
    with torch.no_grad():  # the same architecture and file names, other weights
        other.unet.conv_in.weight.add_(0.1)
    other.pose_projection.register_to_config(trained_d_el_deg=[-5.0, 5.0],
                                             trained_depression_deg=[10.0, 20.0])  # fmt: skip
    other.save_pretrained(pipeline)
    with pytest.raises(ValueError, match=r"^pipeline: .* holds other weights than the ones the views in .*"
                                         r"resuming would mix two models' views"):  # fmt: skip
        main(args)
    # a folder recorded before the digest existed resumes (its weights are unknown)
    del record[PIPELINE_DIGEST]
    (out / AUGMENT_FILE).write_text(json.dumps(record))
    assert main(args) == out
    with pytest.raises(FileNotFoundError, match="pipeline folder not found: '.*missing'"):
        main(run_args(data_dir, tmp_path / "missing", tmp_path / "new"))
    with pytest.raises(FileNotFoundError, match="'sar-zero123/nope': no bundled pipeline .* bundled: "):
        main(run_args(data_dir, "sar-zero123/nope", tmp_path / "new"))


@pytest.mark.parametrize(("d_el", "field"), [("6", "trained_d_el_deg"), ("4", "trained_depression_deg")])
def test_refuses_d_el_outside_the_trained_ranges_before_generating(data_dir, pipeline_dir, tmp_path, d_el,
                                                                   field):
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=rf"^d_el: .*pose_projection\.config\.{field}"):
        main([*run_args(data_dir, pipeline_dir, out), "--d_el", d_el])
    assert not out.exists()


def test_refuses_chips_smaller_than_the_pipeline_or_off_its_scaling(pipeline_dir, tmp_path):
    small = simulate_dataset(tmp_path / "small", classes=("TANK",), instances=1, azimuth_step_deg=180,
                             depressions_deg=(17.0,), size=16)
    with pytest.raises(ValueError, match=r"^data: 2 chip\(s\) are smaller than the pipeline's 32 px"):
        main(run_args(small, pipeline_dir, tmp_path / "a"))
    # an index that claims the 16 px chips are 64 px is not believed: the files are read
    index = (small / "index.csv").read_text().replace(",16,16", ",64,64")
    assert index.count(",64,64") == 2
    (small / "index.csv").write_text(index)
    claimed = r"^data: index.csv lists .* as 64x64 \(height, width\), but the file is 16x16"
    with pytest.raises(ValueError, match=claimed):
        main(run_args(small, pipeline_dir, tmp_path / "a2"))
    assert not (tmp_path / "a2").exists()
    chips = simulate_dataset(tmp_path / "chips", classes=("TANK",), instances=1, azimuth_step_deg=180,
                             depressions_deg=(17.0,), size=32)
    scaling = tmp_path / "scaling.json"  # clutter lies far below -10 dB: most pixels clip
    scaling.write_text(json.dumps(DecibelScaling(min_db=-10.0, max_db=0.0).to_dict()))
    with pytest.raises(ValueError, match=r"^data: chip .* outside the scaling's dB range"):
        main(run_args(chips, pipeline_dir, tmp_path / "b", "--scaling_file", str(scaling)))


def test_plan_and_selection_by_hand():
    records = [ChipRecord(path=f"/d/{c}{k}.npy", target_class=c, serial="s", depression_deg=17.0,
                          azimuth_deg=90.0 * k) for c in ("A", "B") for k in range(4)]
    # B's chips are rows 4-7; 3 of 4 evenly spaced: positions round(0, 1.5, 3) = 0, 2, 3
    assert [row for row, _ in select_records(records, classes=["B"], max_chips_per_class=3)] == [4, 6, 7]
    assert [row for row, _ in select_records(records, depressions_deg=[15.0, 17.0])] == list(range(8))
    views = plan_views([(3, records[3])], d_az=[100.0], d_el=[0.0, -2.0])
    assert [(v.azimuth_deg, v.d_el_deg, v.depression_deg, v.request_index) for v in views] == [
        (10.0, 0.0, 17.0, 0), (10.0, -2.0, 15.0, 1)]
    assert views[1].path.as_posix() == "views/A/A3_r000003_v001.npy"
    with pytest.raises(ValueError, match="^classes: "):
        select_records(records, classes=["C"])
    with pytest.raises(ValueError, match="^d_el: "):
        plan_views([(0, records[0])], d_az=[0.0], d_el=[-20.0])


def test_config_refuses_bad_values(data_dir, pipeline_dir):
    base = {"data": str(data_dir), "pipeline": str(pipeline_dir), "out": "x"}
    with pytest.raises(ValueError, match="^d_az/target_azimuths_deg: "):
        AugmentConfig(**base)
    with pytest.raises(ValueError, match="^target_azimuths_deg "):
        AugmentConfig(**base, target_azimuths_deg=[360.0])
    with pytest.raises(ValueError, match="^batch_size "):
        AugmentConfig(**base, d_az=[30.0], batch_size=0)
    with pytest.raises(FileNotFoundError, match="^data: "):
        AugmentConfig(**{**base, "data": str(data_dir / "missing")}, d_az=[30.0])
    with pytest.raises(ValueError, match=r"^`d_el` must lie in \(-90, 90\) degrees .*got 90$"):
        AugmentConfig(**base, d_az=[30.0], d_el=[0.0, -90.0])  # no depression in (0, 90) reaches a target
    with pytest.raises(ValueError, match=r"^`d_az` must lie in \[-1e\+06, 1e\+06\] degrees .*got 2e\+06$"):
        AugmentConfig(**base, d_az=[2e6])


def test_depression_guidance_reaches_each_view_and_is_recorded(data_dir, tmp_path):
    folder = tmp_path / "pipeline"
    pipe = build_sar_zero123("tiny", input_depression=True)
    read_the_pose(pipe.pose_projection)  # a fresh projection ignores d_el, and so any guidance on it
    pipe.pose_projection.register_to_config(trained_d_el_deg=[-5.0, 5.0], trained_depression_deg=[10.0, 20.0])
    pipe.save_pretrained(folder)
    (folder / SCALING_FILE).write_text(json.dumps(DecibelScaling.for_unit_magnitude().to_dict()))
    pipe.set_progress_bar_config(disable=True)
    options = ["--classes", "APC", "--max_chips_per_class", "1", "--depression_guidance_scale", "2"]
    out = main(run_args(data_dir, folder, tmp_path / "guided", *options))
    assert json.loads((out / AUGMENT_FILE).read_text())["depression_guidance_scale"] == 2.0
    scaling = DecibelScaling.for_unit_magnitude()
    for row in read_csv(out / PROVENANCE_FILE):
        chip_config = GenerateConfig(pipeline=str(folder), image=str(data_dir / row["source_path"]))
        chip = torch.from_numpy(load_input_chip(chip_config, pipe.default_image_size))[None, None]
        row_index, request = (int(part[1:]) for part in Path(row["path"]).stem.split("_")[-2:])
        written = scaling.normalize(np.load(out / row["path"]).astype(np.float64))
        for guidance in (2.0, 0.0):  # the guided view is the one written; the unguided one differs
            expected = pipe(
                chip, d_az=float(row["d_az_deg"]), d_el=float(row["d_el_deg"]), input_depression_deg=17.0,
                num_inference_steps=2, depression_guidance_scale=guidance,
                generator=view_generator(0, row_index, request), output_type="np",
            ).images[0, ..., 0]
            distance = np.abs(written - expected).max()
            assert distance < 1e-4 if guidance else distance > 1e-3
    with pytest.raises(ValueError, match=r"^depression_guidance_scale must lie in \[0, 100\], got -1.0"):
        main(run_args(data_dir, folder, tmp_path / "bad", "--depression_guidance_scale", "-1"))


def test_chips_no_simulator_vehicle_fits_are_skipped_and_counted(data_dir, tmp_path, caplog):
    """Under a proxy pipeline, a chip whose best fit scores below proxy.min_fit_score gets no views (the
    others do), named in a warning; a selection of such chips only is refused."""
    from sar_zero123.model.proxy import fit_scores

    def proxy_pipeline(floor: float) -> Path:
        proxy = {"num_vehicles": 3, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0,
                 "min_db": -60.0, "max_db": 0.0, "min_fit_score": floor}  # fmt: skip
        folder = tmp_path / f"pipe_{floor:.6f}"
        pipe = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
        SARZero123Pipeline(**pipe.components, proxy=proxy).save_pretrained(folder)
        (folder / SCALING_FILE).write_text(json.dumps(DecibelScaling.for_unit_magnitude().to_dict()))
        return folder

    from sar_zero123.augment_dataset.plan import select_records
    from sar_zero123.data import load_index

    records = [record for _, record in select_records(load_index(data_dir), ["APC"], None, 2)]  # augment's
    folder = proxy_pipeline(-1.0)
    size = SARZero123Pipeline.from_pretrained(folder).default_image_size
    chips = [load_input_chip(GenerateConfig(pipeline=str(folder), image=str(r.path)), size) for r in records]
    scores = fit_scores(torch.from_numpy(np.stack(chips))[:, None],
                        torch.tensor([r.azimuth_deg for r in records]),
                        torch.tensor([r.depression_deg for r in records]),
                        {**json.loads((folder / "model_index.json").read_text())["proxy"]})  # fmt: skip
    assert scores[0] != scores[1]
    common = ["--data", str(data_dir), "--d_az", "90", "--classes", "APC", "--max_chips_per_class", "2",
              "--num_inference_steps", "2"]  # fmt: skip
    with caplog.at_level("WARNING"):
        out = main(
            [*common, "--pipeline", str(proxy_pipeline(float(scores.mean()))), "--out", str(tmp_path / "o")]
        )
    (row,) = read_csv(out / PROVENANCE_FILE)  # one chip fits, one view
    assert (data_dir / row["source_path"]).resolve() == Path(records[int(np.argmax(scores))].path).resolve()
    assert "skipped 1 of 2 chips: no simulator vehicle fits them" in caplog.text
    with pytest.raises(ValueError, match="data: no selected chip holds a vehicle the simulator proxy fits"):
        main([*common, "--pipeline", str(proxy_pipeline(1.0)), "--out", str(tmp_path / "none")])


def test_module_help_names_the_module_command():
    import subprocess
    import sys

    command = [sys.executable, "-m", "sar_zero123.augment_dataset", "--help"]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    assert done.returncode == 0
    assert done.stdout.startswith("usage: python -m sar_zero123.augment_dataset [-h]")
