"""Tests of train/finetune_pfm.py (the fine-tune stage): smoke run, CFG dropout, bad input, two-process run,
SIGKILL + resume, trained image tower, the run-folder rule (refusal, restart, extension), bounded work."""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
import re
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import torch
from accelerate.state import AcceleratorState, GradientState
from diffusers import AutoencoderKL
from safetensors.torch import load_file

from sar_zero123.data import ChipRecord, load_index, write_index
from sar_zero123.encoder import SAREncoder, SAREncoderConfig
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.orientation import AzimuthEstimator
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import EXPORTED_SAMPLER
from sar_zero123.runs.launch import check_global_batch, weights_digest
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import ImageEmbedder, compute_losses, micro_batch_generator
from train import finetune_pfm

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "train" / "finetune_pfm.py"


@pytest.fixture(scope="module")
def script():
    return finetune_pfm


@pytest.fixture(autouse=True)
def fresh_accelerate_state():
    AcceleratorState._reset_state(True)  # before too: a test of another file may have left one in this worker
    GradientState._reset_state()
    yield
    AcceleratorState._reset_state(True)
    GradientState._reset_state()


def write_chips(root: Path, azimuths_deg: list[float], size: int = 32) -> Path:
    """Two classes, one object each, at 15 and 17 deg: random magnitudes as .npy chips."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    records = []
    for target_class in ("A", "B"):
        for depression in (15.0, 17.0):
            for k, azimuth in enumerate(azimuths_deg):
                path = root / f"{target_class}_{int(depression)}_{k}.npy"
                np.save(path, rng.random((size, size), dtype=np.float32))
                records.append(
                    ChipRecord(
                        path=path,
                        target_class=target_class,
                        serial="s1",
                        depression_deg=depression,
                        azimuth_deg=azimuth,
                    )
                )
    write_index(records, root)
    return root


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("finetune_assets")
    data = write_chips(base / "data", [0.0, 45.0, 90.0, 135.0, 180.0, 225.0])
    torch.manual_seed(0)
    tiny = SAREncoderConfig(image_size=32, depths=(1,), hidden_sizes=(8,), embedding_size=8)
    encoder = SAREncoder(tiny).save_pretrained(base / "encoder")
    encoder16 = SAREncoder(SAREncoderConfig(**{**tiny.to_dict(), "image_size": 16})).save_pretrained(
        base / "enc16"
    )
    return {"base": base, "data": data, "encoder": encoder, "encoder16": encoder16}


def tiny_args(assets: dict[str, Path], output_dir: Path, *extra: str) -> list[str]:
    return [
        "--output_dir",
        str(output_dir),
        "--size",
        "tiny",
        "--data",
        str(assets["data"]),
        "--encoder",
        str(assets["encoder"]),
        "--train_batch_size",
        "2",
        "--report_to",
        "none",
        "--seed",
        "3",
        *extra,
    ]


def test_smoke_two_steps_writes_checkpoint_grid_and_pipeline(script, assets, tmp_path) -> None:
    out = script.main(
        tiny_args(
            assets,
            tmp_path / "run",
            "--max_train_steps",
            "2",
            "--checkpointing_steps",
            "2",
            "--validation_steps",
            "2",
            "--num_validation_images",
            "2",
            "--validation_inference_steps",
            "2",
            "--pfm_projection_dim",
            "10",
        )
    )
    assert (out / "checkpoint-2" / "run_state.json").is_file()
    assert (out / "pfm_projection.safetensors").is_file()  # the paper-comparable projection, saved
    grid = np.asarray(PIL.Image.open(out / "validation" / "step-000002.png"))
    assert grid.shape == (2 * 32, 3 * 32)  # rows of input | generated | target
    saved = json.loads((out / "config.json").read_text())
    assert saved["pfm_weight"] == 4.0 and "pfm_crop_size" not in saved
    assert json.loads((out / "pipeline" / "decibel_scaling.json").read_text())["min_db"] == -60.0
    pipe = SARZero123Pipeline.from_pretrained(out / "pipeline")
    # the exported pipeline records the measured step count: its plain call samples 20 steps, not 50
    assert pipe.config.sampler == EXPORTED_SAMPLER == {"num_inference_steps": 20}
    image = torch.rand(1, 1, 32, 32)
    result = pipe(
        image, d_az=30.0, num_inference_steps=2, output_type="pt", generator=torch.Generator().manual_seed(0)
    ).images
    assert result.shape == (1, 1, 32, 32) and torch.isfinite(result).all()


def test_cfg_dropout_both_matches_sampling_null() -> None:
    from diffusers import DDPMScheduler

    from tests.dummies import get_dummy_components

    components = get_dummy_components()
    seen = {}

    def hook(module, args, kwargs):
        seen["sample"], seen["tokens"] = args[0], kwargs["encoder_hidden_states"]

    handle = components["unet"].register_forward_pre_hook(hook, with_kwargs=True)
    batch = {
        "input": torch.rand(2, 1, 32, 32),
        "target": torch.rand(2, 1, 32, 32),
        "d_az_deg": torch.tensor([30.0, -90.0]),
        "d_el_deg": torch.tensor([0.0, 2.0]),
    }
    losses = compute_losses(
        batch,
        unet=components["unet"],
        pose_projection=components["pose_projection"],
        vae=components["vae"],
        image_encoder=ImageEmbedder(components["image_encoder"]),
        encoder=None,
        noise_scheduler=DDPMScheduler.from_config(components["scheduler"].config),
        generator=torch.Generator().manual_seed(0),
        loss_settings=LossSettings(
            pfm_weight=0.0, drop_image_prob=0.0, drop_both_prob=1.0, drop_latent_prob=0.0
        ),
    )
    handle.remove()
    assert losses.loss.shape == (2,)
    assert seen["tokens"].abs().sum() == 0 and seen["sample"][:, 4:].abs().sum() == 0
    assert seen["sample"][:, :4].abs().sum() > 0


def test_micro_batch_generator_is_a_pure_function() -> None:
    a = torch.rand(3, generator=micro_batch_generator(1, 7, 0))
    b = torch.rand(3, generator=micro_batch_generator(1, 7, 0))
    c = torch.rand(3, generator=micro_batch_generator(1, 7, 1))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_bad_input_fails_before_training(script, assets, tmp_path) -> None:
    run = tmp_path / "bad"
    with pytest.raises(ValueError, match="pfm_weight"):
        script.main(tiny_args(assets, run, "--pfm_weight", "-1"))
    with pytest.raises(ValueError, match="encoder"):
        script.main(["--output_dir", str(run), "--size", "tiny", "--data", str(assets["data"])])
    with pytest.raises(FileNotFoundError, match="encoder"):
        script.main(tiny_args(assets, run, "--encoder", str(tmp_path / "missing")))
    with pytest.raises(ValueError, match="trained on 16 px"):
        script.main(tiny_args(assets, run, "--encoder", str(assets["encoder16"])))
    with pytest.raises(ValueError, match="protocol"):
        script.main(tiny_args(assets, run, "--protocol", "random"))
    with pytest.raises(ValueError, match="T99"):
        script.main(tiny_args(assets, run, "--protocol", "ood-T99"))
    with pytest.raises(FileNotFoundError, match="not a complete checkpoint"):
        script.main(tiny_args(assets, run, "--resume_from_checkpoint", str(tmp_path)))
    with pytest.raises(FileNotFoundError, match="vae"):
        script.main(tiny_args(assets, run, "--vae", str(tmp_path / "no_vae")))
    vae_run = tmp_path / "vae_run"  # a train_vae.py run folder: its own config.json, the VAE in vae/
    (vae_run / "vae").mkdir(parents=True)
    (vae_run / "config.json").write_text(json.dumps({"max_train_steps": 2}))
    with pytest.raises(FileNotFoundError, match="vae_run/vae"):
        script.main(tiny_args(assets, run, "--vae", str(vae_run)))
    wrong_vae = AutoencoderKL(
        in_channels=1,
        out_channels=1,
        down_block_types=("DownEncoderBlock2D",) * 3,
        up_block_types=("UpDecoderBlock2D",) * 3,
        block_out_channels=(8, 8, 8),
        latent_channels=4,
        norm_num_groups=4,
    )
    wrong_vae.save_pretrained(tmp_path / "vae8")
    with pytest.raises(ValueError, match="downsampling factor 4"):
        script.main(tiny_args(assets, run, "--vae", str(tmp_path / "vae8")))
    lonely = write_chips(tmp_path / "lonely", [10.0])  # one view per object: no pairs
    with pytest.raises(ValueError, match="partner"):
        script.main(tiny_args(assets, run, "--data", str(lonely)))
    assert not list(run.glob("checkpoint-*"))


def read_weights(checkpoint: Path) -> dict[str, torch.Tensor]:
    weights = {f"unet.{k}": v for k, v in load_file(checkpoint / "model.safetensors").items()}
    weights.update({f"pose.{k}": v for k, v in load_file(checkpoint / "model_1.safetensors").items()})
    ema = torch.load(checkpoint / "custom_checkpoint_0.pkl", weights_only=False)
    weights.update({f"ema.{i}": v for i, v in enumerate(ema["shadow_params"])})
    return weights


@pytest.mark.slow
def test_sigkill_then_resume_latest_is_bitwise_identical(script, assets, tmp_path, caplog) -> None:
    steps = [
        "--max_train_steps",
        "6",
        "--checkpointing_steps",
        "2",
        "--validation_steps",
        "0",
        "--no-save_pipeline",
        "--gradient_accumulation_steps",
        "2",
        "--ema_decay",
        "0.5",
    ]
    # 1. uninterrupted reference
    reference = script.main(tiny_args(assets, tmp_path / "reference", *steps))
    # 2. the same run in a forked child (no second interpreter start-up), SIGKILLed once its first
    #    checkpoint exists
    run = tmp_path / "killed"
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    process = multiprocessing.get_context("fork").Process(
        target=script.main, args=(tiny_args(assets, run, *steps),)
    )
    process.start()
    deadline = time.monotonic() + 120
    while not (run / "checkpoint-2" / "run_state.json").is_file():
        assert process.is_alive() and time.monotonic() < deadline, "run ended before its first checkpoint"
        time.sleep(0.02)
    os.kill(process.pid, signal.SIGKILL)
    process.join()
    assert process.exitcode == -signal.SIGKILL
    assert not (run / "checkpoint-6").exists(), "the kill came too late to test a resume"
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    # 3. the newest checkpoint is truncated after it was sealed (a partial copy, unsynced data lost)
    if not (run / "checkpoint-4").exists():
        shutil.copytree(run / "checkpoint-2", run / "checkpoint-4")
    damaged = run / "checkpoint-4" / "model.safetensors"
    damaged.write_bytes(damaged.read_bytes()[:-100])
    # 4. resume from the newest complete and intact checkpoint, saying which one was skipped, and finish
    with caplog.at_level(logging.WARNING, logger="sar_zero123.runs.checkpoints"):
        script.main(tiny_args(assets, run, *steps, "--resume_from_checkpoint", "latest"))
    skipped = r"skipping .*checkpoint-4: .*model.safetensors' has \d+ bytes, manifest.json records"
    assert re.search(skipped, caplog.text)
    expected, actual = read_weights(reference / "checkpoint-6"), read_weights(run / "checkpoint-6")
    assert expected.keys() == actual.keys()
    assert all(torch.equal(expected[k], actual[k]) for k in expected)


@pytest.mark.slow
def test_two_process_cpu_run_keeps_replicas_identical(assets, tmp_path, run_two_process, rendezvous_port):
    out = tmp_path / "ddp"
    command = [
        "accelerate",
        "launch",
        "--multi_gpu",
        "--num_processes",
        "2",
        "--num_machines",
        "1",
        "--mixed_precision",
        "no",
        "--dynamo_backend",
        "no",
        "--main_process_ip",
        "127.0.0.1",
        "--main_process_port",
        str(rendezvous_port),
        str(SCRIPT),
        *tiny_args(
            assets,
            out,
            "--max_train_steps",
            "2",
            "--checkpointing_steps",
            "2",
            "--validation_steps",
            "0",
            "--no-save_pipeline",
        ),
    ]
    run_two_process(command, marker=str(out), timeout=180)
    state = json.loads((out / "train_state.json").read_text())
    digests = state["replica_weight_digests"]
    assert len(digests) == 2 and digests[0] == digests[1]
    assert [p.name for p in out.glob("checkpoint-*")] == ["checkpoint-2"]
    assert sorted(p.name for p in (out / "checkpoint-2").glob("random_states_*.pkl")) == [
        "random_states_0.pkl",
        "random_states_1.pkl",
    ]


# ------------------------------------------------------------------------------ --train_image_encoder
def initial_tower(seed: int = 3) -> dict[str, torch.Tensor]:
    """The random CLIP tower a ``--size tiny --seed 3`` run starts from."""
    return build_sar_zero123("tiny", seed=seed).image_encoder.state_dict()


def read_tower_state(checkpoint: Path) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    """The trained tower (third prepared model) and its EMA (second registered object) of a checkpoint."""
    tower = load_file(checkpoint / "model_2.safetensors")
    ema = torch.load(checkpoint / "custom_checkpoint_1.pkl", weights_only=False)["shadow_params"]
    return tower, ema


def tower_args(assets: dict[str, Path], output_dir: Path, *extra: str) -> list[str]:
    return tiny_args(
        assets,
        output_dir,
        "--train_image_encoder",
        "--max_train_steps",
        "2",
        "--checkpointing_steps",
        "1",
        "--num_validation_images",
        "2",
        "--validation_inference_steps",
        "2",
        *extra,
    )


@pytest.fixture(scope="module")
def tower_run(script, assets, tmp_path_factory) -> Path:
    """Two steps with ``--train_image_encoder``: checkpoints 1 and 2, validation at step 2, pipeline."""
    out = script.main(tower_args(assets, tmp_path_factory.mktemp("tower") / "run", "--validation_steps", "2"))
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    return out


def test_train_image_encoder_trains_checkpoints_and_exports_the_tower(script, tower_run) -> None:
    initial = initial_tower()
    # 1. the exported pipeline loads and carries the EMA tower, which moved away from the random init
    pipe = SARZero123Pipeline.from_pretrained(tower_run / "pipeline")
    exported = pipe.image_encoder.state_dict()
    assert exported.keys() == initial.keys()
    assert all(exported[k].dtype == torch.float32 and torch.isfinite(exported[k]).all() for k in exported)
    changed = [k for k in initial if not torch.equal(initial[k], exported[k])]
    assert changed == list(initial)  # every tensor of the tower is a trained parameter
    tower, ema = read_tower_state(tower_run / "checkpoint-2")
    parameters = [p for _, p in pipe.image_encoder.named_parameters()]
    assert len(ema) == len(parameters) and all(torch.equal(e, p) for e, p in zip(ema, parameters))
    assert not torch.equal(
        tower["image_encoder.visual_projection.weight"], initial["visual_projection.weight"]
    )
    result = pipe(
        torch.rand(1, 1, 32, 32), d_az=30.0, num_inference_steps=2, output_type="pt",
        generator=torch.Generator().manual_seed(0),
    ).images  # fmt: skip
    assert result.shape == (1, 1, 32, 32) and torch.isfinite(result).all()
    # 2. the replica digest covers the tower: recomputed from checkpoint-2 (saved before the step-2
    #    validation, so this also shows validation swapped its EMA weights back out)
    modules = build_sar_zero123("tiny", seed=3)
    modules.unet.load_state_dict(load_file(tower_run / "checkpoint-2" / "model.safetensors"))
    modules.pose_projection.load_state_dict(load_file(tower_run / "checkpoint-2" / "model_1.safetensors"))
    embedder = ImageEmbedder(modules.image_encoder)
    embedder.load_state_dict(tower)
    digest = weights_digest([modules.unet, modules.pose_projection, embedder]).item()
    assert json.loads((tower_run / "train_state.json").read_text())["replica_weight_digests"] == [digest]
    assert (tower_run / "validation" / "step-000002.png").is_file()


def test_frozen_image_encoder_is_bitwise_unchanged(script, assets, tmp_path) -> None:
    out = script.main(
        tiny_args(assets, tmp_path / "frozen", "--max_train_steps", "2", "--checkpointing_steps", "2",
                  "--validation_steps", "0")
    )  # fmt: skip
    initial = initial_tower()
    exported = SARZero123Pipeline.from_pretrained(out / "pipeline").image_encoder.state_dict()
    assert exported.keys() == initial.keys() and all(torch.equal(initial[k], exported[k]) for k in initial)
    assert not (out / "checkpoint-2" / "model_2.safetensors").exists()
    assert not (out / "checkpoint-2" / "custom_checkpoint_1.pkl").exists()


def test_a_cache_on_the_training_device_trains_the_same_weights(script, assets, tmp_path) -> None:
    args = ("--max_train_steps", "2", "--checkpointing_steps", "2", "--validation_steps", "0")
    runs = []
    for name, extra in (("host", ()), ("device", ("--cache_on_device", "--num_workers", "2"))):
        runs.append(script.main(tiny_args(assets, tmp_path / name, *args, *extra)))
        AcceleratorState._reset_state(True)
        GradientState._reset_state()
    host, device = (SARZero123Pipeline.from_pretrained(out / "pipeline").unet.state_dict() for out in runs)
    assert all(torch.equal(host[k], device[k]) for k in host)
    from sar_zero123.stages.finetune import FinetuneConfig

    with pytest.raises(ValueError, match="cache_on_device: .* needs cache_latents"):
        FinetuneConfig(pfm_weight=0.0, cache_on_device=True, cache_latents=False)
    # a schedule diffusers does not know is refused at the config, before any model loads
    unknown = r"lr_scheduler must be one of \['linear', 'cosine', .*got 'piecewise_constant'"
    with pytest.raises(ValueError, match=unknown):
        FinetuneConfig(pfm_weight=0.0, lr_scheduler="piecewise_constant")


def test_train_image_encoder_resume_restores_the_tower_bitwise(script, assets, tower_run, tmp_path) -> None:
    # the tower of checkpoint-1 is already trained, so a resume that dropped it would diverge at step 2
    step1, _ = read_tower_state(tower_run / "checkpoint-1")
    assert not torch.equal(
        step1["image_encoder.visual_projection.weight"], initial_tower()["visual_projection.weight"]
    )
    run = tmp_path / "resumed"
    script.main(
        tower_args(
            assets,
            run,
            "--validation_steps",
            "2",
            "--resume_from_checkpoint",
            str(tower_run / "checkpoint-1"),
        )
    )
    expected, actual = read_weights(tower_run / "checkpoint-2"), read_weights(run / "checkpoint-2")
    assert expected.keys() == actual.keys() and all(torch.equal(expected[k], actual[k]) for k in expected)
    (tower, ema), (tower_resumed, ema_resumed) = map(
        read_tower_state, (tower_run / "checkpoint-2", run / "checkpoint-2")
    )
    assert tower.keys() == tower_resumed.keys() and all(
        torch.equal(tower[k], tower_resumed[k]) for k in tower
    )
    assert len(ema) == len(ema_resumed) and all(torch.equal(a, b) for a, b in zip(ema, ema_resumed))


def test_resume_with_the_other_train_image_encoder_setting_is_refused(script, assets, tower_run, tmp_path):
    checkpoint = tower_run / "checkpoint-1"
    assert json.loads((checkpoint / "run_state.json").read_text())["train_image_encoder"] is True
    argv = tiny_args(assets, tmp_path / "frozen", "--resume_from_checkpoint", str(checkpoint))
    with pytest.raises(ValueError, match=r"resume_from_checkpoint: .* train_image_encoder=True"):
        script.main(argv)
    assert not (tmp_path / "frozen").exists()  # refused before anything was written


def test_train_image_encoder_keeps_float32_master_weights_under_bf16(script, assets, tmp_path) -> None:
    out = script.main(
        tower_args(assets, tmp_path / "bf16", "--mixed_precision", "bf16", "--validation_steps", "0",
                   "--max_train_steps", "1", "--no-save_pipeline")
    )  # fmt: skip
    tower, ema = read_tower_state(out / "checkpoint-1")
    initial = initial_tower()
    assert all(v.dtype == torch.float32 for v in tower.values()) and all(
        e.dtype == torch.float32 for e in ema
    )
    weight = tower["image_encoder.visual_projection.weight"]
    assert torch.isfinite(weight).all() and not torch.equal(weight, initial["visual_projection.weight"])


def test_diverging_run_stops_before_saving_or_exporting_nan_weights(script, assets, tmp_path) -> None:
    run = tmp_path / "diverge"
    argv = tiny_args(assets, run, "--learning_rate", "1e30", "--max_train_steps", "4",
                     "--checkpointing_steps", "1", "--validation_steps", "0")  # fmt: skip
    with pytest.raises(FloatingPointError, match=r"training diverged at step \d+: loss=(nan|inf)"):
        script.main(argv)
    assert not (run / "pipeline").exists()
    for checkpoint in run.glob("checkpoint-*"):
        assert all(torch.isfinite(w).all() for w in read_weights(checkpoint).values()), checkpoint


def test_losses_reach_the_host_every_logging_steps_and_at_each_checkpoint(
    script, assets, tmp_path, monkeypatch
) -> None:
    from sar_zero123.training import finetuning

    steps = []  # the steps whose losses were gathered and checked
    monkeypatch.setattr(finetuning, "check_finite_step", lambda step, **values: steps.append(step))
    argv = tiny_args(assets, tmp_path / "run", "--max_train_steps", "7", "--checkpointing_steps", "5",
                     "--logging_steps", "3", "--validation_steps", "0", "--pfm_weight", "0")  # fmt: skip
    script.main(argv)
    assert steps == [3, 5, 6, 7]  # every third step, the checkpoint at 5 and the last step
    with pytest.raises(ValueError, match="logging_steps must be >= 1"):
        script.main(tiny_args(assets, tmp_path / "other", "--logging_steps", "0"))


@pytest.mark.parametrize(
    ("changed", "listed"),
    [
        (("--learning_rate", "1.0"), r"learning_rate: checkpoint 0.0001, this run 1.0"),
        (("--image_size", "16"), r"image_size: checkpoint None, this run 16"),
        (("--pfm_weight", "2"), r"pfm_weight: checkpoint 4.0, this run 2.0"),
    ],
)
def test_resume_with_changed_settings_is_refused(script, assets, tower_run, tmp_path, changed, listed):
    argv = tower_args(assets, tmp_path / "changed", "--validation_steps", "2", *changed,
                      "--resume_from_checkpoint", str(tower_run / "checkpoint-1"))  # fmt: skip
    with pytest.raises(ValueError, match=rf"other settings that change the run.*{listed}"):
        script.main(argv)
    assert not (tmp_path / "changed").exists()  # refused before config.json was written


def test_output_dir_that_is_a_file_is_refused_before_loading(script, assets, tmp_path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match=r"output_dir: .*file' is a file; expected a folder"):
        script.main(tiny_args(assets, tmp_path / "file"))


def test_estimate_input_azimuth_trains_checkpoints_and_exports_it(script, assets, tmp_path) -> None:
    out = script.main(
        tiny_args(
            assets,
            tmp_path / "estimator",
            "--max_train_steps", "2", "--checkpointing_steps", "2", "--validation_steps", "2",
            "--num_validation_images", "2", "--validation_inference_steps", "2", "--pfm_weight", "0",
            "--estimate_input_azimuth", "--input_code_dim", "3",
        )
    )  # fmt: skip
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    initial = build_sar_zero123("tiny", seed=3, estimate_input_azimuth=True, input_code_dim=3)
    initial = initial.azimuth_estimator
    pipe = SARZero123Pipeline.from_pretrained(out / "pipeline")
    assert isinstance(pipe.azimuth_estimator, AzimuthEstimator) and pipe.azimuth_estimator.output_dim == 5
    trained = pipe.azimuth_estimator.state_dict()
    assert all(not torch.equal(trained[k], v) for k, v in initial.state_dict().items())
    # the estimator is the third trained module of the checkpoint (after the UNet and the pose projection)
    saved = load_file(out / "checkpoint-2" / "model_2.safetensors")
    assert all(torch.equal(saved[k], trained[k]) for k in trained)
    logged = json.loads((out / "validation" / "metrics.jsonl").read_text().splitlines()[-1])
    assert 0.0 <= logged["validation/loss_azimuth"] <= 2.0


# ------------------------------------------------------------------------------ the run-folder rule
def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by relative path, with its bytes."""
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in files}


