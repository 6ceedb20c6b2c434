"""Tests of train/train_vae.py: a short run on fabricated chips, the saved model and its metrics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from accelerate.state import AcceleratorState, GradientState
from diffusers import AutoencoderKL
from safetensors.torch import load_file
from skimage.metrics import peak_signal_noise_ratio

from sar_zero123.config import parse_config
from sar_zero123.data import ChipDataset, ChipRecord, load_index, write_index
from train import train_vae

TINY = [
    "--image_size",
    "32",
    "--block_out_channels",
    "8",
    "8",
    "--norm_num_groups",
    "4",
    "--layers_per_block",
    "1",
    "--train_batch_size",
    "4",
    "--report_to",
    "none",
]


@pytest.fixture(scope="module")
def script():
    return train_vae


@pytest.fixture(autouse=True)
def fresh_accelerate_state():
    yield
    AcceleratorState._reset_state(True)
    GradientState._reset_state()


@pytest.fixture(scope="module")
def chips(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("vae_chips")
    rng = np.random.default_rng(0)
    records = []
    for depression in (15.0, 17.0):
        for k in range(8):
            path = root / f"A_{int(depression)}_{k}.npy"
            np.save(path, rng.random((32, 32), dtype=np.float32))
            records.append(
                ChipRecord(
                    path=path, target_class="A", serial="s", depression_deg=depression, azimuth_deg=40.0 * k
                )
            )
    write_index(records, root)
    return root


def test_train_vae_saves_model_metrics_and_scaling_factor(script, chips, tmp_path) -> None:
    out = script.main(
        [
            "--data",
            str(chips),
            "--output_dir",
            str(tmp_path / "vae"),
            "--max_train_steps",
            "3",
            "--checkpointing_steps",
            "3",
            *TINY,
        ]
    )
    vae = AutoencoderKL.from_pretrained(out / "vae").eval()
    assert vae.config.in_channels == 1 and vae.config.latent_channels == 4
    assert len(vae.config.block_out_channels) == 2  # 32 px -> 16x16x4 latents
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_images"] == 8 and metrics["steps"] == 3
    assert (
        metrics["scaling_factor"] == pytest.approx(vae.config.scaling_factor)
        and metrics["scaling_factor"] > 0
    )
    # the recorded PSNR is scikit-image's on the 15 deg (test) chips
    test_records = [r for r in load_index(chips) if r.depression_deg == 15.0]
    dataset = ChipDataset(test_records, size=32)
    images = torch.stack([dataset[i]["image"] for i in range(len(dataset))])
    recon = script.reconstruct(vae, images).numpy()[:, 0].astype(np.float64)
    psnr = np.mean(
        [
            peak_signal_noise_ratio(a, b, data_range=1.0)
            for a, b in zip(images.numpy()[:, 0].astype(np.float64), recon)
        ]
    )
    assert metrics["psnr_db"] == pytest.approx(psnr, rel=1e-5)
    assert 0.0 < metrics["psnr_db"] < 60.0 and -1.0 <= metrics["ssim"] <= 1.0
    assert (out / "checkpoint-3" / "run_state.json").is_file()


def test_objective_losses_per_sample(script) -> None:
    torch.manual_seed(0)
    config = script.TrainVAEConfig(
        image_size=32, block_out_channels=(8, 8), norm_num_groups=4, layers_per_block=1
    )
    objective = script.VAEObjective(script.build_vae(config), kl_weight=0.0, reconstruction_loss="l2")
    images = torch.rand(3, 1, 32, 32)
    total, reconstruction = objective(images, generator=torch.Generator().manual_seed(0))
    assert total.shape == reconstruction.shape == (3,)
    torch.testing.assert_close(total, reconstruction)  # kl_weight = 0
    posterior = objective.vae.encode(images * 2 - 1).latent_dist
    expected = (
        (objective.vae.decode(posterior.sample(torch.Generator().manual_seed(0))).sample - (images * 2 - 1))
        .pow(2)
        .flatten(1)
        .mean(1)
    )
    torch.testing.assert_close(reconstruction, expected, rtol=1e-5, atol=1e-6)


def test_bad_config_names_the_field(script, tmp_path) -> None:
    with pytest.raises(ValueError, match="image_size"):
        script.TrainVAEConfig(image_size=30, block_out_channels=(8, 8, 8), norm_num_groups=4)
    with pytest.raises(ValueError, match="norm_num_groups"):
        script.TrainVAEConfig(block_out_channels=(8, 12), norm_num_groups=8)
    # a removed setting: a config file at its old default reads as before, another value is refused
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"kl_weight": 1e-6, "reconstruction_loss": "l1"}))
    assert parse_config(script.TrainVAEConfig, ["--config", str(old)]) == script.TrainVAEConfig()
    old.write_text(json.dumps({"kl_weight": -1.0}))
    refused = "kl_weight=-1.0, but kl_weight was removed: the KL term's weight is 1e-06"
    with pytest.raises(ValueError, match=refused):
        parse_config(script.TrainVAEConfig, ["--config", str(old)])
    with pytest.raises(ValueError, match="protocol"):
        script.TrainVAEConfig(protocol="nope")


def test_diverging_run_stops_before_saving_nan_weights(script, chips, tmp_path) -> None:
    out = tmp_path / "diverge"
    argv = ["--data", str(chips), "--output_dir", str(out), "--max_train_steps", "4", *TINY]
    with pytest.raises(FloatingPointError, match=r"training diverged at step \d+: loss=(nan|inf)"):
        script.main([*argv, "--learning_rate", "1e30", "--checkpointing_steps", "1"])
    assert not (out / "vae").exists()
    for checkpoint in out.glob("checkpoint-*"):
        weights = load_file(checkpoint / "model.safetensors")
        assert all(torch.isfinite(w).all() for w in weights.values()), checkpoint


def test_resume_with_another_setting_is_refused(script, chips, tmp_path) -> None:
    out = tmp_path / "vae"
    argv = ["--data", str(chips), "--output_dir", str(out), "--checkpointing_steps", "1", *TINY]
    script.main([*argv, "--max_train_steps", "1"])  # resumed below to 2000 steps: allowed for a VAE
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    with pytest.raises(ValueError, match=r"learning_rate: checkpoint 0.0001, this run 0.5"):
        script.main([*argv, "--learning_rate", "0.5", "--resume_from_checkpoint", "latest"])


def test_reusing_a_finished_run_is_refused_and_more_steps_continue_it(script, chips, tmp_path) -> None:
    out = tmp_path / "vae"
    argv = ["--data", str(chips), "--output_dir", str(out), "--checkpointing_steps", "1", *TINY]
    script.main([*argv, "--max_train_steps", "1"])
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    before = {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    with pytest.raises(ValueError, match=r"already holds a finished vae run.*--restart"):
        script.main([*argv, "--max_train_steps", "1"])
    with pytest.raises(ValueError, match=r"Differences: max_train_steps: folder 1, this run 2"):
        script.main([*argv, "--max_train_steps", "2"])  # more steps only when continuing
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before
    script.main([*argv, "--max_train_steps", "2", "--resume_from_checkpoint", "latest"])
    record = json.loads((out / "run.json").read_text())
    assert record["finished"] is True and record["results"] == {"final_step": 2}
    assert json.loads((out / "metrics.json").read_text())["steps"] == 2


def test_the_retired_decoder_fine_tune_reads_at_its_defaults_and_refuses_another_value(script, tmp_path):
    """pretrained, train_encoder and the feature loss were retired: a record at their old defaults loads."""
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"pretrained": None, "train_encoder": True, "feature_loss_weight": 0.0,
                               "feature_encoder": None}))  # fmt: skip
    assert parse_config(script.TrainVAEConfig, ["--config", str(old)]) == script.TrainVAEConfig()
    for values, name in [
        ({"train_encoder": False}, "train_encoder"),
        ({"feature_loss_weight": 1.0}, "feature_loss_weight"),
        ({"pretrained": "sar-zero123/sim-prior-rotated"}, "pretrained"),
    ]:
        old.write_text(json.dumps(values))
        with pytest.raises(ValueError, match=rf"{name}=.*, but {name} was removed: "):
            parse_config(script.TrainVAEConfig, ["--config", str(old)])
