"""Smoke and consistency tests for ``python -m sar_zero123.generate`` on the tiny pipeline."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import PIL.Image
import pytest
import torch
from dummies import get_dummy_components, read_the_pose
from mstar_files import write_mstar

import sar_zero123.pretrained as pretrained
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.generate import (
    GenerateConfig,
    chip_depression_deg,
    generate_views,
    load_input_chip,
    main,
    resolve_input_depression,
)
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import SamplerSettings
from sar_zero123.pretrained import SIM_PRIOR_ROTATED
from sar_zero123.sim.proxy import ProxyBank


def sampler(steps: int, **fields: float) -> SamplerSettings:
    """A sampler of ``steps`` steps at zero-1-to-3's guidance scale 3, the rest as given."""
    return SamplerSettings(num_inference_steps=steps, guidance_scale=3.0, **fields)


@pytest.fixture(scope="module")
def pipeline_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pipeline")
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def chip_png(tmp_path_factory):
    pixels = np.random.default_rng(0).integers(0, 256, size=(40, 40), dtype=np.uint8)
    path = tmp_path_factory.mktemp("chip") / "chip.png"
    PIL.Image.fromarray(pixels, mode="L").save(path)
    return path


def test_main_writes_one_png_and_npy_per_view_and_a_contact_sheet(pipeline_dir, chip_png, tmp_path):
    out = tmp_path / "views"
    argv = ["--pipeline", str(pipeline_dir), "--image", str(chip_png), "--d-az", "30", "60", "90",
            "--d-el", "0", "--output_dir", str(out), "--num-inference-steps", "2", "--seed", "4"]
    assert main(argv) == out
    arrays = sorted(out.glob("view_*.npy"))
    pngs = sorted(out.glob("view_*.png"))
    assert [p.name for p in arrays] == [
        "view_00_daz+030.00_del+00.00.npy",
        "view_01_daz+060.00_del+00.00.npy",
        "view_02_daz+090.00_del+00.00.npy",
    ]
    assert [p.stem for p in pngs] == [p.stem for p in arrays]
    for array_path, png_path in zip(arrays, pngs):
        view = np.load(array_path)
        assert view.shape == (32, 32) and view.dtype == np.float32
        assert view.min() >= 0.0 and view.max() <= 1.0
        png = np.asarray(PIL.Image.open(png_path))
        np.testing.assert_array_equal(png, np.round(view * 255).astype(np.uint8))
    assert (out / "input.png").exists() and PIL.Image.open(out / "contact_sheet.png").size[0] > 4 * 32
    assert json.loads((out / "config.json").read_text())["d_az"] == [30.0, 60.0, 90.0]
    # views.json says what the arrays hold and lists each view with its request
    described = json.loads((out / "views.json").read_text())
    assert described["domain"].startswith("normalised dB in [0, 1]")
    assert described["scaling"] == DecibelScaling().to_dict()  # a pipeline without decibel_scaling.json
    assert [(v["npy"], v["d_az_deg"], v["d_el_deg"]) for v in described["views"]] == [
        (p.name, a, 0.0) for p, a in zip(arrays, (30.0, 60.0, 90.0))
    ]

    # view i is the pipeline's sample with generator seed + i
    config = GenerateConfig(pipeline=str(pipeline_dir), image=str(chip_png))
    chip = load_input_chip(config, 32)
    pipe = SARZero123Pipeline.from_pretrained(pipeline_dir)
    pipe.set_progress_bar_config(disable=True)
    expected = pipe(torch.from_numpy(chip)[None, None], d_az=60.0, d_el=0.0, num_inference_steps=2,
                    generator=torch.Generator().manual_seed(5), output_type="np").images[0, ..., 0]
    np.testing.assert_allclose(np.load(arrays[1]), expected, atol=1e-5)