def one_step_args(assets: dict[str, Path], output_dir: Path, *extra: str) -> list[str]:
    return tiny_args(assets, output_dir, "--max_train_steps", "1", "--checkpointing_steps", "1",
                     "--validation_steps", "0", "--pfm_weight", "0", *extra)  # fmt: skip


@pytest.fixture(scope="module")
def finished_run(script, assets, tmp_path_factory) -> Path:
    """A finished one-step run (constant learning rate), copied by the tests that change it."""
    out = script.main(one_step_args(assets, tmp_path_factory.mktemp("finished") / "run"))
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    return out


def test_a_finished_run_is_recorded_with_its_data_and_last_output(finished_run, assets) -> None:
    record = json.loads((finished_run / "run.json").read_text())
    assert record["stage"] == "finetune" and record["finished"] is True
    assert record["outputs"] == ["train_state.json", "pipeline/model_index.json"]
    assert record["results"] == {"final_step": 1} and record["seconds"] > 0
    assert record["config"]["max_train_steps"] == 1 and record["config"]["restart"] is False
    index = (assets["data"] / "index.csv").read_bytes()
    assert record["data"]["data"]["index_sha256"] == hashlib.sha256(index).hexdigest()


def test_reusing_a_finished_run_without_resume_is_refused_and_changes_nothing(script, assets, finished_run):
    before = snapshot(finished_run)
    message = rf"output_dir: '{re.escape(str(finished_run))}' already holds a finished finetune run"
    with pytest.raises(ValueError, match=rf"{message}.*--resume_from_checkpoint latest.*--restart"):
        script.main(one_step_args(assets, finished_run))
    with pytest.raises(ValueError, match=r"Differences: learning_rate: folder 0.0001, this run 0.001\."):
        script.main(one_step_args(assets, finished_run, "--learning_rate", "1e-3"))
    assert snapshot(finished_run) == before


