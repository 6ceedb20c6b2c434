"""LoRA fine-tunes (sar_zero123.training.lora): the layers chosen, the identity at the start, the merge as a
closed form, the refusals."""

from __future__ import annotations

import pytest
import torch

from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.training.finetuning import finetuning_modules, finetuning_optimizer
from sar_zero123.training.lora import add_lora, has_lora, lora_target_modules, merged_unet
from tests.dummies import get_dummy_components


@pytest.fixture
def unet():
    return get_dummy_components()["unet"]


def unet_inputs(unet) -> tuple:
    generator = torch.Generator().manual_seed(0)
    sample = torch.randn(2, unet.config.in_channels, 16, 16, generator=generator)
    hidden = torch.randn(2, 1, unet.config.cross_attention_dim, generator=generator)
    dim = unet.config.projection_class_embeddings_input_dim
    labels = None if dim is None else torch.randn(2, dim, generator=generator)
    return sample, torch.tensor([10, 700]), hidden, labels


def forward(unet, inputs) -> torch.Tensor:
    sample, timesteps, hidden, labels = inputs
    with torch.no_grad():
        return unet(sample, timesteps, hidden, class_labels=labels).sample


def test_target_modules_are_every_linear_and_conv_or_the_attention_projections(unet) -> None:
    every = lora_target_modules(unet, "all")
    layers = [n for n, m in unet.named_modules() if isinstance(m, torch.nn.Linear | torch.nn.Conv2d)]
    assert every == layers
    attention = lora_target_modules(unet, "attention")
    assert attention and all(n.rsplit(".", 1)[-1] in ("to_q", "to_k", "to_v", "0") for n in attention)
    # four projections per attention layer
    assert len(attention) == 4 * sum(type(m).__name__ == "Attention" for m in unet.modules())
    with pytest.raises(ValueError, match="lora_modules must be one of .*got 'mlp'"):
        lora_target_modules(unet, "mlp")


def test_lora_starts_at_the_prior_and_trains_only_its_factors(unet) -> None:
    inputs = unet_inputs(unet)
    before = forward(unet, inputs)
    factors = add_lora(unet, rank=2, modules="attention")
    assert has_lora(unet)
    assert torch.equal(forward(unet, inputs), before)  # B = 0: the prior itself
    trained = [p for p in unet.parameters() if p.requires_grad]
    assert {id(p) for p in trained} == {id(p) for p in factors}
    # an A (rank x in) and a B (out x rank) per target layer
    assert len(factors) == 2 * len(lora_target_modules(get_dummy_components()["unet"], "attention"))
    assert all(2 in p.shape for p in factors)


def test_merged_unet_is_the_closed_form_w_plus_scaled_b_a(unet) -> None:
    base = {k: v.clone() for k, v in unet.state_dict().items()}
    add_lora(unet, rank=2, alpha=6.0, modules="all")
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, parameter in unet.named_parameters():
            if "lora_B" in name:
                parameter.copy_(0.05 * torch.randn(parameter.shape, generator=generator))
    inputs = unet_inputs(unet)
    merged = merged_unet(unet)
    assert not has_lora(merged) and has_lora(unet)  # a copy: the trained UNet keeps its factors
    assert merged.state_dict().keys() == base.keys()
    torch.testing.assert_close(forward(merged, inputs), forward(unet, inputs), rtol=1e-4, atol=1e-5)
    # one Linear by hand: W + (alpha / r) B A
    layer = unet.get_submodule("mid_block.attentions.0.transformer_blocks.0.attn1.to_q")
    a, b = layer.lora_A["default"].weight, layer.lora_B["default"].weight
    expected = base["mid_block.attentions.0.transformer_blocks.0.attn1.to_q.weight"] + 3.0 * b @ a
    torch.testing.assert_close(
        merged.state_dict()["mid_block.attentions.0.transformer_blocks.0.attn1.to_q.weight"], expected
    )
    delta = merged.state_dict()["mid_block.attentions.0.transformer_blocks.0.attn1.to_q.weight"] - base[
        "mid_block.attentions.0.transformer_blocks.0.attn1.to_q.weight"
    ]
    assert torch.linalg.matrix_rank(delta) == 2
    # a UNet without factors is its own merge
    plain = get_dummy_components()["unet"]
    assert merged_unet(plain) is plain


def test_add_lora_refuses_bad_settings_and_a_second_adapter(unet) -> None:
    with pytest.raises(ValueError, match="lora_rank must be >= 1 or None, got 0"):
        add_lora(unet, rank=0)
    with pytest.raises(ValueError, match="lora_alpha must be > 0 or None, got 0"):
        add_lora(unet, rank=2, alpha=0)
    add_lora(unet, rank=2)
    with pytest.raises(ValueError, match="unet: already has LoRA factors"):
        add_lora(unet, rank=2)


def test_a_lora_fine_tune_optimises_its_factors_and_the_whole_pose_projection() -> None:
    pipe = SARZero123Pipeline(**get_dummy_components())
    _, _, unet, pose_projection = finetuning_modules(
        pipe, device="cpu", weight_dtype=torch.float32, lora_rank=2, lora_modules="attention"
    )
    optimizer = finetuning_optimizer(unet, pose_projection, learning_rate=1e-3)
    unet_group, pose_group = optimizer.param_groups
    assert all(p.requires_grad for p in unet_group["params"])
    assert len(unet_group["params"]) == sum(p.requires_grad for p in unet.parameters())
    assert len(unet_group["params"]) < len(list(unet.parameters()))
    assert len(pose_group["params"]) == len(list(pose_projection.parameters()))
    assert pose_group["lr"] == pytest.approx(1e-2)