def test_strength_and_heading_guidance_reach_the_pipeline(pipeline_dir, chip_png, tmp_path):
    out = tmp_path / "views"
    argv = ["--pipeline", str(pipeline_dir), "--image", str(chip_png), "--d-az", "30", "120", "--d-el", "0",
            "--output_dir", str(out), "--num-inference-steps", "4", "--seed", "2", "--strength", "0.5",
            "--heading_guidance_scale", "1.5"]  # fmt: skip
    main(argv)
    assert json.loads((out / "config.json").read_text())["strength"] == 0.5
    config = GenerateConfig(pipeline=str(pipeline_dir), image=str(chip_png))
    chip = load_input_chip(config, 32)
    pipe = SARZero123Pipeline.from_pretrained(pipeline_dir)
    pipe.set_progress_bar_config(disable=True)
    for index, d_az in enumerate([30.0, 120.0]):
        generator = torch.Generator().manual_seed(2 + index)
        expected = pipe(torch.from_numpy(chip)[None, None], d_az=d_az, d_el=0.0, num_inference_steps=4,
                        strength=0.5, heading_guidance_scale=1.5, generator=generator,
                        output_type="np").images[0, ..., 0]  # fmt: skip
        np.testing.assert_allclose(np.load(sorted(out.glob("view_*.npy"))[index]), expected, atol=1e-5)
    from_noise = generate_views(pipe, chip, [30.0], [0.0], sampler(4, heading_guidance_scale=1.5), 2)
    assert np.abs(from_noise[0] - np.load(sorted(out.glob("view_*.npy"))[0])).max() > 1e-3


def test_depression_guidance_reaches_the_pipeline(chip_png, tmp_path):
    components = get_dummy_components()
    read_the_pose(components["pose_projection"])  # the dummy one ignores d_el, and so any guidance on it
    pipe = SARZero123Pipeline(**components)
    pipe.save_pretrained(tmp_path / "pipeline")
    pipe.set_progress_bar_config(disable=True)
    out = tmp_path / "views"
    main(["--pipeline", str(tmp_path / "pipeline"), "--image", str(chip_png), "--d-az", "30", "--d-el", "-5",
          "--output_dir", str(out), "--num-inference-steps", "3", "--seed", "1",
          "--depression_guidance_scale", "2"])  # fmt: skip
    assert json.loads((out / "config.json").read_text())["depression_guidance_scale"] == 2.0
    chip = load_input_chip(GenerateConfig(pipeline=str(tmp_path / "pipeline"), image=str(chip_png)), 32)
    expected = generate_views(pipe, chip, [30.0], [-5.0], sampler(3, depression_guidance_scale=2.0), 1)
    written = np.load(sorted(out.glob("view_*.npy"))[0])
    np.testing.assert_allclose(written, expected[0], atol=1e-5)
    unguided = generate_views(pipe, chip, [30.0], [-5.0], sampler(3), 1)
    assert np.abs(written - unguided[0]).max() > 1e-3