def test_restart_moves_the_old_run_aside_and_starts_over(script, assets, finished_run, tmp_path) -> None:
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = snapshot(run)
    script.main(one_step_args(assets, run, "--learning_rate", "1e-3", "--restart"))
    (aside,) = tmp_path.glob("run.replaced-*")
    assert snapshot(aside) == before  # the old run, every file as it was
    record = json.loads((run / "run.json").read_text())
    assert record["finished"] is True and record["config"]["learning_rate"] == 1e-3
    assert (run / "pipeline" / "model_index.json").is_file()
    with pytest.raises(ValueError, match="restart: .*resume_from_checkpoint"):
        script.main(one_step_args(assets, run, "--restart", "--resume_from_checkpoint", "latest"))


def test_resuming_a_constant_lr_run_with_more_steps_continues_it(script, assets, finished_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    script.main(one_step_args(assets, run, "--max_train_steps", "2", "--resume_from_checkpoint", "latest"))
    record = json.loads((run / "run.json").read_text())
    assert record["finished"] is True and record["results"] == {"final_step": 2}
    assert record["config"]["max_train_steps"] == 2
    assert [entry["changed"] for entry in record["continued"]] == [{"max_train_steps": {"from": 1, "to": 2}}]
    assert json.loads((run / "train_state.json").read_text())["global_step"] == 2
    assert sorted(p.name for p in run.glob("checkpoint-*")) == ["checkpoint-1", "checkpoint-2"]
    # continued again with the same settings: finished, nothing to do, nothing rewritten
    before = snapshot(run)
    script.main(one_step_args(assets, run, "--max_train_steps", "2", "--resume_from_checkpoint", "latest"))
    assert snapshot(run) == before
    # resumed with fewer steps than the checkpoint's: refused before the record changes (issue 39)
    fewer = one_step_args(assets, run, "--max_train_steps", "1", "--resume_from_checkpoint", "latest")
    with pytest.raises(ValueError, match=r"^max_train_steps: 1 is below the step of the checkpoint"):
        script.main(fewer)
    assert snapshot(run) == before


def test_gradient_accumulation_beyond_one_epoch_is_refused_with_its_bound(script, assets, tmp_path) -> None:
    run = tmp_path / "run"
    with pytest.raises(ValueError, match=r"gradient_accumulation_steps must be <= \d+ for \d+ training pairs "
                                         r"in global batches of 2 .*got 100000"):  # fmt: skip
        script.main(one_step_args(assets, run, "--gradient_accumulation_steps", "100000"))
    assert not run.exists() or not any(run.iterdir())  # the run never began: its record is withdrawn
    with pytest.raises(ValueError, match=r"^gradient_accumulation_steps must be <= 12 for 48 training pairs"):
        check_global_batch(48, 4, 1, what="pairs", gradient_accumulation_steps=13)
    check_global_batch(48, 4, 1, what="pairs", gradient_accumulation_steps=12)  # one epoch per step


def test_max_train_minutes_stops_exports_and_leaves_the_run_resumable(script, assets, tmp_path) -> None:
    run = tmp_path / "run"
    # the clock stops the run after its first step, long before 50 steps
    script.main(one_step_args(assets, run, "--max_train_steps", "50", "--checkpointing_steps", "50",
                              "--max_train_minutes", "1e-9", "--spatial_pose", "rotated_input"))  # fmt: skip
    assert json.loads((run / "train_state.json").read_text())["global_step"] == 1
    assert sorted(p.name for p in run.glob("checkpoint-*")) == ["checkpoint-1"]
    assert json.loads((run / "run.json").read_text())["finished"] is False
    pipe = SARZero123Pipeline.from_pretrained(run / "pipeline")  # the pipeline at the step reached
    assert pipe.pose_projection.config.spatial_pose == "rotated_input" and pipe.unet.config.in_channels == 12
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    # the same command with --resume_from_checkpoint latest continues (another minute-limited session)
    script.main(one_step_args(assets, run, "--max_train_steps", "50", "--checkpointing_steps", "50",
                              "--max_train_minutes", "1e-9", "--spatial_pose", "rotated_input",
                              "--resume_from_checkpoint", "latest"))  # fmt: skip
    assert json.loads((run / "train_state.json").read_text())["global_step"] == 2
    with pytest.raises(ValueError, match="spatial_pose: only for a model built from scratch"):
        script.main(one_step_args(assets, tmp_path / "other", "--pretrained", str(run / "pipeline"),
                                  "--spatial_pose", "rotated_input"))  # fmt: skip
    with pytest.raises(ValueError, match="max_train_minutes must be > 0"):
        script.main(one_step_args(assets, tmp_path / "other", "--max_train_minutes", "0"))


def test_rehearsal_mixes_corpus_pairs_into_the_fine_tune_and_widens_its_ranges(script, assets, tmp_path):
    from sar_zero123.sim.corpus import write_prior_corpus

    corpus = write_prior_corpus(tmp_path / "corpus", num_vehicles=4, views_per_vehicle=4,
                                num_validation_vehicles=1, size=32, progress=False)  # fmt: skip
    run = tmp_path / "run"
    script.main(one_step_args(assets, run, "--max_train_steps", "2", "--checkpointing_steps", "2",
                              "--rehearsal_data", str(corpus), "--rehearsal_fraction", "0.5"))  # fmt: skip
    projection = SARZero123Pipeline.from_pretrained(run / "pipeline").pose_projection.config
    depressions = [r.depression_deg for r in load_index(corpus) if r.target_class != "PROCVAL"]
    assert projection.trained_depression_deg[0] <= min(min(depressions), 15.0)  # the corpus's, beside 15/17
    assert projection.trained_depression_deg[1] >= max(max(depressions), 17.0)
    assert projection.trained_d_el_deg[1] > 2.0  # the task alone pairs only at one depression
    with pytest.raises(FileNotFoundError, match="rehearsal_data: expected a prior corpus folder"):
        script.main(one_step_args(assets, tmp_path / "other", "--rehearsal_data", str(assets["data"])))
    with pytest.raises(ValueError, match=r"rehearsal_fraction must lie in \[0, 1\), got 1.0"):
        script.main(one_step_args(assets, tmp_path / "other", "--rehearsal_fraction", "1"))
    with pytest.raises(ValueError, match="rehearsal_max_chips must be None or >= 2, got 1"):
        script.main(one_step_args(assets, tmp_path / "other", "--rehearsal_max_chips", "1"))


def test_options_measured_to_do_nothing_are_refused_by_name_and_old_records_still_read(tmp_path) -> None:
    from sar_zero123.config import parse_config
    from sar_zero123.runs.folder import open_run_folder
    from sar_zero123.stages.finetune import FinetuneConfig

    encoder = str(tmp_path / "encoder")
    for flag, value in (("pfm_start_step", "500"), ("pfm_stop_step", "300"), ("pfm_monotonic_q", "512")):
        with pytest.raises(ValueError, match=rf"--{flag} was removed: .*; PFM (applies|compares)"):
            parse_config(FinetuneConfig, [f"--{flag}", value, "--encoder", encoder])
    # a config file written before they went: their old defaults read as before, another value is refused
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"encoder": encoder, "size": "tiny", "pfm_start_step": 0, "pfm_stop_step": None,
                               "pfm_monotonic_q": 0}))  # fmt: skip
    assert parse_config(FinetuneConfig, ["--config", str(old)]).size == "tiny"
    old.write_text(json.dumps({"encoder": encoder, "pfm_start_step": 500}))
    with pytest.raises(ValueError, match=r"pfm_start_step=500, but pfm_start_step was removed: PFM switched"):
        parse_config(FinetuneConfig, ["--config", str(old)])
    # a run folder recorded with them: resumable at the old defaults, refused by name otherwise
    config = FinetuneConfig(output_dir=str(tmp_path / "run"), size="tiny", encoder=encoder)
    folder = open_run_folder(config.output_dir, "finetune", config, data={})
    record_path = folder.path / "run.json"
    record = json.loads(record_path.read_text())
    record["config"].update(pfm_start_step=0, pfm_stop_step=None, pfm_monotonic_q=0)
    record_path.write_text(json.dumps(record))
    assert open_run_folder(config.output_dir, "finetune", config, data={}, resume=True).status != "new"
    record["config"]["pfm_monotonic_q"] = 512
    record_path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match="pfm_monotonic_q=512, but pfm_monotonic_q was removed"):
        open_run_folder(config.output_dir, "finetune", config, data={}, resume=True)


