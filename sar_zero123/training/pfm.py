"""Projected Feature Matching, Eq. (20): the frozen SAR encoder ``f`` of PFM and the distance
``||f(x0) - f(D(x0_hat))||^2`` (:func:`pfm_loss`).

:func:`load_pfm_encoder` loads ``f`` for a fine-tune: the pooled feature of Eq. (20), optionally followed by
the authors' random projection (:class:`ProjectedFeatureEncoder`), or, departing from the paper, that
feature normalised (:class:`NormalizedFeatureEncoder`) or every stage's map (:class:`StageFeatureEncoder`).
Eq. (21) assembles PFM with L_simple in :func:`~sar_zero123.training.losses.total_loss`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, get_args

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from torch import nn

from sar_zero123.domain import center_crop, signed_to_unit, unit_to_signed
from sar_zero123.encoder import SAREncoder
from sar_zero123.model.conditioning import downsampling_factor

#: Width of the authors' random projection of the SimCLR features in PFM (a 10-way fc layer).
PAPER_PFM_PROJECTION_DIM = 10

#: File name of the projection weights saved in a run folder.
PFM_PROJECTION_FILE = "pfm_projection.safetensors"

def random_feature_projection(in_features: int, out_features: int = PAPER_PFM_PROJECTION_DIM, *,
                              seed: int = 0) -> torch.Tensor:
    """Weights of the authors' PFM projection: a freshly initialised ``nn.Linear(in, out)`` weight.

    The reference implementation applies the encoder's ``fc`` layer, absent from its checkpoint and so left
    at PyTorch's default initialisation, ``U(-1/sqrt(in), 1/sqrt(in))``, before the distance. The bias
    cancels in a difference of features and is omitted. Drawn from a CPU generator seeded with ``seed``:
    same seed, same bytes.

    Args:
        in_features: Encoder feature size (512 for ResNet-18).
        out_features: Projected size (10 in the paper's runs).
        seed: Seed of the draw.

    Returns:
        Float32 weight.

    Shape:
        ``(out_features, in_features)``.

    Raises:
        ValueError: If a size is not positive.
    """
    if in_features < 1 or out_features < 1:
        raise ValueError(f"sizes must be positive, got in_features={in_features}, "
                         f"out_features={out_features}")
    generator = torch.Generator().manual_seed(seed)
    bound = 1.0 / math.sqrt(in_features)
    uniform = torch.rand(out_features, in_features, generator=generator, dtype=torch.float64)
    return ((2.0 * uniform - 1.0) * bound).float()


class ProjectedFeatureEncoder(nn.Module):
    """A frozen SAR encoder followed by a frozen random projection: the paper-comparable PFM features.

    ``forward`` returns ``W f(x) / sqrt(k)`` for the ``(k, D)`` weight ``W``, so that the squared L2
    distance of :func:`pfm_loss` equals the authors' ``mse_loss`` of the projected features, i.e. the
    *mean* over the ``k`` outputs of the squared difference. With ``W`` from
    :func:`random_feature_projection` this is their PFM, whose lambda values the paper reports. Its
    expectation over the draw of ``W`` is ``||f(x0) - f(x0_hat)||^2 / (3 D)`` (each entry has variance
    ``1 / (3 D)``), i.e. 1536x smaller than the 512-d form for ``D = 512``; one draw scatters around that.

    The weight is a buffer: it moves with ``.to()``, is saved in ``state_dict`` and never trains.
    ``config`` is the wrapped encoder's (``image_size`` is read by :func:`pfm_loss`).

    Args:
        encoder: The frozen SAR encoder (``forward((B, 1, S, S)) -> (B, D)``).
        weight: ``(k, D)`` projection.
    """

    def __init__(self, encoder: nn.Module, weight: torch.Tensor) -> None:
        super().__init__()
        if weight.ndim != 2:
            raise ValueError(f"weight must be (k, D), got {tuple(weight.shape)}")
        self.encoder = encoder
        self.config = encoder.config
        self.register_buffer("weight", weight.detach().clone())

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        features = self.encoder(images)  # (B, D)
        return F.linear(features, self.weight.to(features.dtype)) / math.sqrt(self.weight.shape[0])

    def save_projection(self, directory) -> None:
        """Write the weight to ``directory / PFM_PROJECTION_FILE`` (safetensors)."""
        save_file({"weight": self.weight.detach().float().cpu().contiguous()},
                  str(Path(directory) / PFM_PROJECTION_FILE))


#: What PFM's encoder returns (``FinetuneConfig.pfm_features``): "pooled", Eq. (20)'s pooled feature;
#: "normalized", that feature on the unit sphere; "stages", every stage's map, LPIPS-style.
PfmFeatures = Literal["pooled", "normalized", "stages"]
PFM_FEATURES: tuple[str, ...] = get_args(PfmFeatures)

#: Added under the square root of the channel norms of :class:`StageFeatureEncoder` (LPIPS uses 1e-10):
#: keeps the normalisation and its gradient finite where a ReLU map is zero at a position.
_NORM_EPS = 1.0e-10


def check_pfm_features(features: str, projection_dim: int | None = None) -> None:
    """Refuse an unknown ``pfm_features`` name, or the random projection of other than pooled features.

    Raises:
        ValueError: Naming the field (``pfm_features`` or ``pfm_projection_dim``) and what is expected.
    """
    if features not in PFM_FEATURES:
        raise ValueError(f"pfm_features must be one of {PFM_FEATURES}, got {features!r}")
    if projection_dim is not None and features != "pooled":
        raise ValueError(f"pfm_projection_dim: the random projection applies to pooled features only, "
                         f"got pfm_features={features!r}; set pfm_projection_dim to null")


def _unit_along_channels(features: torch.Tensor) -> torch.Tensor:
    """``features`` (float32) divided by their L2 norm along dim 1, finite where that norm is 0."""
    features = features.float()
    return features / torch.sqrt(features.pow(2).sum(dim=1, keepdim=True) + _NORM_EPS)


class NormalizedFeatureEncoder(nn.Module):
    """A frozen SAR encoder whose pooled feature is divided by its L2 norm (a departure from Eq. 20).

    SimCLR's loss compares features by their cosine only (NT-Xent on normalised projections), so the
    length of ``f(x)`` is not something the encoder was trained to make meaningful. With unit features
    ``||u - v||^2 = 2 - 2 cos(u, v)``: PFM then matches the direction of the target's feature alone.

    Args:
        encoder: The frozen SAR encoder (``forward((B, 1, S, S)) -> (B, D)``).
    """

    def __init__(self, encoder: nn.Module) -> None:
        super().__init__()
        self.encoder = encoder
        self.config = encoder.config

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return _unit_along_channels(self.encoder(images))


class StageFeatureEncoder(nn.Module):
    """Every stage's feature map, LPIPS-style (Zhang et al., 2018, Eq. 1 with unit weights): a departure
    from Eq. 20, which matches only the last stage, pooled.

    Each stage's map is normalised to unit length along its channels at every position and divided by
    ``sqrt(H_i W_i)``, and the stages are concatenated, so that the squared distance :func:`pfm_loss` takes
    of two outputs is ``sum_i mean_(h, w) ||u_i(h, w) - v_i(h, w)||^2``: LPIPS without its learned channel
    weights (which need human judgements no SAR data set has). Unlike the pooled feature, the maps keep
    *where* the features are, so the distance sees a turned footprint even where a pooled feature would
    not.

    Args:
        encoder: A frozen :class:`~sar_zero123.encoder.SAREncoder` (``stage_features``).
    """

    def __init__(self, encoder: nn.Module) -> None:
        super().__init__()
        if not hasattr(encoder, "stage_features"):
            raise ValueError("pfm_features='stages' needs a SAREncoder (it reads stage_features)")
        self.encoder = encoder
        self.config = encoder.config

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        parts = []
        for hidden in self.encoder.stage_features(images):
            unit = _unit_along_channels(hidden)
            parts.append(unit.flatten(1) / math.sqrt(hidden.shape[-2] * hidden.shape[-1]))
        return torch.cat(parts, dim=1)


def pfm_feature_encoder(encoder: nn.Module, features: str) -> nn.Module:
    """``encoder`` returning the features named by ``features`` (one of :data:`PFM_FEATURES`), frozen.

    Raises:
        ValueError: For an unknown name.
    """
    check_pfm_features(features)
    if features == "pooled":
        return encoder
    wrapper = NormalizedFeatureEncoder if features == "normalized" else StageFeatureEncoder
    return wrapper(encoder).eval().requires_grad_(False)


def project_encoder_features(encoder: nn.Module, projection_dim: int | None, *, seed: int = 0) -> nn.Module:
    """``encoder`` unchanged when ``projection_dim`` is None, else wrapped in a seeded
    :class:`ProjectedFeatureEncoder` (the paper-comparable PFM with ``projection_dim = 10``)."""
    if projection_dim is None:
        return encoder
    weight = random_feature_projection(encoder.feature_dim, projection_dim, seed=seed)
    return ProjectedFeatureEncoder(encoder, weight).eval().requires_grad_(False)


def load_pfm_encoder(
    path: str | Path, *, image_size: int, projection_dim: int | None = None, seed: int = 0,
    features: str = "pooled",
) -> nn.Module:
    """The frozen SAR encoder ``f`` of Eq. (20), checked against the training resolution; with
    ``projection_dim`` followed by the seeded random projection (:func:`project_encoder_features`), with
    ``features`` other than ``"pooled"`` returning those features (:func:`pfm_feature_encoder`).

    Args:
        path: A ``SAREncoder.save_pretrained`` folder (``train/pretrain_simclr.py``'s ``encoder/``).
        image_size: The chip side the diffusion model trains on.
        projection_dim: ``None`` (full features) or ``k`` (the paper-comparable projection).
        seed: Seed of the projection.
        features: One of :data:`PFM_FEATURES`; only ``"pooled"`` takes a projection.

    Raises:
        FileNotFoundError: If the folder or its files are missing.
        ValueError: If the encoder was trained at another resolution, or a projection is asked of other
            than pooled features.
    """
    check_pfm_features(features, projection_dim)
    encoder = SAREncoder.from_pretrained(path)
    if encoder.config.image_size != image_size:
        raise ValueError(
            f"encoder: {str(path)!r} was trained on {encoder.config.image_size} px chips but training "
            f"runs at image_size={image_size}; train the encoder at {image_size} px or set --image_size "
            f"{encoder.config.image_size}"
        )
    encoder = encoder.eval().requires_grad_(False)
    return pfm_feature_encoder(project_encoder_features(encoder, projection_dim, seed=seed), features)


def _require_frozen(module: nn.Module, name: str) -> None:
    if module.training:
        raise ValueError(f"{name} must be in eval mode (call {name}.eval())")
    if any(p.requires_grad for p in module.parameters()):
        raise ValueError(f"{name} must be frozen ({name}.requires_grad_(False)): PFM gradients may only "
                         "reach the diffusion parameters")


def _to_encoder_input(images: torch.Tensor, size: int) -> torch.Tensor:
    """(B, C, H, W) VAE-domain images in [-1, 1] -> (B, 1, size, size) normalised dB in [0, 1]."""
    images = images.mean(dim=1, keepdim=True) if images.shape[1] > 1 else images
    images = signed_to_unit(images)
    if images.shape[-1] != size or images.shape[-2] != size:
        # antialiased resize has no bf16/fp16 CPU kernel: resize in float32
        images = F.interpolate(images.float(), size=(size, size), mode="bilinear", align_corners=False,
                               antialias=True)
    return images


@torch.no_grad()
def encode_target_features(target_images: torch.Tensor, encoder: nn.Module, *,
                           crop_size: int | None = None) -> torch.Tensor:
    """Frozen-encoder features h = f(x0) of the real target views (no gradient).

    Args:
        target_images: Target views, normalised dB in [0, 1].
        encoder: Frozen SAR encoder (``forward((B, 1, S, S)) -> (B, D)``, ``config.image_size``).
        crop_size: Optional centre crop in pixels (before the resize to ``encoder.config.image_size``).

    Returns:
        Float32 features.

    Shape:
        ``(B, 1, H, W) -> (B, D)``.
    """
    images = center_crop(target_images, crop_size) if crop_size is not None else target_images
    images = unit_to_signed(images)  # to the VAE's [-1, 1] so both branches share one mapping
    encoder_dtype = next(encoder.parameters()).dtype
    inputs = _to_encoder_input(images, encoder.config.image_size)
    return encoder(inputs.to(encoder_dtype)).float()


def check_pfm_crop_size(
    crop_size: int, *, image_size: int, vae_scale_factor: int, name: str = "crop_size"
) -> None:
    """Refuse a PFM centre crop whose latent window is not centred on whole latent pixels.

    Args:
        crop_size: Side of the centre crop in pixels.
        image_size: Side of the images in pixels.
        vae_scale_factor: The VAE's downsampling factor (pixels per latent pixel).
        name: What the crop size is called in the message (a flag, an argument).

    Raises:
        ValueError: Unless ``0 < crop_size <= image_size`` and ``image_size - crop_size`` is a multiple of
            ``2 * vae_scale_factor``.
    """
    if crop_size <= 0 or crop_size > image_size or (image_size - crop_size) % (2 * vae_scale_factor):
        raise ValueError(f"{name} must be in (0, {image_size}] with (image_size - {name}) a multiple of "
                         f"{2 * vae_scale_factor} so the latent window is centred, got {crop_size}")


def pfm_loss(
    x0_hat_latents: torch.Tensor,
    target_images: torch.Tensor,
    vae,
    encoder: nn.Module,
    *,
    crop_size: int | None = None,
    target_features: torch.Tensor | None = None,
) -> torch.Tensor:
    """Projected Feature Matching, Eq. (20): ``||f(x0) - f(D(x0_hat))||^2`` per sample.

    ``x0_hat`` is divided by ``vae.config.scaling_factor`` and decoded by the frozen VAE; the decoded image
    (VAE domain [-1, 1]) is averaged to one channel, mapped to normalised dB ``(x + 1) / 2`` and resized to
    the encoder's input size; ``f`` is the encoder's pooled feature. With ``crop_size`` only the latent
    window covering the centre ``crop_size`` pixels is decoded (the paper scores the 64x64 centre of a
    128 px chip), which cuts the decoder cost by ``(image_size / crop_size)**2``; the crop of the
    target and of the estimate are both resized to the encoder's input size, so the encoder cost stays.
    Decoding a latent window is not the centre of the full decode: the VAE's mid-block self-attention
    sees only the window, which changes interior pixels as much as border ones.

    Gradients flow through the frozen decoder and encoder into ``x0_hat_latents`` only.

    Args:
        x0_hat_latents: Scaled x0 estimate from :func:`~sar_zero123.training.losses.estimate_x0`.
        target_images: Real target views, normalised dB in [0, 1] (the same chips the latents encode).
        vae: Frozen ``AutoencoderKL`` (eval mode, no gradients).
        encoder: Frozen SAR encoder with ``config.image_size`` (eval mode, no gradients).
        crop_size: Optional side in pixels of the centre crop; ``image_size - crop_size`` must be a
            multiple of twice the VAE downsampling factor.
        target_features: Optional precomputed :func:`encode_target_features` output.

    Returns:
        Float32 per-sample squared L2 feature distance.

    Shape:
        ``x0_hat_latents``: ``(B, 4, h, w)``; ``target_images``: ``(B, 1, H, W)`` with
        ``H = h * factor``; returns ``(B,)``.

    Raises:
        ValueError: On frozen-module violations, mismatched batch or sizes, or a bad ``crop_size``.
    """
    # 1. check inputs
    _require_frozen(vae, "vae")
    _require_frozen(encoder, "encoder")
    if x0_hat_latents.shape[0] != target_images.shape[0]:
        raise ValueError(f"batch sizes differ: x0_hat_latents {x0_hat_latents.shape[0]}, "
                         f"target_images {target_images.shape[0]}")
    factor = downsampling_factor(vae.config.block_out_channels)
    image_size = target_images.shape[-1]
    if x0_hat_latents.shape[-1] * factor != image_size:
        raise ValueError(f"target_images side {image_size} != latent side {x0_hat_latents.shape[-1]} x "
                         f"VAE factor {factor}")
    latents = x0_hat_latents
    if crop_size is not None:
        check_pfm_crop_size(crop_size, image_size=image_size, vae_scale_factor=factor)
        latents = center_crop(latents, crop_size // factor)
    # 2. features of the real target (no gradient)
    if target_features is None:
        target_features = encode_target_features(target_images, encoder, crop_size=crop_size)
    # 3. decode the estimate and encode it; gradients flow to x0_hat_latents
    vae_dtype = next(vae.parameters()).dtype
    decoded = vae.decode(latents.to(vae_dtype) / vae.config.scaling_factor).sample  # (B, C, crop, crop)
    encoder_dtype = next(encoder.parameters()).dtype
    inputs = _to_encoder_input(decoded, encoder.config.image_size)
    features = encoder(inputs.to(encoder_dtype)).float()
    return (features - target_features).pow(2).sum(dim=1)