def test_input_chip_uses_the_pipeline_scaling_file(pipeline_dir, chip_png, tmp_path):
    magnitude = np.asarray(PIL.Image.open(chip_png), np.float32)[4:36, 4:36] / 255.0  # centre 32 px
    config = GenerateConfig(pipeline=str(pipeline_dir), image=str(chip_png))
    np.testing.assert_allclose(load_input_chip(config, 32), DecibelScaling().normalize(magnitude), atol=1e-6)
    scaling = DecibelScaling(min_db=-40.0, max_db=0.0)
    (tmp_path / SCALING_FILE).write_text(json.dumps(scaling.to_dict()))
    config = GenerateConfig(pipeline=str(tmp_path), image=str(chip_png))
    with pytest.warns(UserWarning, match=r"1\.8% of the pixels lie outside the scaling's dB range"):
        chip = load_input_chip(config, 32)  # the darkest pixels fall below -40 dB and are clipped
    np.testing.assert_allclose(chip, scaling.normalize(magnitude), atol=1e-6)


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"pipeline": ""}, "pipeline"),
        ({"d_az": []}, "d_az"),
        ({"d_az": [10.0, 20.0], "d_el": [0.0, 1.0, 2.0]}, "d_el"),
        ({"d_az": [float("nan")]}, "finite"),
        ({"num_inference_steps": 0}, "num_inference_steps"),
        ({"input_depression": 90.0}, r"input_depression must lie in \(0, 90\) degrees, got 90.0"),
        ({"input_depression": 0.0}, r"input_depression must lie in \(0, 90\) degrees"),
        ({"input_depression": float("nan")}, r"input_depression must lie in \(0, 90\) degrees"),
    ],
)
def test_config_rejects_bad_values(fields, match):
    with pytest.raises(ValueError, match=match):
        GenerateConfig(**{"pipeline": "p", "image": "chip.png", **fields})


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"d_el": [400.0]}, r"^`d_el` must lie in \(-90, 90\) degrees .*got 400$"),
        ({"d_el": [-90.0]}, r"^`d_el` must lie in \(-90, 90\) degrees .*got 90$"),
        ({"guidance_scale": 1e30}, r"guidance_scale must be finite and <= 100"),
        ({"guidance_scale": float("inf")}, r"guidance_scale must be finite"),
        ({"heading_guidance_scale": -1.0}, r"heading_guidance_scale must lie in \[0, 100\], got -1.0"),
        ({"depression_guidance_scale": 101.0}, r"depression_guidance_scale must lie in \[0, 100\]"),
        ({"strength": 0.0}, r"^strength must lie in \(0, 1\], got 0.0"),
        ({"strength": float("nan")}, r"^strength must lie in \(0, 1\], got nan"),
        ({"strength": 0.2, "num_inference_steps": 4},
         r"^strength 0.2 x num_inference_steps 4 leaves no denoising step"),
        ({"start_from": "noise"}, r"^start_from must be one of \(.*'proxy'\), got 'noise'"),
        ({"input_azimuth": float("nan")}, r"input_azimuth must be a finite angle"),
    ],
)
def test_config_rejects_impossible_poses_and_guidance(fields, match):
    with pytest.raises(ValueError, match=match):
        GenerateConfig(**{"pipeline": "p", "image": "chip.png", **fields})


@pytest.mark.parametrize(
    ("scale", "offset", "outcome"),
    [
        (100.0, 0.0, r"100.0% of the pixels lie outside .*clipped; give the pipeline's --scaling_file"),
        (-1.0, 0.0, r"chip.npy: magnitude contains negative values"),  # load_magnitude's check
        (1.0, float("nan"), r"chip.npy: magnitude contains non-finite values"),
    ],
    ids=["saturated", "negative", "nan"],
)
def test_out_of_range_magnitudes_are_refused(pipeline_dir, tmp_path, scale, offset, outcome):
    path = tmp_path / "chip.npy"
    np.save(path, np.random.default_rng(0).uniform(0.5, 1.0, (40, 40)).astype(np.float32) * scale + offset)
    with pytest.raises(ValueError, match=outcome):
        load_input_chip(GenerateConfig(pipeline=str(pipeline_dir), image=str(path)), 32)


def test_partly_clipped_chip_warns_with_the_fraction(pipeline_dir, tmp_path):
    magnitude = np.full((32, 32), 0.5, np.float32)
    magnitude[:4] = 2.0  # 1/8 of the pixels above the unit-magnitude range
    np.save(tmp_path / "chip.npy", magnitude)
    config = GenerateConfig(pipeline=str(pipeline_dir), image=str(tmp_path / "chip.npy"))
    with pytest.warns(UserWarning, match=r"12.5% of the pixels lie outside"):
        chip = load_input_chip(config, 32)
    assert chip.max() == 1.0


def test_nan_pipeline_writes_no_views_and_out_that_is_a_file_is_refused(chip_png, tmp_path):
    components = get_dummy_components()
    with torch.no_grad():
        next(components["vae"].decoder.parameters()).fill_(float("nan"))
    SARZero123Pipeline(**components).save_pretrained(tmp_path / "nan_pipeline")
    out = tmp_path / "views"
    argv = ["--pipeline", str(tmp_path / "nan_pipeline"), "--image", str(chip_png), "--d-az", "30",
            "--num-inference-steps", "1"]  # fmt: skip
    with pytest.raises(FloatingPointError, match=r"non-finite decoded images .*\['vae'\]"):
        main([*argv, "--output_dir", str(out)])
    assert not out.exists()  # the folder is opened only once the views exist
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match=r"output_dir: .*file' is a file"):
        main([*argv, "--output_dir", str(tmp_path / "file")])