def test_the_retired_lora_balance_timestep_and_crop_settings_are_refused_by_name(tmp_path) -> None:
    """LoRA, the adaptive PFM balance, logit-normal timesteps and the PFM crop were removed: a flag, --set or
    a config file naming one is refused with the field and why it went; their old defaults still read."""
    from sar_zero123.config import drop_removed_fields, parse_config
    from sar_zero123.stages.finetune import FinetuneConfig

    encoder = str(tmp_path / "encoder")
    for flag, value in (("lora_rank", "4"), ("lora_alpha", "8"), ("lora_modules", "attention"),
                        ("pfm_balance", "adaptive"), ("timestep_sampling", "logit_normal"),
                        ("timestep_logit_mean", "1.0"), ("timestep_logit_std", "0.5"),
                        ("pfm_crop_size", "16")):  # fmt: skip
        with pytest.raises(ValueError, match=rf"^--{flag} was removed: "):
            parse_config(FinetuneConfig, [f"--{flag}", value, "--encoder", encoder])
    with pytest.raises(ValueError, match=r"^--set lora_rank: lora_rank was removed: a low-rank update"):
        parse_config(FinetuneConfig, ["--set", "lora_rank=4", "--encoder", encoder])
    old = {"lora_rank": None, "lora_alpha": None, "lora_modules": "all", "pfm_balance": "none",
           "timestep_sampling": "uniform", "timestep_logit_mean": 0.0, "timestep_logit_std": 1.0,
           "pfm_crop_size": None, "seed": 1}  # fmt: skip
    assert drop_removed_fields(FinetuneConfig, old, "run") == {"seed": 1}
    with pytest.raises(ValueError, match=r"^run: lora_rank=4, but lora_rank was removed: "):
        drop_removed_fields(FinetuneConfig, {**old, "lora_rank": 4}, "run")
    file = tmp_path / "old.json"
    file.write_text(json.dumps({"encoder": encoder, "timestep_sampling": "logit_normal"}))
    with pytest.raises(ValueError, match="sampling='logit_normal', but timestep_sampling was removed: "):
        parse_config(FinetuneConfig, ["--config", str(file)])


