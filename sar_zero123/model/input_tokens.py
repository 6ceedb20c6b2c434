"""Input tokens: every cross-attention of the UNet also attends to the input view's latent, place by place.

A zero-1-to-3 UNet cross-attends to one token, adding the same vector at every place. Input tokens
(IP-Adapter Plus's spatial tokens, decoupled and gated) give each place ``p`` of the input's latent a token

    ``token_projection([latent(p), fourier(p), fourier(R(-a) p), pose])``

where ``R(-a) p`` is where ``p`` lands when the vehicle turns by ``a = rotation_sign * d_az`` and
``fourier`` the sines and cosines at :data:`TOKEN_FREQUENCIES` octaves. Each cross-attention adds
``tanh(g_l) * Attn(Q, K(tokens), V(tokens))``; the gates ``token_gates`` start at zero, so a warm start
computes exactly what the model did. No extra UNet pass, unlike reference attention, with which it
combines. Rows whose condition latent is zero (the guidance null, a dropped condition) get weight 0.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch
from diffusers.models.attention_processor import Attention

from sar_zero123.model.conditioning import TOKEN_FREQUENCIES, token_feature_dim
from sar_zero123.model.reference_attention import (
    GatedAttnProcessor,
    check_gate_count,
    gate_count,
    shared_state,
    transformer_attentions,
)
from sar_zero123.model.spatial_pose import check_turn_inputs

__all__ = [
    "TOKEN_FREQUENCIES",
    "attending_to_input_tokens",
    "check_token_layers",
    "enable_input_tokens",
    "input_token_context",
    "input_token_features",
    "token_feature_dim",
    "token_layers",
    "uses_input_tokens",
]


def _fourier(positions: torch.Tensor) -> torch.Tensor:
    """``[sin(pi 2^k x), cos(pi 2^k x)]`` over the last axis' coordinates. ``(..., 2) -> (..., 4F)``."""
    scales = math.pi * 2.0 ** torch.arange(TOKEN_FREQUENCIES, dtype=positions.dtype, device=positions.device)
    angles = (positions[..., None] * scales).flatten(-2)  # (..., 2F)
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


def input_token_features(latents: torch.Tensor, pose: torch.Tensor, rotation_sign: int) -> torch.Tensor:
    """Each latent place's token features (module docstring), before the projection.

    Positions are place centres in ``(-1, 1)`` (x right, y down, ``F.affine_grid``'s convention); ``p``
    lands at ``(cos a x + sin a y, -sin a x + cos a y)``, the inverse of
    :func:`~sar_zero123.model.spatial_pose.rotate_condition_latents`'s sampling map.

    Shape:
        ``(B, C, h, w)``, ``(B, 1, 4)`` -> ``(B, h * w, token_feature_dim(C))``, places in row-major order.

    Raises:
        ValueError: If the shapes do not match or ``rotation_sign`` is not +-1.
    """
    check_turn_inputs(latents, pose, rotation_sign)
    batch, channels, height, width = latents.shape
    dtype, device = torch.float32, latents.device
    ys = (torch.arange(height, dtype=dtype, device=device) + 0.5) * (2.0 / height) - 1.0
    xs = (torch.arange(width, dtype=dtype, device=device) + 0.5) * (2.0 / width) - 1.0
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    places = torch.stack([x.flatten(), y.flatten()], dim=-1)  # (L, 2)
    pose = pose.to(device=device, dtype=dtype)
    sin, cos = rotation_sign * pose[:, 0, 1, None], pose[:, 0, 2, None]  # (B, 1)
    landed = torch.stack(
        [cos * places[:, 0] + sin * places[:, 1], -sin * places[:, 0] + cos * places[:, 1]], dim=-1
    )  # (B, L, 2)
    content = latents.to(dtype).flatten(2).transpose(1, 2)  # (B, L, C)
    return torch.cat(
        [
            content,
            _fourier(places).expand(batch, -1, -1),
            _fourier(landed),
            pose.expand(-1, height * width, -1),
        ],
        dim=-1,
    )


class _TokenState:
    """What the processors of one UNet share: while reading, the tokens and each row's weights."""

    def __init__(self, layers: int) -> None:
        self.layers = layers
        self.tokens: torch.Tensor | None = None  # (N, L, D)
        self.weights: torch.Tensor | None = None  # (N, layers)