@pytest.fixture(scope="module")
def registry_dir(tmp_path_factory):
    """A registry folder whose ``tiny`` is a tiny pipeline whose pose takes the input's depression, and
    whose ``sim_prior_rotated`` (the command's default) is a copy of it."""
    registry = tmp_path_factory.mktemp("registry")
    build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True).save_pretrained(
        registry / "tiny"
    )
    scaling = DecibelScaling(min_db=-60.0, max_db=6.0)  # not the unit default: shows which file is read
    (registry / "tiny" / SCALING_FILE).write_text(json.dumps(scaling.to_dict()))
    shutil.copytree(registry / "tiny", registry / pretrained.BUNDLED_PIPELINES[SIM_PRIOR_ROTATED])
    return registry


def _run(tmp_path, name, *argv):
    out = tmp_path / name
    main([*argv, "--num-inference-steps", "2", "--output_dir", str(out)])
    return out, {p.name: np.load(p) for p in sorted(out.glob("view_*.npy"))}


def test_default_pipeline_is_the_bundled_prior_with_17_deg_and_a_note(registry_dir, chip_png, tmp_path,
                                                                      monkeypatch, capsys):
    assert GenerateConfig(image="chip.png").pipeline == SIM_PRIOR_ROTATED
    # with the chip's azimuth known, the prior conditioned on a simulator proxy fitted to it
    assert GenerateConfig(image="chip.png", input_azimuth=30.0).pipeline == pretrained.SIM_PRIOR_IDENTITY
    assert GenerateConfig(image="chip.png", input_azimuth=30.0, pipeline="p").pipeline == "p"
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", registry_dir)
    _, default = _run(tmp_path, "default", "--image", str(chip_png), "--d-az", "30", "--d-el", "10")
    note = f"note: {str(chip_png)!r} records no depression angle; assuming the input chip was taken at 17 deg"
    assert note in capsys.readouterr().out
    assert list(default) == ["view_00_daz+030.00_del+10.00.npy"]
    folder = str(registry_dir / pretrained.BUNDLED_PIPELINES[SIM_PRIOR_ROTATED])
    argv = ["--pipeline", folder, "--image", str(chip_png), "--d-az", "30", "--d-el", "10"]
    _, explicit = _run(tmp_path, "explicit", *argv, "--input_depression", "17")
    assert "note" not in capsys.readouterr().out
    np.testing.assert_array_equal(default["view_00_daz+030.00_del+10.00.npy"],
                                  explicit["view_00_daz+030.00_del+10.00.npy"])  # fmt: skip
    # the chip went through the registered folder's decibel_scaling.json, not the unit default
    magnitude = np.asarray(PIL.Image.open(chip_png), np.float32)[4:36, 4:36] / 255.0
    expected = DecibelScaling(min_db=-60.0, max_db=6.0).normalize(magnitude)
    np.testing.assert_allclose(load_input_chip(GenerateConfig(image=str(chip_png)), 32), expected, atol=1e-6)


def test_input_depression_reaches_the_pipeline(registry_dir, chip_png, tmp_path):
    folder = registry_dir / "tiny"
    argv = ["--pipeline", str(folder), "--image", str(chip_png), "--d-az", "30", "90", "--d-el", "0", "10"]
    out, at_17 = _run(tmp_path, "at_17", *argv, "--input-depression", "17")
    _, at_40 = _run(tmp_path, "at_40", *argv, "--input_depression", "40")
    names = ["view_00_daz+030.00_del+00.00.npy", "view_01_daz+090.00_del+10.00.npy"]
    assert list(at_17) == list(at_40) == names
    for name in at_17:
        assert np.abs(at_17[name] - at_40[name]).max() > 1e-3, name
    assert json.loads((out / "config.json").read_text())["input_depression"] == 17.0
    # the same views straight from the pipeline; without the depression it refuses
    pipe = SARZero123Pipeline.from_pretrained(folder)
    pipe.set_progress_bar_config(disable=True)
    chip = load_input_chip(GenerateConfig(pipeline=str(folder), image=str(chip_png)), 32)
    views = generate_views(pipe, chip, [30.0, 90.0], [0.0, 10.0], sampler(2), 0, input_depression_deg=40.0)
    np.testing.assert_allclose(views[1], at_40["view_01_daz+090.00_del+10.00.npy"], atol=1e-5)
    with pytest.raises(ValueError, match=r"`input_depression_deg`: this pipeline's pose carries"):
        generate_views(pipe, chip, [30.0], [0.0], sampler(1), 0)


