"""Bad inputs refused at the library's boundary, each with a message that names the problem.

One test per class of failure: index rows outside physical ranges, inputs too small to be chips,
pipeline folders with a missing or mismatched component, unreadable JSON and image files, plain numbers
where tensors were expected, and requests whose work a user can make unbounded.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import torch
from dummies import dummy_images, get_dummy_components

import sar_zero123.augment_dataset as augment
from sar_zero123.augment_dataset import MAX_BATCH_SIZE, MAX_REQUESTS_PER_CHIP, AugmentConfig, augment_dataset
from sar_zero123.config import read_config_file
from sar_zero123.data import (
    MIN_CHIP_SIZE,
    SCALING_FILE,
    ChipRecord,
    DecibelScaling,
    load_chip,
    load_index,
    load_magnitude,
)
from sar_zero123.encoder import SAREncoder, SAREncoderConfig
from sar_zero123.evaluation.evaluators import SARClassifier, load_evaluator
from sar_zero123.evaluation.metrics import azimuth_error_deg
from sar_zero123.evaluation.scoring import MAX_POSE_REQUESTS, pose_following
from sar_zero123.generate import MAX_VIEWS, GenerateConfig, load_input_chip
from sar_zero123.generate import main as generate_main
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.sim.contact_sheet import MAX_SHEET_CELLS, contact_sheet, procedural_contact_sheet
from sar_zero123.sim.corpus import corpus_views

TINY_ENCODER = {"image_size": 16, "in_channels": 1, "cifar_stem": True, "depths": (1,), "hidden_sizes": (8,)}


def _write_png(path: Path, side: int) -> Path:
    pixels = np.random.default_rng(0).integers(0, 256, size=(side, side), dtype=np.uint8)
    PIL.Image.fromarray(pixels, mode="L").save(path)
    return path


# ------------------------------------------------------------------------------ out-of-range metadata
@pytest.mark.parametrize(
    ("depression", "azimuth", "column", "expected"),
    [
        ("400", "10", "depression_deg", r"\(0, 90\)"),
        ("-10", "10", "depression_deg", r"\(0, 90\)"),
        ("91", "10", "depression_deg", r"\(0, 90\)"),
        ("90", "10", "depression_deg", r"\(0, 90\)"),
        ("0", "10", "depression_deg", r"\(0, 90\)"),
        ("17", "360", "azimuth_deg", r"\[0, 360\)"),
        ("17", "-0.5", "azimuth_deg", r"\[0, 360\)"),
    ],
    ids=["depression_400", "depression_-10", "depression_91", "depression_90", "depression_0", "azimuth_360",
         "azimuth_-0.5"],
)  # fmt: skip
def test_index_rows_outside_physical_ranges_are_refused_with_file_and_line(
    tmp_path: Path, depression: str, azimuth: str, column: str, expected: str
) -> None:
    for name in ("a.npy", "b.npy"):
        np.save(tmp_path / name, np.full((32, 32), 0.5, dtype=np.float32))
    index = tmp_path / "index.csv"
    index.write_text(
        "path,target_class,serial,depression_deg,azimuth_deg\n"
        "a.npy,T72,s1,17,10\n"
        f"b.npy,T72,s1,{depression},{azimuth}\n"
    )
    where = re.escape(f"{index}:3")
    with pytest.raises(ValueError, match=rf"{where}: column '{column}' must lie in {expected}"):
        load_index(tmp_path)
    # records built in code obey the same ranges, naming the chip
    with pytest.raises(ValueError, match=r"b\.npy: depression_deg must lie in \(0, 90\) degrees, got 95"):
        ChipRecord(path=tmp_path / "b.npy", target_class="T72", serial="s1", depression_deg=95, azimuth_deg=0)
    # the writers stay inside what the reader accepts: the corpus rounds 359.99996 to 0, never to 360
    azimuths, depressions = corpus_views(0, 0, 20_000, (10.0, 60.0), 0.3)
    assert azimuths.min() >= 0.0 and azimuths.max() < 360.0
    assert depressions.min() > 0.0 and depressions.max() < 90.0


# ------------------------------------------------------------------------ inputs too small to be chips
def test_images_too_small_to_be_chips_are_refused_with_the_minimum_named(tmp_path: Path) -> None:
    tiny = _write_png(tmp_path / "one_pixel.png", 1)
    assert MIN_CHIP_SIZE == 16
    assert load_magnitude(tiny).shape == (1, 1)  # the raw reader still reads it
    expected = r"one_pixel\.png: a 1x1 image is too small to be a chip; expected at least 16x16 pixels"
    with pytest.raises(ValueError, match=expected + r" \(MIN_CHIP_SIZE = 16\)"):
        load_chip(tiny, size=32)
    # a chip at the minimum is upsampled as before; a small output size needs only that size
    assert load_chip(_write_png(tmp_path / "sixteen.png", 16), size=32).shape == (32, 32)
    assert load_chip(_write_png(tmp_path / "eight.png", 8), size=8).shape == (8, 8)

    pipeline = tmp_path / "pipeline"
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(pipeline)
    out = tmp_path / "views"
    argv = ["--pipeline", str(pipeline), "--image", str(tiny), "--d-az", "30", "60", "90",
            "--num-inference-steps", "1", "--output_dir", str(out)]  # fmt: skip
    with pytest.raises(ValueError, match=r"one_pixel\.png'?: a 1x1 image is too small to be a chip"):
        generate_main(argv)
    assert not list(out.glob("view_*")) and not (out / "contact_sheet.png").exists()


# -------------------------------------------------------------------- unclear component-loading errors
@pytest.fixture(scope="module")
def estimator_pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("estimator_pipeline")
    build_sar_zero123("tiny", estimate_input_azimuth=True).save_pretrained(folder)
    return folder


def _remove_unet_weights(folder: Path) -> None:
    (folder / "unet" / "diffusion_pytorch_model.safetensors").unlink()


def _remove_estimator(folder: Path) -> None:
    shutil.rmtree(folder / "azimuth_estimator")


def _mismatch_estimator_config(folder: Path) -> None:
    config_path = folder / "azimuth_estimator" / "config.json"
    config = json.loads(config_path.read_text())
    config["code_dim"] = 3  # the saved head has 2 + 16 outputs
    config_path.write_text(json.dumps(config))


def _break_pose_projection_json(folder: Path) -> None:
    (folder / "pose_projection" / "config.json").write_text('{"in_features": 36,\n')


def _truncate_vae_weights(folder: Path) -> None:
    weights = folder / "vae" / "diffusion_pytorch_model.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])


@pytest.mark.parametrize(
    ("mutate", "error", "pattern"),
    [
        (_remove_unet_weights, FileNotFoundError,
         r"component 'unet' \(UNet2DConditionModel\) has no weights: expected "
         r"diffusion_pytorch_model\.safetensors in '.*/broken/unet'"),
        (_remove_estimator, FileNotFoundError,
         r"component 'azimuth_estimator' \(AzimuthEstimator\) is missing: model_index\.json lists it, but "
         r"'.*/broken' has no folder 'azimuth_estimator'"),
        (_mismatch_estimator_config, ValueError,
         r"component 'azimuth_estimator' \(AzimuthEstimator\) cannot be loaded from '.*/broken/"
         r"azimuth_estimator': its config does not match its weights: the config builds head\.(weight|bias)"),
        (_break_pose_projection_json, ValueError,
         r"/broken/pose_projection/config\.json: invalid JSON at line 2 column 1 .*"
         r"component 'pose_projection'"),
        (_truncate_vae_weights, ValueError,
         r"component 'vae' \(AutoencoderKL\) cannot be loaded from '.*/broken/vae'"),
    ],
    ids=["unet_weights_missing", "estimator_folder_removed", "estimator_config_mismatch",
         "pose_projection_json_invalid", "vae_weights_truncated"],
)  # fmt: skip
def test_pipeline_folder_errors_name_the_component_the_file_and_the_folder(
    estimator_pipeline: Path, tmp_path: Path, mutate, error: type[Exception], pattern: str
) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(estimator_pipeline, broken)
    mutate(broken)
    # its manifest names the changed file first; without one (an older folder), the component's own check
    with pytest.raises(ValueError, match=r"manifest\.json .*verify_manifest=False|listed in manifest\.json"):
        SARZero123Pipeline.from_pretrained(broken)
    (broken / "manifest.json").unlink()
    with pytest.raises(error, match=pattern) as raised:
        SARZero123Pipeline.from_pretrained(broken)
    message = str(raised.value)
    assert ".bin" not in message and "Cannot load  because" not in message
    assert SARZero123Pipeline.from_pretrained(estimator_pipeline).azimuth_estimator is not None


# --------------------------------------------------------------------- unreadable JSON and image files
def test_invalid_json_and_corrupt_images_name_the_file(tmp_path: Path) -> None:
    # decibel_scaling.json beside a pipeline, as generate and augment_dataset read it
    pipeline = tmp_path / "pipeline"
    pipeline.mkdir()
    (pipeline / SCALING_FILE).write_text('{"min_db": -60.0, "max_db": }')
    chip = _write_png(tmp_path / "chip.png", 40)
    config = GenerateConfig(pipeline=str(pipeline), image=str(chip))
    scaling_file = re.escape(str(pipeline / SCALING_FILE))
    with pytest.raises(ValueError, match=rf"{scaling_file}: invalid JSON at line 1"):
        load_input_chip(config, 32)
    (pipeline / SCALING_FILE).write_text('{"min_db": -60.0}')
    with pytest.raises(ValueError, match=r"decibel_scaling\.json: decibel scaling dict lacks \['max_db'\]"):
        DecibelScaling.from_file(pipeline / SCALING_FILE)

    # evaluator.json, and weights that do not fit what it describes
    torch.manual_seed(0)
    evaluator = SARClassifier(SAREncoderConfig(**TINY_ENCODER), ["A", "B"]).save_pretrained(tmp_path / "clf")
    saved = json.loads((evaluator / "evaluator.json").read_text())
    (evaluator / "evaluator.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"clf/evaluator\.json: invalid JSON at line 1 column 2"):
        load_evaluator(evaluator)
    saved["encoder"]["hidden_sizes"] = [16]
    (evaluator / "evaluator.json").write_text(json.dumps(saved))
    with pytest.raises(ValueError, match=r"clf/model\.safetensors: the weights do not fit the evaluator in"):
        load_evaluator(evaluator)

    # a SAR encoder's config.json and a --config file
    encoder = SAREncoder(SAREncoderConfig(**TINY_ENCODER)).save_pretrained(tmp_path / "encoder")
    (encoder / "config.json").write_text("[1, 2")
    with pytest.raises(ValueError, match=r"encoder/config\.json: invalid JSON at line 1 column 6"):
        SAREncoder.from_pretrained(encoder)
    (tmp_path / "run.json").write_text('{"seed": 1,}')
    with pytest.raises(ValueError, match=r"run\.json: invalid JSON at line 1 column 12"):
        read_config_file(tmp_path / "run.json")

    # a truncated PNG, bytes that are no image, and a cut .npy
    whole = _write_png(tmp_path / "whole.png", 64).read_bytes()
    (tmp_path / "cut.png").write_bytes(whole[: len(whole) // 2])
    (tmp_path / "text.png").write_bytes(b"not an image")
    np.save(tmp_path / "chip.npy", np.ones((32, 32), dtype=np.float32))
    (tmp_path / "cut.npy").write_bytes((tmp_path / "chip.npy").read_bytes()[:100])
    for name in ("cut.png", "text.png"):
        with pytest.raises(ValueError, match=rf"{name}: cannot read the \.png image .*truncated, corrupt"):
            load_magnitude(tmp_path / name)
    words = r"cut\.npy: cannot read the \.npy (header|array) .*truncated or corrupt"
    with pytest.raises(ValueError, match=words):
        load_magnitude(tmp_path / "cut.npy")


# -------------------------------------------------------------------------- plain numbers as inputs
def test_azimuth_error_deg_takes_plain_numbers_and_tensors() -> None:
    error = azimuth_error_deg(350.0, 10.0)
    assert isinstance(error, float) and error == 20.0
    assert azimuth_error_deg(10, 350) == 20.0 and azimuth_error_deg(np.float32(5.0), 185.0) == 180.0
    torch.testing.assert_close(
        azimuth_error_deg([350.0, 90.0], 10.0), torch.tensor([20.0, 80.0], dtype=torch.float64)
    )
    torch.testing.assert_close(azimuth_error_deg(torch.tensor([350.0, 0.5]), 10.0), torch.tensor([20.0, 9.5]))
    with pytest.raises(ValueError, match="predicted_deg contains non-finite azimuths"):
        azimuth_error_deg(float("nan"), 10.0)


# ----------------------------------------------------------------------------------- unbounded work
def test_user_sizable_work_is_refused_with_the_bound_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    many = [float(d) for d in range(5000)]
    with pytest.raises(ValueError, match=rf"d_az: at most {MAX_VIEWS} views per call .*got 5000"):
        GenerateConfig(image="chip.png", d_az=many)
    with pytest.raises(ValueError, match=r"image_size must lie in \[1, 1024\] pixels, got 100000"):
        GenerateConfig(image="chip.png", image_size=100_000)

    sheet = tmp_path / "sheet.png"
    with pytest.raises(ValueError, match=r"azimuths_deg: expected 1 to 64 azimuths .*got 5000"):
        contact_sheet(sheet, azimuths_deg=many)
    with pytest.raises(ValueError, match=rf"seeds: at most {MAX_SHEET_CELLS} chips per sheet, got 100000"):
        procedural_contact_sheet(sheet, seeds=range(100_000))
    assert not sheet.exists()

    with pytest.raises(ValueError, match=rf"batch_size must be <= {MAX_BATCH_SIZE} views per call"):
        AugmentConfig(data="d", out="o", d_az=[30.0], batch_size=100_000)
    with pytest.raises(ValueError, match=rf"at most {MAX_REQUESTS_PER_CHIP} requests per chip, got 5000 x 3"):
        AugmentConfig(data="d", out="o", d_az=many, d_el=[0.0, 1.0, 2.0])
    # the total is checked from the index, before the pipeline loads (a bound of 4 stands for 10^6 here)
    data = tmp_path / "data"
    data.mkdir()
    for name in ("a.npy", "b.npy"):
        np.save(data / name, np.full((32, 32), 0.5, dtype=np.float32))
    (data / "index.csv").write_text(
        "path,target_class,serial,depression_deg,azimuth_deg\na.npy,T72,s1,17,10\nb.npy,T72,s1,17,40\n"
    )
    monkeypatch.setattr(augment, "MAX_AUGMENT_VIEWS", 4)
    config = AugmentConfig(data=str(data), out=str(tmp_path / "augmented"), d_az=[10.0, 20.0, 30.0])
    with pytest.raises(ValueError, match=r"data: 2 chips x 3 requests = 6 views, more than 4; select fewer"):
        augment_dataset(config)
    assert not (tmp_path / "augmented").exists()
    with pytest.raises(ValueError, match=rf"d_az_deg: expected 1 to {MAX_POSE_REQUESTS} requests"):
        pose_following(None, torch.zeros(1, 1, 32, 32), 0.0, None, d_az_deg=many)

    pipe = SARZero123Pipeline(**get_dummy_components())
    with pytest.raises(ValueError, match=r"`num_inference_steps` must be <= 1000 \(the scheduler's"):
        pipe(dummy_images(), d_az=30.0, num_inference_steps=100_000)
