"""Conditioning of the SAR zero-1-to-3 model: relative pose, its projection, image embeddings and latents.

The UNet sees the input view as a cross-attention token ``PoseProjection([clip_image_embedding, pose])``
``(B, 1, D)`` and as its unscaled VAE posterior mode concatenated to the noisy latent (``in_channels = 8``).
Parts pretrained on RGB get the single SAR channel replicated; channel counts are read from model configs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from diffusers import AutoencoderKL
from diffusers.configuration_utils import ConfigMixin, register_to_config
from diffusers.models.modeling_utils import ModelMixin
from transformers import CLIPVisionModelWithProjection

from sar_zero123.domain import unit_to_signed

__all__ = [
    "CLIP_IMAGE_MEAN",
    "CLIP_IMAGE_STD",
    "POSE_DIM",
    "PROXY_FORMS",
    "PoseProjection",
    "SPATIAL_POSE_MODES",
    "VAE_SIGNATURE_FIELDS",
    "check_vae_signature",
    "embed_pose",
    "encode_condition_latents",
    "pose_class_labels",
    "encode_image_embeddings",
    "encode_target_latents",
    "match_channels",
    "vae_signature",
]

#: Size of the zero-1-to-3 relative-pose vector ``[d_el_rad, sin d_az, cos d_az, d_radius]``.
POSE_DIM = 4
#: Per-channel statistics CLIP was trained with (OpenAI CLIP preprocessing).
CLIP_IMAGE_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_IMAGE_STD = (0.26862954, 0.26130258, 0.27577711)
#: What the UNet sees of the input besides its latent (``spatial_pose.unet_condition_latents``).
SPATIAL_POSE_MODES = (None, "rotated_input", "proxy")
#: How a ``"proxy"`` model reads its proxy (``spatial_pose.proxy_condition_views``): the simulator render
#: itself, or its geometry alone (shadow, ground and lit masks; no simulator intensities).
PROXY_FORMS = ("render", "geometry")
#: Image-plane turn per degree of azimuth in the built-in simulator's convention (and the prior's).
SIMULATOR_ROTATION_SIGN = -1


def as_angle_tensor(value: float | torch.Tensor | list[float], name: str) -> torch.Tensor:
    """Angles in degrees as a flat float64 tensor, checked at the boundary.

    Args:
        name: The caller's argument name, for the message.

    Shape:
        ``() | (B,) -> (1,) | (B,)``.

    Raises:
        ValueError: Naming ``name``, if the angles are more than 1-D, empty or not finite.
    """
    tensor = torch.as_tensor(value, dtype=torch.float64).cpu()
    if tensor.ndim > 1:
        raise ValueError(
            f"`{name}` must be a scalar or a 1-D sequence of angles, got shape {tuple(tensor.shape)}"
        )
    tensor = tensor.reshape(-1)
    if tensor.numel() == 0:
        raise ValueError(f"`{name}` is empty")
    if not torch.isfinite(tensor).all():
        raise ValueError(f"`{name}` must be finite, got {tensor.tolist()}")
    return tensor


def embed_pose(
    d_az_deg: float | list[float] | torch.Tensor,
    d_el_deg: float | list[float] | torch.Tensor,
    input_depression_deg: float | list[float] | torch.Tensor | None = None,
) -> torch.Tensor:
    """Relative-pose vector of zero-1-to-3, ``[d_el_rad, sin(d_az), cos(d_az), 0]``, or Stable Zero123's
    ``[d_el_rad, sin(d_az), cos(d_az), input_depression_rad]`` when ``input_depression_deg`` is given.

    - ``d_az_deg = target - input azimuth``; only its sine and cosine enter, so ``370 == 10 == -350``.
    - ``d_el_deg = target - input depression``, in radians with its sign unchanged, as the paper's authors
      do (their ``get_T``). In zero-1-to-3's polar convention a depression increase thus reads as a camera
      moving toward the horizon; fine-tuning learns it, and the numbers equal the authors'.
    - The fourth entry (camera-distance delta) is 0: SAR chips are range-normalised. With
      ``input_depression_deg`` it holds the input's absolute depression, since a depression change
      reshapes a chip by an amount that depends on where it starts (shadow length ~ 1 / tan(depression)).

    Returns:
        Float32 pose vectors on the CPU.

    Shape:
        ``(B, 1, 4)`` with ``B = max(len(d_az_deg), len(d_el_deg))``; scalars broadcast.

    Raises:
        ValueError: If an angle is not finite, empty, more than 1-D, or the lengths differ and none is 1.
    """
    d_az = as_angle_tensor(d_az_deg, "d_az_deg")
    d_el = as_angle_tensor(d_el_deg, "d_el_deg")
    if d_az.numel() != d_el.numel() and 1 not in (d_az.numel(), d_el.numel()):
        raise ValueError(
            f"`d_az_deg` ({d_az.numel()} values) and `d_el_deg` ({d_el.numel()} values) must have the same "
            "length or one of them must be a scalar"
        )
    depression = torch.zeros(1, dtype=d_el.dtype)
    if input_depression_deg is not None:
        depression = as_angle_tensor(input_depression_deg, "input_depression_deg")
        lengths = {d_az.numel(), d_el.numel(), depression.numel()} - {1}
        if len(lengths) > 1:
            raise ValueError(
                f"`input_depression_deg` ({depression.numel()} values) must be a scalar or match the "
                f"{max(d_az.numel(), d_el.numel())} pose values"
            )
    d_az, d_el, depression = torch.broadcast_tensors(d_az, d_el, depression)
    # float64 for the trigonometry so that 370 and 10 give bit-identical float32 vectors.
    d_az_rad = torch.deg2rad(torch.remainder(d_az, 360.0))
    d_el_rad = torch.deg2rad(d_el)
    fourth = torch.deg2rad(depression)  # 0 (zero-1-to-3's radius delta) unless a depression was given
    pose = torch.stack([d_el_rad, torch.sin(d_az_rad), torch.cos(d_az_rad), fourth], dim=-1)
    return pose.to(torch.float32).unsqueeze(1)  # (B, 1, 4)


#: The VAE config fields a trained model depends on (:func:`vae_signature`).
VAE_SIGNATURE_FIELDS = ("sample_size", "block_out_channels", "latent_channels", "scaling_factor")


def vae_signature(vae_config: Any) -> dict[str, Any]:
    """The VAE config fields (of an ``AutoencoderKL.config`` or a mapping) a model trained on its latents
    depends on, JSON-ready.
    """
    get = vae_config.get if isinstance(vae_config, dict) else lambda name: getattr(vae_config, name, None)
    signature = {}
    for name in VAE_SIGNATURE_FIELDS:
        value = get(name)
        signature[name] = list(value) if isinstance(value, list | tuple) else value
    return signature


def check_vae_signature(vae_config: Any, trained_vae: dict[str, Any] | None, name: str = "vae") -> None:
    """Refuse a VAE whose :func:`vae_signature` differs from ``trained_vae`` (``None`` accepts any).

    Raises:
        ValueError: Naming every field that differs with both values.
    """
    if trained_vae is None:
        return
    actual = vae_signature(vae_config)
    differences = [
        f"{field} {actual[field]!r} (the model was trained with {trained_vae[field]!r})"
        for field in VAE_SIGNATURE_FIELDS
        if field in trained_vae and actual[field] != trained_vae[field]
    ]
    if differences:
        raise ValueError(
            f"{name}: " + "; ".join(differences) + ": the vae comes from another model than the unet "
            "(pose_projection.config.trained_vae records the one it was trained with)"
        )


class PoseProjection(ModelMixin, ConfigMixin):
    """Linear map of ``[image_embedding, pose]`` to the UNet's cross-attention token (zero-1-to-3's
    ``cc_projection``; weights in ``self.projection``, that folder's layout).

    Initialised as the identity on the image embedding and zero on the pose and the bias, so an untuned
    UNet sees the plain CLIP embedding.

    Args:
        in_features: Image-embedding dimension + 4.
        out_features: The UNet's cross-attention dimension.
        input_depression: The pose's fourth entry is the input's absolute depression (:func:`embed_pose`).
        trained_d_el_deg: ``[min, max]`` of the trained depression changes, or ``None`` (unknown);
            requests outside are refused.
        trained_depression_deg: ``[min, max]`` of the trained absolute depressions, or ``None``.
        spatial_pose: One of :data:`SPATIAL_POSE_MODES`: ``None`` (zero-1-to-3), ``"rotated_input"`` (the
            input latent turned by ``rotation_sign * d_az`` too; ``3 * latent_channels`` UNet inputs) or
            ``"proxy"`` (also the input's simulator proxy at the input's and the requested pose;
            ``5 * latent_channels``).
        rotation_sign: Image-plane turn per degree of ``d_az`` in the data's convention
            (:data:`SIMULATOR_ROTATION_SIGN`).
        trained_vae: The trained VAE's :func:`vae_signature`, or ``None``; another VAE is refused.
        trained_estimator: SHA-256 of the azimuth estimator trained beside the UNet, or ``None``.
        reference_layers: ``n > 0``: each of ``n`` self-attentions also attends to the input's own
            features (:mod:`~sar_zero123.model.reference_attention`), gated by ``reference_gates``.
        input_token_layers: ``n > 0``: each of ``n`` cross-attentions also attends to the input tokens
            (:mod:`~sar_zero123.model.input_tokens`), gated by ``token_gates``.
        input_token_channels: The latent channels the token projection takes.
        proxy_form: One of :data:`PROXY_FORMS`: what a ``"proxy"`` model encodes of each proxy view.

    Raises:
        ValueError: If ``in_features <= 4``, ``out_features < 1``, a range is not ``[min, max]``,
            ``spatial_pose`` or ``proxy_form`` is unknown or ``rotation_sign`` not +-1.
    """

    @register_to_config
    def __init__(
        self,
        in_features: int = 772,
        out_features: int = 768,
        input_depression: bool = False,
        trained_d_el_deg: list[float] | None = None,
        trained_depression_deg: list[float] | None = None,
        spatial_pose: str | None = None,
        rotation_sign: int = SIMULATOR_ROTATION_SIGN,
        trained_vae: dict[str, Any] | None = None,
        trained_estimator: str | None = None,
        reference_layers: int = 0,
        input_token_layers: int = 0,
        input_token_channels: int = 0,
        proxy_form: str = "render",
    ) -> None:
        super().__init__()
        if proxy_form not in PROXY_FORMS:
            raise ValueError(f"`proxy_form` must be one of {PROXY_FORMS}, got {proxy_form!r}")
        for name, value in (
            ("input_token_layers", input_token_layers),
            ("input_token_channels", input_token_channels),
        ):
            if isinstance(value, bool) or int(value) != value or value < 0:
                raise ValueError(f"`{name}` must be an integer >= 0, got {value!r}")
        if bool(input_token_layers) != bool(input_token_channels):
            raise ValueError(
                "`input_token_layers` and `input_token_channels` must both be 0 or both positive, got "
                f"{input_token_layers} and {input_token_channels}"
            )
        if (
            isinstance(reference_layers, bool)
            or int(reference_layers) != reference_layers
            or reference_layers < 0
        ):
            raise ValueError(f"`reference_layers` must be an integer >= 0, got {reference_layers!r}")
        if spatial_pose not in SPATIAL_POSE_MODES:
            raise ValueError(f"`spatial_pose` must be one of {SPATIAL_POSE_MODES}, got {spatial_pose!r}")
        if rotation_sign not in (-1, 1):
            raise ValueError(f"`rotation_sign` must be +1 or -1, got {rotation_sign!r}")
        for name, value in (
            ("trained_d_el_deg", trained_d_el_deg),
            ("trained_depression_deg", trained_depression_deg),
        ):
            if value is not None and (len(value) != 2 or not float(value[0]) <= float(value[1])):
                raise ValueError(f"`{name}` must be [min, max] in degrees or None, got {value!r}")
        if in_features <= POSE_DIM:
            raise ValueError(f"`in_features` must exceed the pose size {POSE_DIM}, got {in_features}")
        if out_features < 1:
            raise ValueError(f"`out_features` must be positive, got {out_features}")
        self.projection = torch.nn.Linear(in_features, out_features)
        with torch.no_grad():
            self.projection.weight.copy_(torch.eye(out_features, in_features))
            self.projection.weight[:, in_features - POSE_DIM :].zero_()
            self.projection.bias.zero_()
        if reference_layers:
            self.reference_gates = torch.nn.Parameter(torch.zeros(int(reference_layers)))
        if input_token_layers:
            self.add_input_tokens(int(input_token_layers), int(input_token_channels))

    def add_input_tokens(self, layers: int, latent_channels: int) -> None:
        """Create the token projection and ``layers`` zero gates (the caller records the config)."""
        self.token_projection = torch.nn.Linear(token_feature_dim(latent_channels), self.config.out_features)
        self.token_gates = torch.nn.Parameter(torch.zeros(layers))

    @property
    def image_embed_dim(self) -> int:
        """Size of the image embedding this projection expects (``in_features - 4``)."""
        return self.config.in_features - POSE_DIM

    def forward(self, image_embeds: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        """Project the concatenated image embedding and pose.

        Shape:
            ``(B, 1, in_features - 4)``, ``(B, 1, 4)`` -> ``(B, 1, out_features)``.

        Raises:
            ValueError: If the shapes do not match the configured sizes.
        """
        if image_embeds.ndim != 3 or image_embeds.shape[-1] != self.image_embed_dim:
            raise ValueError(
                f"`image_embeds` must have shape (B, 1, {self.image_embed_dim}), "
                f"got {tuple(image_embeds.shape)}"
            )
        if pose.shape != (*image_embeds.shape[:2], POSE_DIM):
            raise ValueError(
                f"`pose` must have shape {(*image_embeds.shape[:2], POSE_DIM)}, got {tuple(pose.shape)}"
            )
        features = torch.cat([image_embeds, pose.to(image_embeds)], dim=-1)  # (B, 1, D + 4)
        return self.projection(features.to(self.projection.weight.dtype))


#: Octaves of the Fourier features of an input token's two positions (:mod:`sar_zero123.model.input_tokens`).
TOKEN_FREQUENCIES = 4


def token_feature_dim(latent_channels: int) -> int:
    """Size of one input token's features: the latent, two positions' Fourier features and the pose."""
    return int(latent_channels) + 2 * 4 * TOKEN_FREQUENCIES + POSE_DIM


def match_channels(images: torch.Tensor, channels: int) -> torch.Tensor:
    """Replicate a single-channel batch to ``channels`` (an RGB one to 1 by its mean; a match passes).

    Shape:
        ``(B, 1 | channels, H, W) -> (B, channels, H, W)``.

    Raises:
        ValueError: If the batch is not 4-D or its channel count is neither 1 nor ``channels``.
    """
    if images.ndim != 4:
        raise ValueError(f"`images` must be (B, C, H, W), got shape {tuple(images.shape)}")
    if images.shape[1] == channels:
        return images
    if images.shape[1] == 1:
        return images.expand(-1, channels, -1, -1)
    if channels == 1:
        # An RGB rendering of a SAR chip carries the same magnitude in every channel.
        return images.mean(dim=1, keepdim=True)
    raise ValueError(f"`images` has {images.shape[1]} channels; the model takes {channels}")


def encode_image_embeddings(
    image_encoder: CLIPVisionModelWithProjection,
    images: torch.Tensor,
    image_mean: tuple[float, ...] = CLIP_IMAGE_MEAN,
    image_std: tuple[float, ...] = CLIP_IMAGE_STD,
) -> torch.Tensor:
    """CLIP image embedding of normalised dB chips in [0, 1].

    zero-1-to-3's preprocessing exactly, so an Objaverse checkpoint sees what it was trained with: bicubic
    resize (``align_corners=True``, no antialiasing, no clamping; kornia's resize without its blur) to
    ``config.image_size``, then CLIP mean/std. In torch, so it is batched and differentiable.

    Shape:
        ``(B, 1 | 3, H, W) -> (B, 1, projection_dim)``.
    """
    channels = image_encoder.config.num_channels
    size = image_encoder.config.image_size
    pixels = match_channels(images, channels).to(device=image_encoder.device, dtype=torch.float32)
    if pixels.shape[-2:] != (size, size):
        pixels = F.interpolate(pixels, size=(size, size), mode="bicubic", align_corners=True)
    mean = torch.tensor(image_mean[:channels], device=pixels.device).view(1, -1, 1, 1)
    std = torch.tensor(image_std[:channels], device=pixels.device).view(1, -1, 1, 1)
    pixels = ((pixels - mean) / std).to(image_encoder.dtype)
    return image_encoder(pixel_values=pixels).image_embeds.unsqueeze(1)  # (B, 1, D)


def vae_input(vae: AutoencoderKL, images: torch.Tensor) -> torch.Tensor:
    """Normalised dB chips in [0, 1] as the VAE's input: its channel count, [-1, 1], its device and dtype."""
    pixels = match_channels(images, vae.config.in_channels)
    return unit_to_signed(pixels).to(device=vae.device, dtype=vae.dtype)


def downsampling_factor(block_out_channels: Sequence[int]) -> int:
    """Resolution ratio ``2 ** (n - 1)`` of a diffusers VAE or UNet of ``n`` levels (``vae_scale_factor``)."""
    return 2 ** (len(block_out_channels) - 1)


def encode_condition_latents(vae: AutoencoderKL, images: torch.Tensor) -> torch.Tensor:
    """Unscaled VAE posterior mode of the input view, as zero-1-to-3 concatenates it to the noisy latent.

    Shape:
        ``(B, 1 | 3, H, W) -> (B, latent_channels, H / f, W / f)``, ``f`` the :func:`downsampling_factor`.
    """
    return vae.encode(vae_input(vae, images)).latent_dist.mode()


def encode_target_latents(
    vae: AutoencoderKL,
    images: torch.Tensor,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Scaled posterior sample ``z * scaling_factor`` of the target view, the ``x_0`` the model learns.

    Shape:
        ``(B, 1 | 3, H, W) -> (B, latent_channels, H / f, W / f)``.
    """
    latents = vae.encode(vae_input(vae, images)).latent_dist.sample(generator=generator)
    return latents * vae.config.scaling_factor


def pose_class_labels(
    unet: torch.nn.Module, pose: torch.Tensor, target_features: torch.Tensor | None = None
) -> torch.Tensor | None:
    """The pose as the UNet's ``class_labels`` when it embeds the pose with its timestep, else ``None``.

    Such a UNet (``class_embed_type="projection"``) adds a projection of the pose, then of the
    ``target_features`` (:func:`~sar_zero123.model.orientation.target_view_features`) where it takes
    them, to its timestep embedding. The pose is never dropped for guidance, as in zero-1-to-3.

    Raises:
        ValueError: If ``target_features`` is missing, unexpected, or of the wrong size.

    Shape:
        pose ``(B, 1, 4)``, target_features ``(B, F)`` -> ``(B, 4 + F)`` or ``None``.
    """
    config = getattr(unet, "module", unet).config
    if getattr(config, "class_embed_type", None) != "projection":
        if target_features is not None:
            raise ValueError("target_features given, but the UNet does not embed the pose with its timestep")
        return None
    labels = pose.reshape(pose.shape[0], POSE_DIM)
    extra = config.projection_class_embeddings_input_dim - POSE_DIM
    given = 0 if target_features is None else target_features.shape[-1]
    if given != extra:
        raise ValueError(
            f"the UNet's pose embedding takes {POSE_DIM} pose inputs and {extra} target-view features "
            f"(an AzimuthEstimator's, turned), got {given} target-view features"
        )
    if target_features is None:
        return labels
    return torch.cat([labels, target_features.to(labels.dtype)], dim=-1)
