"""Tests for the SAR encoder, projection head and NT-Xent loss."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sar_zero123.encoder import (
    ProjectionHead,
    SAREncoder,
    SAREncoderConfig,
    nt_xent_loss,
    resolve_encoder_dir,
)

TINY = {"image_size": 32, "hidden_sizes": (8, 16, 16, 16), "embedding_size": 8}


def tiny_encoder(**overrides) -> SAREncoder:
    torch.manual_seed(0)
    return SAREncoder(SAREncoderConfig(**{**TINY, **overrides}))


def numpy_nt_xent(z1: np.ndarray, z2: np.ndarray, temperature: float) -> np.ndarray:
    """Double-loop reference of NT-Xent: per-pair mean of the two anchor losses."""
    z = np.concatenate([z1, z2]).astype(np.float64)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    two_n = z.shape[0]
    n = two_n // 2
    anchor = np.zeros(two_n)
    for i in range(two_n):
        j = (i + n) % two_n
        denominator = 0.0
        for k in range(two_n):
            if k != i:
                denominator += math.exp(float(z[i] @ z[k]) / temperature)
        anchor[i] = -math.log(math.exp(float(z[i] @ z[j]) / temperature) / denominator)
    return (anchor[:n] + anchor[n:]) / 2


def test_reference_backbone_parameter_count():
    # CIFAR-stem ResNet-18 of the reference implementation: 11,168,832 with 3 channels;
    # the 1-channel stem has 2 * 64 * 3 * 3 = 1,152 fewer weights.
    counts = {}
    for channels in (3, 1):
        encoder = SAREncoder(SAREncoderConfig(in_channels=channels))
        counts[channels] = sum(p.numel() for p in encoder.parameters())
    assert counts == {3: 11_168_832, 1: 11_167_680}


def test_forward_shape_feature_dim_and_stem_resolution():
    encoder = tiny_encoder().eval()
    x = torch.rand(3, 1, 32, 32)
    h = encoder(x)
    assert h.shape == (3, 16) and encoder.feature_dim == 16
    # CIFAR stem keeps full resolution into stage 1 (32 -> 4 after three stride-2 stages).
    last = encoder.resnet(x * 2 - 1).last_hidden_state
    assert last.shape[-2:] == (4, 4)
    imagenet = tiny_encoder(cifar_stem=False).eval()
    assert imagenet.resnet(x * 2 - 1).last_hidden_state.shape[-2:] == (1, 1)


def test_three_channel_encoder_replicates_single_channel():
    encoder = tiny_encoder(in_channels=3).eval()
    x = torch.rand(2, 1, 32, 32)
    torch.testing.assert_close(encoder(x), encoder(x.repeat(1, 3, 1, 1)))


def test_gradients_reach_the_input_of_a_frozen_encoder():
    encoder = tiny_encoder().eval().requires_grad_(False)
    x = torch.rand(2, 1, 32, 32, requires_grad=True)
    encoder(x).pow(2).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in encoder.parameters())


@pytest.mark.parametrize(
    ("shape", "field"),
    [((1, 32, 32), "rank"), ((2, 2, 32, 32), "in_channels"), ((2, 1, 16, 32), "image_size")],
)
def test_forward_rejects_bad_input(shape, field):
    with pytest.raises(ValueError, match=field):
        tiny_encoder()(torch.rand(*shape))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"in_channels": 2}, "in_channels"), ({"image_size": 4}, "image_size"), ({"depths": (2, 2)}, "depths")],
)
def test_config_rejects_bad_fields(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SAREncoderConfig(**{**TINY, **kwargs})


def test_save_load_round_trip(tmp_path):
    encoder = tiny_encoder(cifar_stem=False)
    encoder.train()
    encoder(torch.rand(4, 1, 32, 32))  # move BatchNorm running statistics away from their init
    encoder.eval()
    x = torch.rand(2, 1, 32, 32)
    expected = encoder(x)
    encoder.save_pretrained(tmp_path / "enc")
    assert sorted(p.name for p in (tmp_path / "enc").iterdir()) == ["config.json", "model.safetensors"]
    loaded = SAREncoder.from_pretrained(tmp_path / "enc")
    assert not loaded.training and loaded.config == encoder.config
    torch.testing.assert_close(loaded(x), expected, rtol=0, atol=0)


def test_from_pretrained_missing_path_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        SAREncoder.from_pretrained(tmp_path / "nowhere")


def test_resolve_encoder_dir_accepts_run_or_encoder_folder(tmp_path):
    tiny_encoder().save_pretrained(tmp_path / "run" / "encoder")
    assert resolve_encoder_dir(tmp_path / "run") == tmp_path / "run" / "encoder"
    assert resolve_encoder_dir(tmp_path / "run" / "encoder") == tmp_path / "run" / "encoder"
    with pytest.raises(FileNotFoundError, match="simclr_encoders: no SAR encoder"):
        resolve_encoder_dir(tmp_path, field="simclr_encoders")


def test_projection_head_shape():
    torch.manual_seed(0)
    head = ProjectionHead(16, 16, 8)
    assert head(torch.randn(5, 16)).shape == (5, 8)
    assert sum(p.numel() for p in ProjectionHead().parameters()) == 512 * 512 + 512 + 512 * 128 + 128


@pytest.mark.parametrize(("n", "temperature"), [(2, 0.5), (3, 0.1), (8, 0.5), (5, 1.0)])  # n = 1: refused
def test_nt_xent_matches_double_loop_reference(n, temperature):
    generator = torch.Generator().manual_seed(n)
    z1 = torch.randn(n, 6, generator=generator)
    z2 = torch.randn(n, 6, generator=generator)
    got = nt_xent_loss(z1, z2, temperature=temperature).double().numpy()
    np.testing.assert_allclose(got, numpy_nt_xent(z1.numpy(), z2.numpy(), temperature), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("n", [2, 4, 16])
def test_nt_xent_collapsed_embeddings_closed_form(n):
    z = torch.ones(n, 4)
    torch.testing.assert_close(nt_xent_loss(z, 3 * z), torch.full((n,), math.log(2 * n - 1)))


GATHER_WORKER = """
import datetime, sys, torch, torch.distributed as dist
from sar_zero123.encoder import nt_xent_loss
dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=60))
rank = dist.get_rank()
generator = torch.Generator().manual_seed(0)
z1, z2 = torch.randn(6, 5, generator=generator), torch.randn(6, 5, generator=generator)
local1 = z1[3 * rank : 3 * rank + 3].clone().requires_grad_(True)
local2 = z2[3 * rank : 3 * rank + 3].clone().requires_grad_(True)
loss = nt_xent_loss(local1, local2, temperature=0.5, gather_distributed=True)
loss.mean().backward()
try:
    nt_xent_loss(torch.ones(rank + 1, 5), torch.ones(rank + 1, 5), gather_distributed=True)
    unequal = "accepted"
