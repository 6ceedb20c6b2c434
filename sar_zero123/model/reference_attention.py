"""Reference attention: every self-attention of the UNet also attends to the input view's own features.

A zero-1-to-3 UNet reaches the input's appearance only through the condition latents at the input's own
pose, carried by convolutions. Reference attention (Zero123++'s mechanism in IP-Adapter's decoupled, gated
form) makes it reachable from every place, by content:

1. a **reference pass** runs the UNet on the input asked for itself (``d_az = d_el = 0``, the clean input
   latent at timestep 0), once per call, and keeps each self-attention's input (:func:`reference_features`);
2. in the **target pass** each self-attention adds ``tanh(g_l) * Attn(Q, K_ref, V_ref)`` through its own
   projections (:func:`attending_to_reference`). The gates ``reference_gates`` start at zero, so a warm
   start computes exactly what the model did without them.

The classifier-free-guidance null gets weight 0, as in Zero123++.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import torch
import torch.nn.functional as F
from diffusers.models.attention_processor import Attention, AttnProcessor2_0

from sar_zero123.model.spatial_pose import unet_condition_latents

__all__ = [
    "GatedAttnProcessor",
    "attend_extra",
    "attending_to_reference",
    "check_gate_count",
    "check_reference_layers",
    "enable_reference_attention",
    "gate_count",
    "input_reference",
    "own_pose",
    "reference_features",
    "reference_layers",
    "reference_weights",
    "shared_state",
    "transformer_attentions",
    "uses_reference",
]


class _ReferenceState:
    """What the processors of one UNet share: the mode and, while reading, the kept features and weights."""

    def __init__(self, layers: int) -> None:
        self.mode = "off"  # "off" | "write" | "read"
        self.features: list[torch.Tensor | None] = [None] * layers
        self.rows: torch.Tensor | None = None
        self.weights: torch.Tensor | None = None  # (N, layers)


class GatedAttnProcessor:
    """Diffusers' own attention plus ``weight * Attn(Q, K(context), V(context))`` for the
    ``(weight, context)`` that :meth:`extra` gives.
    """

    def __init__(self, layer: int) -> None:
        self.layer = layer
        self.base = AttnProcessor2_0()

    def extra(self, hidden_states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(weight (N, 1, 1), context (N, L', C))`` to attend to, or ``None``."""
        raise NotImplementedError

    def __call__(
        self,
        attn: Attention,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        attention_mask: torch.Tensor | None = None,
        temb: torch.Tensor | None = None,
        **kwargs,
    ) -> torch.Tensor:
        output = self.base(attn, hidden_states, encoder_hidden_states, attention_mask, temb, **kwargs)
        extra = self.extra(hidden_states)
        if extra is not None:
            weight, context = extra
            mixed = attend_extra(attn, hidden_states, context)
            output = output + weight.to(output.dtype) * mixed / attn.rescale_output_factor
        return output