class InputTokenAttnProcessor(GatedAttnProcessor):
    """A cross-attention's processor: while reading, it also attends to the input tokens."""

    def __init__(self, layer: int, state: _TokenState) -> None:
        super().__init__(layer)
        self.state = state

    def extra(self, hidden_states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        state = self.state
        if state.tokens is None:
            return None
        return state.weights[:, self.layer][:, None, None], state.tokens.to(hidden_states.dtype)  # (N, 1, 1)


def token_layers(unet: torch.nn.Module) -> list[Attention]:
    """The UNet's cross-attentions (each transformer block's ``attn2``), in module order."""
    return transformer_attentions(unet, "attn2", "input tokens")


def _state(unet: torch.nn.Module) -> _TokenState:
    return shared_state(unet, "_input_token_state", token_layers, _TokenState, InputTokenAttnProcessor)


def uses_input_tokens(pose_projection: torch.nn.Module) -> bool:
    """Whether a (possibly DDP-wrapped) pose projection records input tokens."""
    return gate_count(pose_projection, "input_token_layers") > 0


def enable_input_tokens(
    unet: torch.nn.Module, pose_projection: torch.nn.Module, latent_channels: int
) -> None:
    """Give a model input tokens in place, computing exactly what it did (every gate zero; the token
    projection keeps ``torch.nn.Linear``'s default draw).

    Raises:
        ValueError: If the model already has them, or ``latent_channels < 1``.
    """
    if uses_input_tokens(pose_projection):
        raise ValueError("pose_projection: this model already has input tokens (input_token_layers > 0)")
    if isinstance(latent_channels, bool) or int(latent_channels) != latent_channels or latent_channels < 1:
        raise ValueError(f"`latent_channels` must be a positive integer, got {latent_channels!r}")
    count = len(token_layers(unet))
    weight = pose_projection.projection.weight
    pose_projection.add_input_tokens(count, int(latent_channels))
    pose_projection.to(device=weight.device, dtype=weight.dtype)
    pose_projection.register_to_config(input_token_layers=count, input_token_channels=int(latent_channels))


def check_token_layers(unet: torch.nn.Module, pose_projection: torch.nn.Module) -> None:
    """Refuse a pose projection whose token gates do not match the UNet's cross-attentions."""
    check_gate_count(unet, pose_projection, "input_token_layers", token_layers, "cross-attentions")


@contextlib.contextmanager
def attending_to_input_tokens(
    unet: torch.nn.Module, tokens: torch.Tensor, weights: torch.Tensor
) -> Iterator[None]:
    """Within the block, the UNet's cross-attentions also attend to ``tokens`` ``(N, L, D)``, each row's
    layer weighted by ``weights`` ``(N, layers)``.

    Raises:
        ValueError: If the shapes disagree.
    """
    state = _state(unet)
    if tokens.ndim != 3 or weights.shape != (tokens.shape[0], state.layers):
        raise ValueError(
            f"input tokens: expected tokens (N, L, D) and weights (N, {state.layers}), got "
            f"{tuple(tokens.shape)} and {tuple(weights.shape)}"
        )
    state.tokens, state.weights = tokens, weights
    try:
        yield
    finally:
        state.tokens = state.weights = None


def input_token_context(
    unet: torch.nn.Module,
    pose_projection: torch.nn.Module,
    condition_latents: torch.Tensor,
    pose: torch.Tensor,
) -> contextlib.AbstractContextManager:
    """The context in which the cross-attentions attend to each row's input tokens (a null context for a
    model without them); a zero (dropped) condition latent row gets weight 0.

    Shape:
        ``(N, C, h, w)``, ``(N, 1, 4)``.
    """
    if not uses_input_tokens(pose_projection):
        return contextlib.nullcontext()
    projection = getattr(pose_projection, "module", pose_projection)
    features = input_token_features(condition_latents, pose, projection.config.rotation_sign)
    tokens = projection.token_projection(features.to(projection.token_projection.weight.dtype))  # (N, L, D)
    keep = condition_latents.flatten(1).abs().amax(dim=1) > 0  # (N,)
    gates = torch.tanh(projection.token_gates)
    weights = gates[None, :] * keep.to(gates.device, gates.dtype)[:, None]  # (N, layers)
    return attending_to_input_tokens(unet, tokens.to(condition_latents.dtype), weights)
