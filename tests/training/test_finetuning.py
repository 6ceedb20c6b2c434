"""Tests for sar_zero123.training.finetuning: module set-up, parameter groups, EMA, step logs, the export."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from accelerate import Accelerator
from accelerate.state import AcceleratorState

from sar_zero123.data import DecibelScaling
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.training.finetuning import (
    ema_models,
    export_finetuned,
    finetuning_modules,
    finetuning_optimizer,
    mixed_precision_dtype,
    step_logs,
    training_image_size,
)
from sar_zero123.training.losses import LossOutput
from tests.dummies import get_dummy_components


@pytest.fixture
def pipe() -> SARZero123Pipeline:
    return SARZero123Pipeline(**get_dummy_components())


@pytest.fixture
def accelerator():
    yield Accelerator(cpu=True)
    AcceleratorState._reset_state(True)


def test_training_image_size_defaults_to_the_model_and_checks_the_multiple(pipe) -> None:
    assert pipe.size_multiple == 4 and training_image_size(pipe) == pipe.default_image_size == 32
    assert training_image_size(pipe, 16) == 16
    with pytest.raises(ValueError, match="image_size must be a multiple of 4, got 18"):
        training_image_size(pipe, 18)


@pytest.mark.parametrize("train_image_encoder", [False, True])
def test_finetuning_modules_freeze_and_cast_what_is_not_trained(pipe, train_image_encoder) -> None:
    assert mixed_precision_dtype("bf16") == torch.bfloat16 and mixed_precision_dtype("no") == torch.float32
    vae, embedder, unet, pose_projection = finetuning_modules(
        pipe, device="cpu", weight_dtype=torch.bfloat16, train_image_encoder=train_image_encoder
    )
    assert vae is pipe.vae and unet is pipe.unet and pose_projection is pipe.pose_projection
    assert embedder.image_encoder is pipe.image_encoder  # export and validation read pipe's modules
    assert vae.dtype == torch.bfloat16 and not vae.training
    assert not any(p.requires_grad for p in vae.parameters())
    for module in (unet, pose_projection):
        assert module.training
        assert all(p.requires_grad and p.dtype == torch.float32 for p in module.parameters())
    tower = list(embedder.parameters())
    expected_dtype = torch.float32 if train_image_encoder else torch.bfloat16
    assert all(p.dtype == expected_dtype and p.requires_grad == train_image_encoder for p in tower)
    assert embedder.image_encoder.training == train_image_encoder


def test_finetuning_optimizer_puts_the_pose_projection_at_its_multiple(pipe) -> None:
    _, embedder, unet, pose_projection = finetuning_modules(
        pipe, device="cpu", weight_dtype=torch.float32, train_image_encoder=True
    )
    optimizer = finetuning_optimizer(
        unet, pose_projection, embedder, learning_rate=1e-4, pose_lr_multiplier=10.0
    )
    assert [group["lr"] for group in optimizer.param_groups] == pytest.approx([1e-4, 1e-3, 1e-4])
    modules = (unet, pose_projection, embedder)
    for group, module in zip(optimizer.param_groups, modules):
        assert [id(p) for p in group["params"]] == [id(p) for p in module.parameters()]
        assert group["weight_decay"] == 1e-2
    assert len(finetuning_optimizer(unet, pose_projection, learning_rate=1e-4).param_groups) == 2


def test_ema_models_pair_each_trained_module_and_register_them_in_order(pipe, accelerator) -> None:
    _, embedder, unet, _ = finetuning_modules(pipe, device="cpu", weight_dtype=torch.float32)
    pairs = ema_models(accelerator, unet, embedder, decay=0.9)
    assert [module for _, module in pairs] == [unet, embedder]
    assert accelerator._custom_objects == [ema for ema, _ in pairs]  # checkpoint file names follow this order
    assert len(ema_models(accelerator, unet, decay=0.9)) == 1


def test_step_logs_are_means_over_the_batch_and_per_timestep_quarter(accelerator) -> None:
    losses = LossOutput(
        loss=torch.tensor([1.0, 3.0, 5.0, 7.0]),
        denoising=torch.tensor([1.0, 2.0, 3.0, 4.0]),
        pfm=torch.tensor([0.0, 0.5, 1.0, 1.5]),
        pfm_mask=torch.tensor([False, True, True, True]),
        timesteps=torch.tensor([0, 10, 600, 999]),
    )
    logs = step_logs(accelerator, losses, learning_rate=2e-4, num_train_timesteps=1000)
    assert logs["train/loss"] == 4.0 and logs["train/loss_simple"] == 2.5 and logs["train/loss_pfm"] == 0.75
    assert logs["lr"] == 2e-4
    quarters = {name: value for name, value in logs.items() if name.startswith("train/loss_simple_")}
    assert quarters == {"train/loss_simple_t000-249": 1.5, "train/loss_simple_t500-749": 3.0,
                        "train/loss_simple_t750-999": 4.0}  # fmt: skip


def test_export_finetuned_saves_the_ema_weights_and_the_scaling(pipe, accelerator, tmp_path: Path) -> None:
    _, embedder, unet, _ = finetuning_modules(pipe, device="cpu", weight_dtype=torch.float32)
    initial = {name: p.detach().clone() for name, p in unet.named_parameters()}
    pairs = ema_models(accelerator, unet, embedder, decay=0.9)
    with torch.no_grad():
        for p in unet.parameters():
            p.add_(1.0)  # the trained weights move; the EMA (no step taken) keeps the initial ones
    scaling = DecibelScaling(min_db=-50.0, max_db=5.0)
    folder = export_finetuned(tmp_path / "pipeline", pipe, scaling, pairs)
    loaded = SARZero123Pipeline.from_pretrained(folder)
    for name, p in loaded.unet.named_parameters():
        torch.testing.assert_close(p, initial[name], rtol=0, atol=0)
    assert type(loaded.scheduler).__name__ == "DDIMScheduler"
    assert json.loads((folder / "decibel_scaling.json").read_text()) == scaling.to_dict()


def test_export_finetuned_refuses_non_finite_weights(pipe, tmp_path: Path) -> None:
    with torch.no_grad():
        next(pipe.unet.parameters()).fill_(float("nan"))
    with pytest.raises(FloatingPointError, match="unet"):
        export_finetuned(tmp_path / "pipeline", pipe, DecibelScaling())
    assert not (tmp_path / "pipeline").exists()
