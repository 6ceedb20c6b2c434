"""The multi-view prior's parts: procedural vehicles, the corpus, depression in the pose, trained ranges."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from sar_zero123.data import ViewPairDataset, load_index, split_records
from sar_zero123.model.build import build_sar_zero123, record_trained_pose_ranges
from sar_zero123.model.conditioning import embed_pose
from sar_zero123.sim import TARGET_CLASSES, render_chip
from sar_zero123.sim.corpus import VALIDATION_CLASS, corpus_views, write_prior_corpus
from sar_zero123.sim.procedural import PROCEDURAL_CLASS, make_procedural_target, procedural_parts
from sar_zero123.stages.prior import PriorConfig, prior_base_config


# ---------------------------------------------------------------------------- procedural vehicles
def test_procedural_vehicle_is_deterministic_per_seed_and_seeds_differ():
    a, b = make_procedural_target(7), make_procedural_target(7)
    assert a.primitives == b.primitives
    np.testing.assert_array_equal(a.scatterers.position, b.scatterers.position)
    assert (a.class_name, a.instance) == (PROCEDURAL_CLASS, 7)
    assert PROCEDURAL_CLASS not in TARGET_CLASSES
    # no two of the first 200 seeds share their solids
    shapes = {procedural_parts(seed)[0].__repr__() for seed in range(200)}
    assert len(shapes) == 200


def test_procedural_family_covers_tracks_wheels_turrets_and_beds():
    from sar_zero123.sim.primitives import Box, HorizontalCylinder, VerticalCylinder

    counts = {"wheels": 0, "round": 0, "many": 0}
    lengths = []
    for seed in range(300):
        parts, details = procedural_parts(seed)
        assert 8 <= details < 22
        wheels = [p for p in parts if isinstance(p, HorizontalCylinder) and p.yaw_deg == 90.0]
        counts["wheels"] += bool(wheels)
        counts["round"] += any(isinstance(p, VerticalCylinder) and p.radius > 0.7 for p in parts)
        counts["many"] += len(parts) >= 8
        lengths.append(max(p.length for p in parts if isinstance(p, Box)))
    assert 0.3 < counts["wheels"] / 300 < 0.6  # 45 % wheeled by construction
    assert counts["round"] > 30 and counts["many"] > 30
    assert min(lengths) < 5.0 and max(lengths) > 7.5  # hulls from scout cars to long trucks


def test_procedural_vehicle_renders_inside_the_chip_with_its_shadow():
    target = make_procedural_target(3)
    chip = render_chip(target, 30.0, 17.0, 64, np.random.default_rng(0))
    assert chip.shape == (64, 64) and chip.dtype == np.float32 and float(chip.max()) == 1.0
    # radar at the bottom: the shadow lies above the vehicle, well below the clutter level in front of it,
    # and shortens at a steeper depression (the band above the vehicle brightens)
    behind, front = np.median(chip[4:24, 24:40]), np.median(chip[44:60, 24:40])
    assert behind < 0.5 * front
    steep = render_chip(target, 30.0, 45.0, 64, np.random.default_rng(0))
    assert np.median(steep[4:24, 24:40]) > 2.0 * behind
    with pytest.raises(ValueError, match="seed"):
        make_procedural_target(-1)
    with pytest.raises(ValueError, match="seed"):
        make_procedural_target(True)


# -------------------------------------------------------------------------------------- corpus
def test_corpus_views_are_seeded_and_in_range():
    azimuth, depression = corpus_views(0, 5, 400, (10.0, 60.0), 0.25)
    again = corpus_views(0, 5, 400, (10.0, 60.0), 0.25)
    np.testing.assert_array_equal(azimuth, again[0])
    assert ((0 <= azimuth) & (azimuth < 360)).all()
    assert ((10 <= depression) & (depression <= 60)).all()
    at_mstar = np.isin(depression, (15.0, 17.0)).mean()
    assert 0.18 < at_mstar < 0.32  # 25 % by construction (binomial, n = 400)


def test_corpus_writes_an_index_the_readers_take_and_refuses_other_options(tmp_path: Path):
    out = tmp_path / "corpus"
    write_prior_corpus(
        out, num_vehicles=4, views_per_vehicle=3, num_validation_vehicles=1, size=32, progress=False
    )
    records = load_index(out)
    assert len(records) == 12
    assert {r.target_class for r in records} == {PROCEDURAL_CLASS, VALIDATION_CLASS}
    assert sum(r.target_class == VALIDATION_CLASS for r in records) == 3  # the last vehicle
    assert np.load(records[0].path).dtype == np.float16
    splits = split_records(records, f"ood-{VALIDATION_CLASS}")
    assert {r.serial for r in splits["test"]} == {"proc00003"}
    # a chip deleted after the index was written is re-rendered identically on a re-run (no index yet)
    first = np.load(records[0].path)
    records[0].path.unlink()
    (out / "index.csv").unlink()
    write_prior_corpus(
        out, num_vehicles=4, views_per_vehicle=3, num_validation_vehicles=1, size=32, progress=False
    )
    np.testing.assert_array_equal(np.load(records[0].path), first)
    with open(out / "index.csv") as f:
        assert len(list(csv.reader(f))) == 13
    with pytest.raises(ValueError, match=r"views_per_vehicle 3 -> 5"):
        write_prior_corpus(out, num_vehicles=4, views_per_vehicle=5, num_validation_vehicles=1, size=32)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.txt").write_text("x")
    with pytest.raises(ValueError, match="not empty"):
        write_prior_corpus(tmp_path / "other", num_vehicles=4, views_per_vehicle=3, num_validation_vehicles=1)
    with pytest.raises(ValueError, match="depression_range_deg"):
        write_prior_corpus(tmp_path / "x", depression_range_deg=(40.0, 20.0))


# ------------------------------------------------------------------------- depression in the pose
def test_embed_pose_fourth_slot_is_the_input_depression_in_radians():
    pose = embed_pose([90.0, 0.0], [13.0, -7.0], [17.0, 45.0])
    expected = torch.tensor(
        [
            [math.radians(13.0), 1.0, 0.0, math.radians(17.0)],
            [math.radians(-7.0), 0.0, 1.0, math.radians(45.0)],
        ]
    )
    torch.testing.assert_close(pose[:, 0], expected, atol=1e-7, rtol=0)
    assert float(embed_pose(30.0, 0.0)[0, 0, 3]) == 0.0  # zero-1-to-3's radius delta without it
    torch.testing.assert_close(embed_pose(30.0, 0.0, 17.0)[0, 0, 3], torch.tensor(math.radians(17.0)))
    with pytest.raises(ValueError, match="input_depression_deg"):
        embed_pose([1.0, 2.0], 0.0, [17.0, 15.0, 30.0])


@pytest.fixture(scope="module")
def depression_pipe():
    pipe = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
    pipe.pose_projection.register_to_config(
        trained_d_el_deg=[-40.0, 40.0], trained_depression_deg=[10.0, 60.0]
    )
    pipe.set_progress_bar_config(disable=True)
    return pipe


def test_pipeline_needs_and_uses_the_input_depression(depression_pipe):
    image = torch.rand(1, 1, 32, 32)
    kwargs = {"num_inference_steps": 2, "output_type": "np"}
    with pytest.raises(ValueError, match="input_depression_deg"):
        depression_pipe(image, 30.0, 0.0, **kwargs)
    # the projection's pose columns are zero at initialisation: make the 4th slot matter
    with torch.no_grad():
        depression_pipe.pose_projection.projection.weight[:, -1] = 1.0
    low = depression_pipe(image, 30.0, 0.0, 17.0, generator=torch.Generator().manual_seed(0), **kwargs).images
    high = depression_pipe(
        image, 30.0, 0.0, 45.0, generator=torch.Generator().manual_seed(0), **kwargs
    ).images
    assert np.abs(low - high).max() > 1e-4


@pytest.mark.parametrize(
    "d_el, depression, match",
    [
        (45.0, 17.0, r"d_el` must lie in the trained range \[-40, 40\]"),
        (-10.0, 17.0, r"input_depression_deg \+ d_el` must lie in the trained depression range"),
        (0.0, 70.0, r"input_depression_deg` must lie in the trained depression range"),
        (0.0, 95.0, r"input_depression_deg` must lie in \(0, 90\)"),
        (0.0, [17.0, 15.0], "expected 1 or one per input image"),
    ],
)
def test_pipeline_refuses_requests_outside_its_trained_ranges(depression_pipe, d_el, depression, match):
    with pytest.raises(ValueError, match=match):
        depression_pipe(torch.rand(1, 1, 32, 32), 30.0, d_el, depression, num_inference_steps=1)


def test_trained_ranges_are_the_union_of_the_prior_and_the_new_pairs(tmp_path: Path):
    write_prior_corpus(
        tmp_path / "c",
        num_vehicles=3,
        views_per_vehicle=4,
        num_validation_vehicles=1,
        size=32,
        progress=False,
    )
    records = load_index(tmp_path / "c")
    pairs = ViewPairDataset(records, size=32, same_depression=False, seed=0)
    pipe = build_sar_zero123("tiny")
    d_el, depressions = record_trained_pose_ranges(pipe.pose_projection, pairs)
    used = [r.depression_deg for r in records]
    spread = math.ceil((max(used) - min(used)) * 10) / 10
    assert depressions == [math.floor(min(used) * 10) / 10, math.ceil(max(used) * 10) / 10]
    assert d_el == [-spread, spread]
    fields = [pairs.pair_fields(i) for i in range(len(pairs))]
    assert all(-spread <= f["d_el_deg"] <= spread for f in fields)
    # pairs at one depression: no depression change
    fresh = build_sar_zero123("tiny")
    write_prior_corpus(
        tmp_path / "m",
        num_vehicles=2,
        views_per_vehicle=6,
        num_validation_vehicles=1,
        size=32,
        mstar_fraction=1.0,
        progress=False,
    )  # every view at 15 or 17 deg
    same = ViewPairDataset(load_index(tmp_path / "m"), size=32, same_depression=True, seed=0)
    assert record_trained_pose_ranges(fresh.pose_projection, same)[0] == [0.0, 0.0]
    # a fine-tune on same-depression pairs keeps the prior's wider range
    pipe.pose_projection.register_to_config(
        trained_d_el_deg=[-50.0, 50.0], trained_depression_deg=[5.0, 80.0]
    )
    assert record_trained_pose_ranges(pipe.pose_projection, pairs) == ([-50.0, 50.0], [5.0, 80.0])
    pipe.pose_projection.save_pretrained(tmp_path / "proj")
    saved = json.loads((tmp_path / "proj" / "config.json").read_text())
    assert saved["trained_d_el_deg"] == [-50.0, 50.0]


# ------------------------------------------------------------------------------- pretrain_prior
def test_pretrain_prior_smoke_writes_a_pipeline_that_takes_depression(tmp_path: Path):
    from train import pretrain_prior

    argv = [
        "--output_dir",
        str(tmp_path / "prior"),
        "--num_vehicles",
        "6",
        "--views_per_vehicle",
        "4",
        "--num_validation_vehicles",
        "2",
        "--image_size",
        "32",
        "--model_size",
        "tiny",
        "--vae_widths",
        "16",
        "32",
        "--vae_steps",
        "2",
        "--base_steps",
        "2",
        "--train_batch_size",
        "2",
        "--vae_batch_size",
        "2",
        "--corpus_workers",
        "1",
    ]
    pipeline = pretrain_prior.main(argv)
    projection = json.loads((pipeline / "pose_projection" / "config.json").read_text())
    assert projection["input_depression"] is True
    records = load_index(tmp_path / "prior" / "corpus")
    used = [r.depression_deg for r in records if r.target_class == PROCEDURAL_CLASS]
    assert projection["trained_depression_deg"] == [
        math.floor(min(used) * 10) / 10,
        math.ceil(max(used) * 10) / 10,
    ]
    base = json.loads((tmp_path / "prior" / "base" / "config.json").read_text())
    assert (base["same_depression"], base["prediction_type"], base["snr_gamma"]) == (
        False,
        "v_prediction",
        5.0,
    )
    timings = json.loads((tmp_path / "prior" / "timings.json").read_text())
    assert set(timings) == {"corpus", "vae", "base"}
    # a re-run finds every stage done; more base steps resume the run and export again
    assert pretrain_prior.main(argv) == pipeline
    longer = list(argv)
    longer[longer.index("--base_steps") + 1] = "3"
    pretrain_prior.main(longer)
    assert json.loads((tmp_path / "prior" / "base" / "config.json").read_text())["max_train_steps"] == 3
    record = json.loads((tmp_path / "prior" / "run.json").read_text())
    assert record["stage"] == "prior" and record["finished"] is True and record["config"]["base_steps"] == 3
    assert json.loads((tmp_path / "prior" / "base" / "run.json").read_text())["results"] == {"final_step": 3}
    # the same folder with another setting is refused before any work, naming it
    refused = r"holds a prior run made with other settings.*seed: folder 0, this run 1\b"
    with pytest.raises(ValueError, match=refused):
        pretrain_prior.main([*longer, "--seed", "1"])
    with pytest.raises(ValueError, match=r"depression_range_deg=\[50.0, 20.0\], but depression_range_deg was "
                       r"removed: the corpus's depressions are drawn in \(10.0, 60.0\) deg"):
        (tmp_path / "old.json").write_text(json.dumps({"depression_range_deg": [50.0, 20.0]}))
        pretrain_prior.main([*longer, "--config", str(tmp_path / "old.json")])

    # a warm start: the UNet stage continues this prior on another corpus, with its VAE and its settings
    # (--model_size micro is the init's to decide: ignored, the tiny pipeline stays tiny)
    # with a learning rate that decays to 0 over its steps (so those steps cannot be extended later)
    warm_argv = [*argv, "--seed", "1", "--init", str(pipeline), "--model_size", "micro",
                 "--lr_scheduler", "cosine", "--lr_warmup_steps", "1"]  # fmt: skip
    warm_argv[warm_argv.index("--output_dir") + 1] = str(tmp_path / "warm")
    warm = pretrain_prior.main(warm_argv)
    base = json.loads((tmp_path / "warm" / "base" / "config.json").read_text())
    assert (base["pretrained"], base["vae"]) == (str(pipeline), str(pipeline / "vae"))
    assert (base["lr_scheduler"], base["lr_warmup_steps"], base["learning_rate"]) == ("cosine", 1, 1e-3)
    extended = list(warm_argv)
    extended[extended.index("--base_steps") + 1] = "3"
    with pytest.raises(ValueError, match=r"other settings.*base_steps: folder 2, this run 3\b"):
        pretrain_prior.main(extended)
    with pytest.raises(ValueError, match=r"lr_scheduler must be one of \[.*'cosine'.*\], got 'cosin'"):
        pretrain_prior.PriorConfig(lr_scheduler="cosin")
    with pytest.raises(ValueError, match=r"lr_warmup_steps must be >= 0, got -1"):
        pretrain_prior.PriorConfig(lr_warmup_steps=-1)
    assert (base["spatial_pose"], base["input_depression"], base["prediction_type"]) == (None, False, None)
    assert not (tmp_path / "warm" / "vae").exists()  # no VAE stage
    for part in ("vae", "unet"):  # the same models, whatever path they were loaded from
        configs = [json.loads((p / part / "config.json").read_text()) for p in (pipeline, warm)]
        for config in configs:
            config.pop("_name_or_path", None)
        assert configs[0] == configs[1]
    assert (warm / "vae" / "diffusion_pytorch_model.safetensors").read_bytes() == (
        pipeline / "vae" / "diffusion_pytorch_model.safetensors"
    ).read_bytes()
    unet = [load_file(p / "unet" / "diffusion_pytorch_model.safetensors") for p in (pipeline, warm)]
    assert unet[0].keys() == unet[1].keys() and any(not torch.equal(unet[0][k], unet[1][k]) for k in unet[0])
    with pytest.raises(ValueError, match="vae: a warm start"):
        pretrain_prior.PriorConfig(init=str(pipeline), vae=str(pipeline / "vae"))
    with pytest.raises(FileNotFoundError, match="init: expected"):
        pretrain_prior.PriorConfig(init=str(tmp_path / "nowhere"))
    # settings the warm start would ignore are refused, not recorded as applied
    ignored = r"^model_size, input_depression, spatial_pose: a warm start .* keeps that pipeline's own"
    with pytest.raises(ValueError, match=ignored):
        pretrain_prior.PriorConfig(init=str(pipeline), model_size="tiny", input_depression=False,
                                   spatial_pose="rotated_input")  # fmt: skip


def test_a_folder_that_is_not_a_prior_corpus_or_a_vae_is_refused_before_any_work(tmp_path: Path):
    images = tmp_path / "images"
    images.mkdir()
    (images / "index.csv").write_text("path,target_class\n")  # an image folder, not a corpus
    with pytest.raises(FileNotFoundError, match=r"corpus: .*images is not a prior corpus \(no corpus.json"):
        PriorConfig(output_dir=str(tmp_path / "prior"), corpus=str(images))
    with pytest.raises(FileNotFoundError, match=r"vae: expected an AutoencoderKL folder with config.json"):
        PriorConfig(output_dir=str(tmp_path / "prior"), vae=str(tmp_path / "nowhere"))
    assert not (tmp_path / "prior").exists()


def test_settings_a_later_stage_would_refuse_are_refused_before_the_corpus(tmp_path: Path):
    message = r"model_size 'tiny' needs a VAE that downsamples by 2 \(2 width levels\), but vae_widths "
    with pytest.raises(ValueError, match=message + r"\[16, 32, 64\] downsamples by 4"):
        PriorConfig(output_dir=str(tmp_path / "prior"), model_size="tiny")
    with pytest.raises(ValueError, match=r"train_batch_size 100000 exceeds the 16 training chips"):
        PriorConfig(output_dir=str(tmp_path / "prior"), num_vehicles=6, views_per_vehicle=4,
                    num_validation_vehicles=2, train_batch_size=100000)  # fmt: skip
    assert not (tmp_path / "prior").exists()


def test_a_batch_the_corpus_pairs_cannot_fill_is_refused_before_the_vae_keeping_the_corpus(tmp_path: Path):
    with pytest.raises(ValueError, match=r"num_validation_vehicles must be below num_vehicles \(4\)"):
        PriorConfig(output_dir=str(tmp_path / "prior"), num_vehicles=4, num_validation_vehicles=4)
    # 4 training vehicles x 4 views = 16 chips pass the first bound; the validation azimuths take some
    config = PriorConfig(
        output_dir=str(tmp_path / "prior"), num_vehicles=8, views_per_vehicle=4, num_validation_vehicles=4,
        model_size="tiny", vae_widths=[16, 32], train_batch_size=16, corpus_workers=1,
    )  # fmt: skip
    from sar_zero123.stages.prior import check_corpus_pairs, run_prior

    refused = (r"train_batch_size: the corpus .*corpus' gives (\d+) training pairs .*fewer than a global "
               r"batch of 16; use train_batch_size <= \1 .*The corpus is kept: pass --corpus ")
    with pytest.raises(ValueError, match=refused):
        run_prior(config)
    out = tmp_path / "prior"
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "corpus", "run.json"]  # no VAE stage
    pairs = check_corpus_pairs(dataclasses.replace(config, train_batch_size=4), out / "corpus")
    assert 4 <= pairs < 16


def test_the_proxy_shares_reach_the_unet_stage_and_a_bad_sum_is_refused_at_the_prior(tmp_path: Path):
    config = PriorConfig(output_dir=str(tmp_path / "prior"), spatial_pose="proxy", proxy_oracle_prob=0.25,
                         proxy_runner_up_prob=0.0)  # fmt: skip
    base = prior_base_config(config, vae=tmp_path / "vae")
    assert (base.proxy_oracle_prob, base.proxy_runner_up_prob) == (0.25, 0.0)
    assert PriorConfig(output_dir=str(tmp_path / "p2")).proxy_runner_up_prob == 0.25  # the bundled priors'
    message = r"proxy_runner_up_prob, proxy_oracle_prob must be >= 0 with sum <= 1"
    with pytest.raises(ValueError, match=message):
        PriorConfig(output_dir=str(tmp_path / "prior"), proxy_oracle_prob=0.5, proxy_runner_up_prob=0.75)
    assert not (tmp_path / "prior").exists()