def test_the_exported_pipeline_records_the_vae_it_was_trained_with(finished_run) -> None:
    from sar_zero123.model.conditioning import vae_signature

    pose = json.loads((finished_run / "pipeline" / "pose_projection" / "config.json").read_text())
    vae = json.loads((finished_run / "pipeline" / "vae" / "config.json").read_text())
    assert pose["trained_vae"] == vae_signature(vae)
    assert set(pose["trained_vae"]) == {"sample_size", "block_out_channels", "latent_channels",
                                        "scaling_factor"}  # fmt: skip


def test_export_records_the_lineage_and_drops_a_killed_exports_half_written_file(tmp_path) -> None:
    from sar_zero123.data import DecibelScaling
    from sar_zero123.training.finetuning import export_finetuned
    from tests.dummies import get_dummy_components

    directory = tmp_path / "pipeline"
    directory.mkdir()
    (directory / ".model_index.json.x1y2.tmp").write_text("{")  # what a kill during a write leaves
    lineage = {"start": "sar-zero123/sim-prior-rotated", "start_weights": "ab" * 32}
    pipe = SARZero123Pipeline(**get_dummy_components())
    export_finetuned(directory, pipe, DecibelScaling(), lineage=lineage)
    assert not list(directory.glob(".*.tmp"))
    assert SARZero123Pipeline.from_pretrained(directory).config.lineage == lineage
    with pytest.raises(ValueError, match="`lineage` must be a dict of strings"):
        SARZero123Pipeline(**get_dummy_components(), lineage={"start": 3})