except ValueError as error:
    unequal = str(error)
torch.save({"loss": loss.detach(), "grad1": local1.grad, "grad2": local2.grad, "unequal": unequal},
           f"{sys.argv[1]}/rank{rank}.pt")
dist.destroy_process_group()
"""


@pytest.mark.slow
def test_nt_xent_gathered_over_two_processes_equals_one_process_on_the_global_batch(
    run_two_process, rendezvous_port: int, tmp_path: Path
) -> None:
    worker = tmp_path / "gather_worker.py"
    worker.write_text(GATHER_WORKER)
    command = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr", "127.0.0.1",
        "--master_port", str(rendezvous_port), str(worker), str(tmp_path),
    ]  # fmt: skip
    run_two_process(command, marker=str(worker), timeout=120)
    generator = torch.Generator().manual_seed(0)
    z1 = torch.randn(6, 5, generator=generator).requires_grad_(True)
    z2 = torch.randn(6, 5, generator=generator).requires_grad_(True)
    reference = nt_xent_loss(z1, z2, temperature=0.5)
    reference.mean().backward()
    ranks = [torch.load(tmp_path / f"rank{rank}.pt") for rank in (0, 1)]
    torch.testing.assert_close(torch.cat([r["loss"] for r in ranks]), reference.detach())
    # each rank's gradient is world_size x its slice of the global one, so DDP's average over ranks
    # gives the parameters the single-process gradient
    torch.testing.assert_close(torch.cat([r["grad1"] for r in ranks]), 2 * z1.grad)
    torch.testing.assert_close(torch.cat([r["grad2"] for r in ranks]), 2 * z2.grad)
    assert all("equal pairs on every process, got [1, 2]" in r["unequal"] for r in ranks)
    # the local loss (no gather) differs: it sees 2 x 3 - 1 = 5 candidates per anchor, not 11
    local = nt_xent_loss(z1[:3].detach(), z2[:3].detach(), temperature=0.5)
    assert not torch.allclose(local, reference[:3].detach())


def test_nt_xent_gather_without_process_group_is_the_local_loss() -> None:
    z1, z2 = torch.randn(4, 8), torch.randn(4, 8)
    torch.testing.assert_close(
        nt_xent_loss(z1, z2, gather_distributed=True), nt_xent_loss(z1, z2), rtol=0, atol=0
    )


def test_nt_xent_bad_input():
    with pytest.raises(ValueError, match="temperature"):
        nt_xent_loss(torch.ones(2, 3), torch.ones(2, 3), temperature=0.0)
    with pytest.raises(ValueError, match="z1 and z2"):
        nt_xent_loss(torch.ones(2, 3), torch.ones(3, 3))
    with pytest.raises(ValueError, match="at least 2 pairs .* got 1"):  # batch 1 would give loss 0
        nt_xent_loss(torch.randn(1, 3), torch.randn(1, 3))