class ReferenceAttnProcessor(GatedAttnProcessor):
    """A self-attention's processor: writing, it keeps its input; reading, it also attends to that layer's
    reference features.
    """

    def __init__(self, layer: int, state: _ReferenceState) -> None:
        super().__init__(layer)
        self.state = state

    def extra(self, hidden_states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        state = self.state
        if state.mode == "write":
            state.features[self.layer] = hidden_states
        elif state.mode == "read":
            reference = state.features[self.layer].index_select(0, state.rows)  # (N, L_ref, C)
            return state.weights[:, self.layer][:, None, None], reference  # (N, 1, 1)
        return None


def attend_extra(attn: Attention, hidden_states: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """``Attn(Q(hidden_states), K(reference), V(reference))`` through the layer's projections, the output
    projection without its bias (the layer's own attention adds it once).

    Shape:
        ``(N, L, C)``, ``(N, L_ref, C)`` -> ``(N, L, C)``.
    """
    batch, _, _ = hidden_states.shape
    heads = attn.heads
    query = attn.to_q(hidden_states)
    key, value = attn.to_k(reference), attn.to_v(reference)
    head_dim = key.shape[-1] // heads
    query, key, value = (x.view(batch, -1, heads, head_dim).transpose(1, 2) for x in (query, key, value))
    if attn.norm_q is not None:
        query = attn.norm_q(query)
    if attn.norm_k is not None:
        key = attn.norm_k(key)
    mixed = F.scaled_dot_product_attention(query, key, value)  # (N, heads, L, head_dim)
    mixed = mixed.transpose(1, 2).reshape(batch, -1, heads * head_dim).to(query.dtype)
    return attn.to_out[1](F.linear(mixed, attn.to_out[0].weight))


def transformer_attentions(unet: torch.nn.Module, name: str, purpose: str) -> list[Attention]:
    """The UNet's transformer-block attentions named ``name`` (``"attn1"``: self, ``"attn2"``: cross), in
    module order.

    Raises:
        ValueError: If one is not a transformer block's (``purpose`` names what needs them).
    """
    unet = getattr(unet, "module", unet)
    layers = [m for key, m in unet.named_modules() if key.endswith(name) and isinstance(m, Attention)]
    for layer in layers:
        if layer.residual_connection or layer.spatial_norm is not None or layer.group_norm is not None:
            raise ValueError(f"unet: {purpose} needs transformer-block attentions")
    return layers


def reference_layers(unet: torch.nn.Module) -> list[Attention]:
    """The UNet's self-attentions (each transformer block's ``attn1``), in module order."""
    return transformer_attentions(unet, "attn1", "reference attention")


def shared_state(
    unet: torch.nn.Module,
    attribute: str,
    layers: Callable[[torch.nn.Module], list[Attention]],
    make_state: Callable[[int], Any],
    processor: Callable[[int, Any], GatedAttnProcessor],
) -> Any:
    """The state a (possibly DDP-wrapped) UNet's ``layers`` share, kept as its ``attribute``: on first use
    ``make_state(count)``, and each layer's ``processor(index, state)`` installed (idempotent)."""
    unet = getattr(unet, "module", unet)
    state = getattr(unet, attribute, None)
    if state is None:
        found = layers(unet)
        state = make_state(len(found))
        for index, layer in enumerate(found):
            layer.set_processor(processor(index, state))
        setattr(unet, attribute, state)
    return state


def _state(unet: torch.nn.Module) -> _ReferenceState:
    return shared_state(unet, "_reference_state", reference_layers, _ReferenceState, ReferenceAttnProcessor)


def gate_count(pose_projection: torch.nn.Module, field: str) -> int:
    """How many gated layers a (possibly DDP-wrapped) pose projection records in its config ``field``."""
    config = getattr(pose_projection, "module", pose_projection).config
    return int(getattr(config, field, 0) or 0)


def check_gate_count(
    unet: torch.nn.Module,
    pose_projection: torch.nn.Module,
    field: str,
    layers: Callable[[torch.nn.Module], list[Attention]],
    kind: str,
) -> None:
    """Refuse a pose projection whose gates (``field``) do not match the UNet's ``layers`` (``kind``).

    Raises:
        ValueError: Naming both counts.
    """
    recorded = gate_count(pose_projection, field)
    if recorded <= 0:
        return
    count = len(layers(unet))
    if recorded != count:
        raise ValueError(f"pose_projection: {field}={recorded} gates, but the UNet has {count} {kind}")


def uses_reference(pose_projection: torch.nn.Module) -> bool:
    """Whether a (possibly DDP-wrapped) pose projection records reference attention."""
    return gate_count(pose_projection, "reference_layers") > 0


def enable_reference_attention(unet: torch.nn.Module, pose_projection: torch.nn.Module) -> None:
    """Give a model reference attention in place, computing exactly what it did (every gate zero).

    Raises:
        ValueError: If the model already has it.
    """
    if uses_reference(pose_projection):
        raise ValueError("pose_projection: this model already has reference attention (reference_layers > 0)")
    count = len(reference_layers(unet))
    weight = pose_projection.projection.weight
    pose_projection.reference_gates = torch.nn.Parameter(
        torch.zeros(count, dtype=weight.dtype, device=weight.device)
    )
    pose_projection.register_to_config(reference_layers=count)


def check_reference_layers(unet: torch.nn.Module, pose_projection: torch.nn.Module) -> None:
    """Refuse a pose projection whose gates do not match the UNet's self-attentions."""
    check_gate_count(unet, pose_projection, "reference_layers", reference_layers, "self-attentions")


@torch.no_grad()
def reference_features(unet: torch.nn.Module, model_input: torch.Tensor, **unet_kwargs) -> list[torch.Tensor]:
    """The reference pass: the input of every self-attention while the UNet runs on ``model_input``.

    Args:
        model_input: ``[the input's scaled latent, its condition latents at its own pose]``.
        **unet_kwargs: ``timestep``, ``encoder_hidden_states``, ``class_labels``.

    Returns:
        One ``(B, L_l, C_l)`` tensor per self-attention (:func:`reference_layers`).
    """
    state = _state(unet)
    state.mode = "write"
    try:
        unet(model_input, **unet_kwargs)
        return list(state.features)
    finally:
        state.mode = "off"
        state.features = [None] * len(state.features)


def reference_weights(pose_projection: torch.nn.Module, keep: torch.Tensor) -> torch.Tensor:
    """Each row's weight of each layer's reference attention: ``tanh(g_l)`` where ``keep``, else 0.

    Shape:
        ``keep`` ``(N,)`` bool -> ``(N, layers)``.
    """
    gates = getattr(pose_projection, "module", pose_projection).reference_gates
    return torch.tanh(gates)[None, :] * keep.to(gates.device, gates.dtype)[:, None]


@contextlib.contextmanager
def attending_to_reference(
    unet: torch.nn.Module, features: list[torch.Tensor], rows: torch.Tensor, weights: torch.Tensor
) -> Iterator[None]:
    """Within the block, the UNet's self-attentions also attend to ``features``.

    Args:
        features: From :func:`reference_features`, ``B_ref`` rows.
        rows: ``(N,)`` the reference row of each row of the UNet's batch.
        weights: ``(N, layers)`` from :func:`reference_weights`.

    Raises:
        ValueError: If the counts or shapes disagree.
    """
    state = _state(unet)
    if len(features) != len(state.features) or weights.shape != (rows.shape[0], len(state.features)):
        raise ValueError(
            f"reference: expected {len(state.features)} layers' features and weights (N, "
            f"{len(state.features)}), got {len(features)} and {tuple(weights.shape)}"
        )
    state.mode, state.features, state.rows, state.weights = "read", list(features), rows, weights
    try:
        yield
    finally:
        state.mode, state.rows, state.weights = "off", None, None
        state.features = [None] * len(state.features)


def own_pose(pose: torch.Tensor) -> torch.Tensor:
    """The pose of a view asked for itself: ``d_az = d_el = 0``, the fourth entry (the input's depression,
    where the model takes it) kept.

    Shape:
        ``(B, 1, 4)`` -> ``(B, 1, 4)``.
    """
    own = pose.clone()
    own[..., 0], own[..., 1], own[..., 2] = 0.0, 0.0, 1.0
    return own


def input_reference(
    unet: torch.nn.Module,
    pose_projection: torch.nn.Module,
    condition_latents: torch.Tensor,
    own: torch.Tensor,
    tokens: torch.Tensor,
    class_labels: torch.Tensor | None,
    scaling_factor: float,
    proxy_at_input: torch.Tensor | None = None,
) -> list[torch.Tensor]:
    """The reference pass (module docstring, step 1): the UNet on each input view asked for itself.

    Args:
        condition_latents: The inputs' unscaled latents (never the guidance null).
        own: :func:`own_pose` of the request's pose.
        tokens: ``pose_projection(image_embeds, own)``.
        class_labels: The UNet's class labels at the own pose, or ``None``.
        scaling_factor: The VAE's: the clean input latent is scaled as a target latent, at timestep 0.
        proxy_at_input: A ``spatial_pose="proxy"`` UNet's proxy latent at the input's pose, also its
            request's proxy.

    Shape:
        ``(B, C, h, w)``, ``(B, 1, 4)``, ``(B, 1, D)`` -> a list of ``(B, L_l, C_l)``.
    """
    proxy = None if proxy_at_input is None else torch.cat([proxy_at_input, proxy_at_input], dim=1)
    condition = unet_condition_latents(condition_latents, own, pose_projection, proxy)
    sample = condition_latents * scaling_factor
    timestep = torch.zeros(condition_latents.shape[0], dtype=torch.long, device=condition_latents.device)
    return reference_features(
        unet, torch.cat([sample, condition], dim=1), timestep=timestep, encoder_hidden_states=tokens,
        class_labels=class_labels,
    )  # fmt: skip