def test_depression_recorded_in_the_chip_file_is_used(registry_dir, tmp_path, capsys):
    magnitude = np.random.default_rng(0).rayleigh(0.1, size=(40, 40)).astype(np.float32)
    raw = write_mstar(tmp_path / "HB00001.015", magnitude, fields={"DesiredDepression": "30"})
    assert chip_depression_deg(raw) == 30.0
    assert chip_depression_deg(tmp_path / "2s1_real_A_elevDeg_015_azCenter_010_22_serial_b01.png") == 15.0
    assert chip_depression_deg(tmp_path / "chip.png") is None
    assert resolve_input_depression(raw, None) == (30.0, "file")
    assert resolve_input_depression(raw, 20.0) == (20.0, "given")
    assert resolve_input_depression(tmp_path / "chip.npy", None) == (17.0, "default")
    argv = ["--pipeline", str(registry_dir / "tiny"), "--image", str(raw), "--d-az", "30"]
    _, from_file = _run(tmp_path, "from_file", *argv)
    assert f"note: input depression 30 deg, read from {str(raw)!r}" in capsys.readouterr().out
    _, given = _run(tmp_path, "given", *argv, "--input_depression", "30")
    np.testing.assert_array_equal(from_file["view_00_daz+030.00_del+00.00.npy"],
                                  given["view_00_daz+030.00_del+00.00.npy"])  # fmt: skip


def test_input_depression_only_bounds_the_target_on_a_pipeline_without_it(pipeline_dir, chip_png, tmp_path,
                                                                            capsys):
    """The views are those of a call without it; a target past (0, 90) deg is refused (see
    test_reliability_probes)."""
    argv = ["--pipeline", str(pipeline_dir), "--image", str(chip_png), "--d-az", "30"]
    _, plain = _run(tmp_path, "plain", *argv)
    assert capsys.readouterr().out == ""
    _, given = _run(tmp_path, "given", *argv, "--input_depression", "40")
    assert "--input_depression only bounds the target depression (input + d_el) to (0, 90) deg" in (
        capsys.readouterr().out
    )
    name = "view_00_daz+030.00_del+00.00.npy"
    np.testing.assert_array_equal(plain[name], given[name])


def _snapshot(folder):
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def test_output_dir_refuses_other_settings_returns_with_resume_and_moves_aside_with_restart(
    pipeline_dir, chip_png, tmp_path, monkeypatch
):
    chip = tmp_path / "chip.png"
    chip.write_bytes(chip_png.read_bytes())
    out = tmp_path / "views"
    argv = ["--pipeline", str(pipeline_dir), "--image", str(chip), "--d-az", "30",
            "--num-inference-steps", "1", "--output_dir", str(out)]  # fmt: skip
    assert main(argv) == out
    record = json.loads((out / "run.json").read_text())
    assert (record["stage"], record["finished"]) == ("generate", True)
    assert record["data"]["image"]["index_sha256"] == hashlib.sha256(chip.read_bytes()).hexdigest()
    assert {"view_00_daz+030.00_del+00.00.npy", "contact_sheet.png"} <= set(record["outputs"])
    before = _snapshot(out)
    # other settings, another chip in the same file, or the same request without a flag: refused, naming the
    # difference, and nothing on disk changed
    with pytest.raises(ValueError, match=r"holds a generate run made with other settings.*seed: folder 0, "
                                         r"this run 1.*--restart"):  # fmt: skip
        main([*argv, "--seed", "1"])
    PIL.Image.fromarray(np.full((40, 40), 128, np.uint8), mode="L").save(chip)
    with pytest.raises(ValueError, match=r"Differences: data: folder \{'image': .*'index_sha256'"):
        main(argv)
    chip.write_bytes(chip_png.read_bytes())
    same = r"already holds a finished generate run with these settings; continue it explicitly \(--resume\)"
    with pytest.raises(ValueError, match=same):
        main(argv)
    assert _snapshot(out) == before
    # --resume: the finished folder as it is; the pipeline is not even loaded
    def no_work(*args, **kwargs):
        raise AssertionError("a finished folder continued with --resume must not be worked on")

    monkeypatch.setattr(SARZero123Pipeline, "from_pretrained", no_work)
    assert main([*argv, "--resume"]) == out
    assert _snapshot(out) == before
    monkeypatch.undo()
    # --restart: the old views moved aside untouched, the new ones in their place
    assert main([*argv, "--seed", "1", "--restart"]) == out
    (aside,) = tmp_path.glob("views.replaced-*")
    assert _snapshot(aside) == before
    assert json.loads((out / "config.json").read_text())["seed"] == 1


