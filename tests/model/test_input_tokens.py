"""Input tokens: the input's latent, place by place, reachable from every cross-attention."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import PoseProjection, embed_pose
from sar_zero123.model.input_tokens import (
    attending_to_input_tokens,
    enable_input_tokens,
    input_token_context,
    input_token_features,
    token_feature_dim,
    token_layers,
    uses_input_tokens,
)
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.reference_attention import enable_reference_attention
from sar_zero123.model.spatial_pose import rotate_condition_latents
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import ImageEmbedder, compute_losses

KWARGS = {"num_inference_steps": 3, "guidance_scale": 3.0, "output_type": "np"}


def _tokens_pipe(gate: float | None = None) -> SARZero123Pipeline:
    pipe = build_sar_zero123("tiny", seed=0)
    enable_input_tokens(pipe.unet, pipe.pose_projection, pipe.vae.config.latent_channels)
    if gate is not None:
        with torch.no_grad():
            pipe.pose_projection.token_gates.fill_(gate)
    return pipe


def _image(pipe: SARZero123Pipeline, batch: int = 2) -> torch.Tensor:
    size = pipe.default_image_size
    return torch.rand(batch, 1, size, size, generator=torch.Generator().manual_seed(3))


def test_a_model_given_input_tokens_computes_what_it_did_until_trained() -> None:
    pipe = build_sar_zero123("tiny", seed=0)
    image = _image(pipe)
    before = pipe(image, [40.0, -120.0], generator=torch.Generator().manual_seed(0), **KWARGS).images
    enable_input_tokens(pipe.unet, pipe.pose_projection, pipe.vae.config.latent_channels)
    layers = token_layers(pipe.unet)
    assert uses_input_tokens(pipe.pose_projection) and len(layers) >= 2
    assert pipe.pose_projection.config.input_token_layers == len(layers)
    assert pipe.pose_projection.token_gates.shape == (len(layers),)
    after = pipe(image, [40.0, -120.0], generator=torch.Generator().manual_seed(0), **KWARGS).images
    np.testing.assert_array_equal(after, before)  # every gate zero: the same bytes
    with torch.no_grad():
        pipe.pose_projection.token_gates.fill_(0.7)
    opened = pipe(image, [40.0, -120.0], generator=torch.Generator().manual_seed(0), **KWARGS).images
    assert np.abs(opened - before).max() > 1e-3
    with pytest.raises(ValueError, match="already has input tokens"):
        enable_input_tokens(pipe.unet, pipe.pose_projection, 4)


def test_token_features_carry_each_place_where_the_turn_puts_it() -> None:
    latents = torch.arange(2 * 3 * 4 * 4, dtype=torch.float32).reshape(2, 3, 4, 4)
    pose = embed_pose([90.0, 0.0], 0.0)
    features = input_token_features(latents, pose, rotation_sign=1)
    assert features.shape == (2, 16, token_feature_dim(3)) == (2, 16, 3 + 32 + 4)
    torch.testing.assert_close(features[:, :, :3], latents.flatten(2).transpose(1, 2))
    torch.testing.assert_close(features[:, :, -4:], pose.expand(-1, 16, -1))
    # place (row 0, col 3): centre x = 0.75, y = -0.75; turned by +90 deg it lands at (y, -x) = (-0.75, -0.75)
    place = 3
    x, y = 0.75, -0.75
    own = features[0, place, 3:19]
    landed = features[0, place, 19:35]
    unturned = features[1, place, 19:35]
    expected_own = [math.sin(math.pi * 2**k * c) for c in (x, y) for k in range(4)]
    expected_own += [math.cos(math.pi * 2**k * c) for c in (x, y) for k in range(4)]
    expected_landed = [math.sin(math.pi * 2**k * c) for c in (y, -x) for k in range(4)]
    expected_landed += [math.cos(math.pi * 2**k * c) for c in (y, -x) for k in range(4)]
    torch.testing.assert_close(own, torch.tensor(expected_own), atol=1e-5, rtol=0)
    torch.testing.assert_close(landed, torch.tensor(expected_landed), atol=1e-5, rtol=0)
    torch.testing.assert_close(unturned, own)  # d_az = 0: it lands where it was


def test_the_landed_place_is_where_the_turned_latent_shows_it() -> None:
    """A single lit place, turned by ``rotate_condition_latents``, peaks where its token says it lands."""
    latents = torch.zeros(1, 1, 8, 8)
    latents[0, 0, 1, 6] = 1.0
    pose = embed_pose(90.0, 0.0)
    for sign in (1, -1):
        turned = rotate_condition_latents(latents, pose, sign)
        peak = int(turned.flatten().argmax())
        row, col = divmod(peak, 8)
        features = input_token_features(latents, pose, sign)
        own = features[0, :, 1:17]  # one latent channel, then the place's own position
        landed = features[0, 1 * 8 + 6, 17:33]
        match = int((own - landed).abs().sum(-1).argmin())  # the place whose own position is the landing
        assert divmod(match, 8) == (row, col)


def test_each_cross_attention_adds_its_gated_attention_to_the_tokens() -> None:
    """The processor against ``own + tanh(g) * W_o softmax(Q K_tok^T / sqrt(d)) V_tok`` computed directly."""
    pipe = _tokens_pipe(gate=0.4)
    unet = pipe.unet
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(2, unet.config.in_channels, 8, 8, generator=generator)
    context = torch.randn(2, 1, unet.config.cross_attention_dim, generator=generator)
    tokens = torch.randn(2, 5, unet.config.cross_attention_dim, generator=generator)
    weights = torch.tanh(pipe.pose_projection.token_gates.detach())[None].repeat(2, 1)
    weights[1] = 0.0
    layer = token_layers(unet)[0]
    seen = {}

    def record(module, args, kwargs, output):
        seen["input"], seen["output"] = args[0] if args else kwargs["hidden_states"], output

    handle = layer.register_forward_hook(record, with_kwargs=True)
    with torch.no_grad(), attending_to_input_tokens(unet, tokens, weights):
        unet(x, torch.tensor([10, 700]), encoder_hidden_states=context)
    handle.remove()
    hidden, heads = seen["input"].double(), layer.heads
    with torch.no_grad():
        q = layer.to_q(seen["input"]).double()
        k, v = layer.to_k(tokens).double(), layer.to_v(tokens).double()
        v_own = layer.to_v(context).double()
    out_weight = layer.to_out[0].weight.detach().double()
    dim = q.shape[-1] // heads
    expected = torch.zeros(2, hidden.shape[1], out_weight.shape[0], dtype=torch.float64)
    own = torch.zeros_like(expected)
    for n in range(2):
        for head in range(heads):
            cols = slice(head * dim, (head + 1) * dim)
            mixed = torch.softmax(q[n, :, cols] @ k[n, :, cols].T / math.sqrt(dim), -1) @ v[n, :, cols]
            expected[n] += mixed @ out_weight[:, cols].T
            own[n] += (
                v_own[n, :, cols].expand(hidden.shape[1], -1) @ out_weight[:, cols].T
            )  # one key: weight 1
    own = own + layer.to_out[0].bias.detach().double()
    torch.testing.assert_close(
        seen["output"][0].double(), own[0] + math.tanh(0.4) * expected[0], atol=1e-5, rtol=0
    )
    torch.testing.assert_close(seen["output"][1].double(), own[1], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="weights"):
        with attending_to_input_tokens(unet, tokens, weights[:, :1]):
            pass


def test_a_zero_condition_latent_sees_no_tokens_and_the_unet_is_itself_outside() -> None:
    pipe = _tokens_pipe(gate=0.7)
    unet = pipe.unet
    generator = torch.Generator().manual_seed(1)
    latents = torch.randn(2, 4, 8, 8, generator=generator)
    latents[0] = 0.0  # the classifier-free-guidance null
    pose = embed_pose([30.0, 60.0], 0.0)
    x = torch.randn(2, unet.config.in_channels, 8, 8, generator=generator)
    context = torch.randn(2, 1, unet.config.cross_attention_dim, generator=generator)
    t = torch.tensor([5, 500])
    with torch.no_grad():
        plain = unet(x, t, encoder_hidden_states=context).sample
        with input_token_context(unet, pipe.pose_projection, latents, pose):
            mixed = unet(x, t, encoder_hidden_states=context).sample
        after = unet(x, t, encoder_hidden_states=context).sample
    torch.testing.assert_close(mixed[0], plain[0], rtol=0, atol=0)
    assert float((mixed[1] - plain[1]).abs().max()) > 1e-4
    torch.testing.assert_close(after, plain, rtol=0, atol=0)


def test_a_tokens_pipeline_saves_loads_and_refuses_a_mismatch(tmp_path: Path) -> None:
    pipe = _tokens_pipe(gate=0.3)
    enable_reference_attention(pipe.unet, pipe.pose_projection)  # the two combine
    image = _image(pipe, 1)
    views = pipe(image, 90.0, generator=torch.Generator().manual_seed(0), **KWARGS).images
    pipe.save_pretrained(tmp_path / "pipe")
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "pipe")
    assert uses_input_tokens(loaded.pose_projection)
    torch.testing.assert_close(
        loaded.pose_projection.token_projection.weight, pipe.pose_projection.token_projection.weight
    )
    again = loaded(image, 90.0, generator=torch.Generator().manual_seed(0), **KWARGS).images
    np.testing.assert_allclose(again, views, rtol=0, atol=1e-6)
    wrong = PoseProjection(**{**dict(pipe.pose_projection.config), "input_token_layers": 1})
    with pytest.raises(ValueError, match="input_token_layers=1 gates, but the UNet has"):
        SARZero123Pipeline(**{**pipe.components, "pose_projection": wrong})
    with pytest.raises(ValueError, match="input_token_channels"):
        PoseProjection(input_token_layers=2)
    with pytest.raises(ValueError, match="input_token_layers"):
        PoseProjection(input_token_layers=-1, input_token_channels=4)


def test_a_training_step_trains_the_gates_and_drops_the_tokens_with_the_latent() -> None:
    pipe = _tokens_pipe()
    size = pipe.default_image_size
    generator = torch.Generator().manual_seed(0)
    batch = {"input": torch.rand(3, 1, size, size, generator=generator),
             "target": torch.rand(3, 1, size, size, generator=generator),
             "d_az_deg": torch.tensor([30.0, 90.0, -150.0]), "d_el_deg": torch.zeros(3)}  # fmt: skip
    common = {"unet": pipe.unet, "pose_projection": pipe.pose_projection, "vae": pipe.vae,
              "image_encoder": ImageEmbedder(pipe.image_encoder), "encoder": None,
              "noise_scheduler": pipe.scheduler}  # fmt: skip
    losses = compute_losses(batch, **common, generator=torch.Generator().manual_seed(0), apply_dropout=False)
    losses.loss.mean().backward()
    grad = pipe.pose_projection.token_gates.grad
    assert grad is not None and float(grad.abs().min()) > 0
    assert pipe.pose_projection.token_projection.weight.grad is not None
    pipe.pose_projection.token_gates.grad = None
    only_latent = LossSettings(pfm_weight=0.0, drop_image_prob=0.0, drop_both_prob=0.0, drop_latent_prob=1.0)
    dropped = compute_losses(
        batch, **common, generator=torch.Generator().manual_seed(0), loss_settings=only_latent
    )
    dropped.loss.mean().backward()
    assert float(pipe.pose_projection.token_gates.grad.abs().max()) == 0.0
