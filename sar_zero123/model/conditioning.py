"""Conditioning of the SAR zero-1-to-3 model: relative pose, its projection, image embeddings and latents.

zero-1-to-3 conditions the denoising UNet on the input view in two ways:

1. cross-attention on ``PoseProjection([clip_image_embedding, pose])``, a (B, 1, D) token, and
2. channel concatenation of the VAE posterior mode of the input view (unscaled) to the noisy latent,
   which is why the UNet has ``in_channels = 8``.

SAR chips are single-channel images in the normalised dB domain ([0, 1], see ``docs/ARCHITECTURE.md``).
Parts pretrained on RGB (the CLIP vision tower, the Stable Diffusion VAE) get the channel replicated at
their boundary; a VAE trained on SAR may take one channel, so the channel count is always read from
the model config.
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
#: What the UNet sees of the input view besides its latent: ``None`` (zero-1-to-3: the latent alone) or
#: ``"rotated_input"`` (also the latent turned in the image plane by the requested azimuth change).
SPATIAL_POSE_MODES = (None, "rotated_input", "proxy")
#: Turn of the image plane per degree of azimuth in the built-in simulator's convention (and the prior's):
#: the input's footprint turned by ``-d_az`` lies over the target's
#: (``sar_zero123.model.spatial_pose.rotate_condition_latents``).
SIMULATOR_ROTATION_SIGN = -1


def as_angle_tensor(value: float | torch.Tensor | list[float], name: str) -> torch.Tensor:
    """Angles in degrees as a flat float64 tensor, checked at the boundary.

    Args:
        value: A scalar or a 1-D sequence (list, array, tensor) of angles.
        name: The argument's name in the caller's signature, for the message (``"d_az_deg"``, ``"d_az"``).

    Shape:
        ``() | (B,) -> (1,) | (B,)``.

    Raises:
        ValueError: Naming ``name``, if the angles are more than 1-D, empty or not finite.
    """
    # on the CPU: angles given as tensors on an accelerator (an evaluation's pair batch) meet CPU scalars here
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

    Convention (SAR geometry mapped onto zero-1-to-3's spherical camera):

    - ``d_az_deg = target azimuth - input azimuth`` in degrees. Only its sine and cosine enter the
      vector, so any real value is valid and ``370 == 10 == -350``.
    - ``d_el_deg = target depression - input depression`` in degrees, entered in radians with its sign
      unchanged into the first slot, as the paper's authors do (their ``get_T`` subtracts the chips'
      depression angles). That slot is zero-1-to-3's *polar* delta ``theta_target - theta_cond``, with
      ``theta`` measured down from the +Z axis (``arctan2(sqrt(x^2 + y^2), z)``): a camera that moves up by
      ``e`` has delta ``-e``. A larger depression puts the radar higher above the ground, i.e. it is a
      higher camera, yet it enters with a positive sign: to a pretrained Objaverse checkpoint a depression
      increase reads as a camera moving toward the horizon. Fine-tuning on SAR pairs learns the
      convention; we keep it so that the numbers equal the authors' (tests compare with both formulas).
    - The fourth entry, zero-1-to-3's camera-distance delta, is 0: SAR chips are range-normalised.
      Stable Zero123 puts the input view's absolute elevation there instead; with ``input_depression_deg``
      the input chip's absolute depression (radians) fills it, since a depression change reshapes a chip
      by an amount that depends on where it starts (shadow length ~ 1 / tan(depression)).

    Args:
        d_az_deg: Azimuth delta(s) in degrees: a scalar or one value per sample.
        d_el_deg: Depression delta(s) in degrees: a scalar or one value per sample. Scalars broadcast
            against the other argument.
        input_depression_deg: The input chip's absolute depression(s) in degrees (fourth slot), or
            ``None`` for zero-1-to-3's 0.

    Returns:
        The pose vectors, float32 on the CPU (move them with ``.to``).

    Shape:
        - Output: ``(B, 1, 4)`` with ``B = max(len(d_az_deg), len(d_el_deg))``.

    Raises:
        ValueError: If an angle is not finite, empty, more than 1-D, or the two lengths differ and
            neither is 1.
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
    """The fields of a VAE config (an ``AutoencoderKL.config`` or a mapping) that a model trained on its
    latents depends on, JSON-ready: the chip size, the block widths (the downsampling factor), the latent
    channels and the latent scaling factor."""
    get = vae_config.get if isinstance(vae_config, dict) else lambda name: getattr(vae_config, name, None)
    signature = {}
    for name in VAE_SIGNATURE_FIELDS:
        value = get(name)
        signature[name] = list(value) if isinstance(value, list | tuple) else value
    return signature


def check_vae_signature(vae_config: Any, trained_vae: dict[str, Any] | None, name: str = "vae") -> None:
    """Refuse a VAE whose shape differs from the one a model was trained with (``trained_vae``, recorded
    in its ``pose_projection`` config); ``None`` (not recorded) accepts any.

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
    ``cc_projection``).

    Initialised as the identity on the image-embedding inputs and zero on the pose inputs and the bias,
    so that before fine-tuning the UNet sees the plain CLIP image embedding. The weights live in
    ``self.projection`` (keys ``projection.weight`` / ``projection.bias``), the layout of the
    ``cc_projection`` folder of the diffusers zero-1-to-3 checkpoints.

    Args:
        in_features: Image-embedding dimension + 4 (772 for zero-1-to-3's CLIP ViT-L/14).
        out_features: Cross-attention dimension of the UNet (768 for zero-1-to-3).
        input_depression: The pose's fourth entry is the input chip's absolute depression (Stable
            Zero123's convention, :func:`embed_pose`) instead of 0; the pipeline then needs
            ``input_depression_deg``.
        trained_d_el_deg: ``[min, max]`` of the depression changes the model was trained on, or
            ``None`` (unknown); the pipeline refuses requests outside it.
        trained_depression_deg: ``[min, max]`` of the absolute depressions (inputs and targets) it was
            trained on, or ``None``.
        spatial_pose: What the UNet sees of the input view besides its latent (:data:`SPATIAL_POSE_MODES`,
            :func:`~sar_zero123.model.spatial_pose.unet_condition_latents`): ``None`` is zero-1-to-3 (every
            loaded zero-1-to-3 checkpoint and every pipeline saved before the field existed);
            ``"rotated_input"`` also concatenates the input latent turned in the image plane by
            ``rotation_sign * d_az``, a spatial hint of where the target's footprint lies (the UNet then has
            ``3 * latent_channels`` input channels); ``"proxy"`` adds to those two the latents of the input's
            simulator proxy rendered at the input's pose and at the requested pose
            (:func:`~sar_zero123.model.spatial_pose.proxy_pair_latents`; ``5 * latent_channels`` inputs):
            the UNet learns "the proxy at the input's pose is to the proxy at the target pose as the input is
            to the target".
        rotation_sign: ``+1`` or ``-1``: the image-plane turn per degree of ``d_az`` in the training
            data's azimuth convention (``-1`` for the built-in simulator, :data:`SIMULATOR_ROTATION_SIGN`).
        trained_vae: The shape of the VAE the model was trained with (:func:`vae_signature`: chip size,
            block widths, latent channels, scaling factor), or ``None`` (unknown: pipelines saved before
            the field existed, zero-1-to-3 checkpoints); a pipeline refuses a VAE of another shape.
        trained_estimator: The SHA-256 of the azimuth estimator the UNet was trained beside
            (:func:`~sar_zero123.model.orientation.estimator_weights_digest`), or ``None`` (unknown); a
            pipeline refuses another estimator.
        reference_layers: ``0``: the UNet's self-attentions see only the view being generated (every
            pipeline saved before the field existed). ``n > 0``: each of the UNet's ``n`` self-attentions
            also attends to the input view's own features (:mod:`sar_zero123.model.reference_attention`),
            weighted by ``tanh`` of its gate in ``reference_gates`` (``(n,)``, zero at the start: a warm
            start computes exactly what the model did without it).
        input_token_layers: ``0``: the UNet's cross-attentions see only the pose token (every pipeline saved
            before the field existed). ``n > 0``: each of its ``n`` cross-attentions also attends to the
            input's latent as one token per place (:mod:`sar_zero123.model.input_tokens`), weighted by
            ``tanh`` of its gate in ``token_gates`` (zero at the start), the tokens made by
            ``token_projection``.
        input_token_channels: The latent channels the token projection takes (with
            ``input_token_layers > 0``).

    Raises:
        ValueError: If ``in_features <= 4``, ``out_features < 1``, a range is not ``[min, max]``,
            ``spatial_pose`` is not one of :data:`SPATIAL_POSE_MODES` or ``rotation_sign`` not +-1.
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
    ) -> None:
        super().__init__()
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
        """Create the input tokens' projection and their ``layers`` zero gates (the caller records the
        config: :func:`~sar_zero123.model.input_tokens.enable_input_tokens`)."""
        self.token_projection = torch.nn.Linear(token_feature_dim(latent_channels), self.config.out_features)
        self.token_gates = torch.nn.Parameter(torch.zeros(layers))

    @property
    def image_embed_dim(self) -> int:
        """Size of the image embedding this projection expects (``in_features - 4``)."""
        return self.config.in_features - POSE_DIM

    def forward(self, image_embeds: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        """Project the concatenated image embedding and pose.

        Args:
            image_embeds: CLIP image embeddings.
            pose: Pose vectors from :func:`embed_pose`.

        Returns:
            The cross-attention conditioning token.

        Shape:
            - image_embeds: ``(B, 1, in_features - 4)``
            - pose: ``(B, 1, 4)``
            - Output: ``(B, 1, out_features)``

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
    """Size of one input token's features before the projection: the latent, two positions' Fourier
    features (2 coordinates x sin/cos x :data:`TOKEN_FREQUENCIES` each) and the pose."""
    return int(latent_channels) + 2 * 4 * TOKEN_FREQUENCIES + POSE_DIM


def match_channels(images: torch.Tensor, channels: int) -> torch.Tensor:
    """Replicate a single-channel SAR batch to ``channels`` (or pass it through when it already matches).

    Args:
        images: Batch of images.
        channels: Channel count the receiving model takes (1 or 3 in practice).

    Returns:
        The batch with ``channels`` channels.

    Shape:
        - images: ``(B, 1 | channels, H, W)``
        - Output: ``(B, channels, H, W)``

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
    """CLIP image embedding of a batch of SAR chips in the normalised dB domain.

    Preprocessing is zero-1-to-3's exactly (``FrozenCLIPImageEmbedder.preprocess``, also used by the paper's
    authors and the diffusers community pipeline): bicubic resize to the encoder's ``config.image_size``
    with ``align_corners=True`` and no antialiasing, then CLIP mean/std normalisation; an Objaverse
    checkpoint therefore sees the conditioning it was trained with. zero-1-to-3 calls kornia's
    ``resize(..., interpolation="bicubic", align_corners=True, antialias=False)``, which is
    ``F.interpolate(mode="bicubic", align_corners=True)`` (cubic convolution, ``a = -0.75``, borders
    replicated) without kornia's optional blur; it resizes the [-1, 1] image and then maps to [0, 1],
    which equals resizing the [0, 1] image because the bicubic weights sum to one. No clamping of the
    bicubic overshoot, as in zero-1-to-3. Done in torch rather than with ``CLIPImageProcessor`` so that it
    is batched, differentiable and runs on the encoder's device and dtype.

    Args:
        image_encoder: The CLIP vision tower with projection.
        images: Normalised dB images in [0, 1].
        image_mean: Per-channel mean subtracted after resizing.
        image_std: Per-channel standard deviation divided after resizing.

    Returns:
        ``image_embeds`` as a one-token sequence.

    Shape:
        - images: ``(B, 1 | 3, H, W)``
        - Output: ``(B, 1, projection_dim)``
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
    """Resolution ratio of a diffusers VAE or UNet: ``n`` levels halve it ``n - 1`` times.

    Args:
        block_out_channels: The model's ``config.block_out_channels``.

    Returns:
        ``2 ** (n - 1)``; for the VAE, pixels per latent along each side (diffusers' ``vae_scale_factor``).
    """
    return 2 ** (len(block_out_channels) - 1)


def encode_condition_latents(vae: AutoencoderKL, images: torch.Tensor) -> torch.Tensor:
    """VAE posterior mode of the input view, unscaled, as zero-1-to-3 concatenates it to the noisy latent.

    Only the target latent is multiplied by ``vae.config.scaling_factor`` (see
    :func:`encode_target_latents`); the condition latent is not, as in the original zero-1-to-3.

    Args:
        vae: The autoencoder; ``vae.config.in_channels`` decides whether the chip is replicated.
        images: Normalised dB images in [0, 1].

    Returns:
        The posterior mode.

    Shape:
        - images: ``(B, 1 | 3, H, W)``
        - Output: ``(B, latent_channels, H / f, W / f)`` with
          ``f = downsampling_factor(vae.config.block_out_channels)``.
    """
    return vae.encode(vae_input(vae, images)).latent_dist.mode()


def encode_target_latents(
    vae: AutoencoderKL,
    images: torch.Tensor,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Scaled posterior sample of the target view, the ``x_0`` that the diffusion model learns.

    Args:
        vae: The autoencoder.
        images: Normalised dB images in [0, 1].
        generator: Random generator for the posterior sample.

    Returns:
        ``z * vae.config.scaling_factor`` with ``z`` sampled from the posterior.

    Shape:
        - images: ``(B, 1 | 3, H, W)``
        - Output: ``(B, latent_channels, H / f, W / f)``
    """
    latents = vae.encode(vae_input(vae, images)).latent_dist.sample(generator=generator)
    return latents * vae.config.scaling_factor


def pose_class_labels(
    unet: torch.nn.Module, pose: torch.Tensor, target_features: torch.Tensor | None = None
) -> torch.Tensor | None:
    """The pose as the UNet's ``class_labels`` when it embeds the pose with its timestep, else ``None``.

    A UNet built with ``class_embed_type="projection"`` and ``projection_class_embeddings_input_dim=4``
    (``build_sar_zero123(..., pose_in_time_embedding=True)``) adds a learned projection of the pose vector
    to its timestep embedding, so the pose scales and shifts the features of every ResNet block, on top
    of zero-1-to-3's cross-attention token. With more inputs (``build_sar_zero123(...,
    estimate_input_azimuth=True)``), the target's estimated azimuth and the input's code
    (:func:`~sar_zero123.model.orientation.target_view_features`) follow the pose. The pose is never dropped
    for classifier-free guidance (as in zero-1-to-3), so both guidance branches receive it.

    Args:
        unet: A ``UNet2DConditionModel``, possibly wrapped by DDP (``.module``).
        pose: Pose vectors from :func:`embed_pose`.
        target_features: Outputs of ``target_view_features``; required exactly when the UNet takes them.

    Raises:
        ValueError: If ``target_features`` is missing for a UNet that takes them, given to one that does
            not, or of the wrong size.

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