@pytest.mark.parametrize(
    ("image", "error", "match"),
    [
        ("tiny.png", ValueError, r"a 1x1 image is too small to be a chip; expected at least 16x16 pixels"),
        ("missing.png", FileNotFoundError, r"image: .*missing.png' is not a file"),
    ],
)
def test_bad_input_is_refused_before_anything_is_written(pipeline_dir, tmp_path, image, error, match):
    PIL.Image.fromarray(np.zeros((1, 1), np.uint8), mode="L").save(tmp_path / "tiny.png")
    out = tmp_path / "views"
    with pytest.raises(error, match=match):
        main(["--pipeline", str(pipeline_dir), "--image", str(tmp_path / image), "--output_dir", str(out)])
    assert not out.exists()


def test_a_plain_generate_uses_the_pipelines_recorded_sampler_and_its_proxy_with_the_chips_azimuth(
    chip_png, tmp_path
):
    proxy = {"num_vehicles": 2, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0,
             "min_db": -60.0, "max_db": 0.0, "min_fit_score": -1.0}  # fmt: skip
    sampler = {"num_inference_steps": 4, "strength": 0.5, "start_from": "proxy"}
    folder = tmp_path / "pipeline"
    SARZero123Pipeline(**get_dummy_components(), sampler=sampler, proxy=proxy).save_pretrained(folder)
    pipe = SARZero123Pipeline.from_pretrained(folder)
    pipe.set_progress_bar_config(disable=True)
    chip = load_input_chip(GenerateConfig(pipeline=str(folder), image=str(chip_png)), 32)
    common = ["--pipeline", str(folder), "--image", str(chip_png), "--d-az", "90", "--seed", "1"]
    for azimuth, start_from in ((["--input_azimuth", "40"], "proxy"), ([], "input")):  # no azimuth: the input
        out = tmp_path / f"views_{start_from}"
        main([*common, *azimuth, "--output_dir", str(out)])
        expected = pipe(torch.from_numpy(chip)[None, None], d_az=90.0, num_inference_steps=4, strength=0.5,
                        start_from=start_from, input_azimuth_deg=40.0 if azimuth else None,
                        input_depression_deg=17.0, generator=torch.Generator().manual_seed(1),
                        output_type="np").images[0, ..., 0]  # fmt: skip
        np.testing.assert_allclose(np.load(next(out.glob("view_*.npy"))), expected, atol=1e-5)
        assert json.loads((out / "config.json").read_text())["strength"] is None  # the pipeline's own
        # views.json records how well the proxy fits the chip (the best bank score), where one was fitted
        score = json.loads((out / "views.json").read_text())["proxy_fit_score"]
        if azimuth:
            fields = ("num_vehicles", "first_seed", "blur_sigma_px", "render_seed")
            bank = ProxyBank(*(proxy[k] for k in fields))
            best = float(bank.scores(chip.astype(np.float64), 40.0, 17.0).max())
            assert score == pytest.approx(best, abs=1e-6)
        else:
            assert score is None


def test_an_image_size_far_above_the_trained_one_is_refused_before_any_work(pipeline_dir, chip_png, tmp_path):
    out = tmp_path / "views"
    argv = ["--pipeline", str(pipeline_dir), "--image", str(chip_png), "--d-az", "30",
            "--output_dir", str(out), "--image_size", "1024"]  # fmt: skip
    refused = r"^image_size: at most twice the pipeline's trained size 32 px \(64\)"
    with pytest.raises(ValueError, match=refused):
        main(argv)
    assert not out.exists()
