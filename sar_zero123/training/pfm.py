"""Projected Feature Matching, Eq. (20): the frozen SAR encoder ``f`` and ``||f(x0) - f(D(x0_hat))||^2``.

``f`` is the pooled feature of Eq. (20), optionally followed by the authors' random projection. Eq. (21) is
:func:`~sar_zero123.training.losses.total_loss`.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from torch import nn

from sar_zero123.domain import signed_to_unit, unit_to_signed
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
    at PyTorch's default ``U(-1/sqrt(in), 1/sqrt(in))``. The bias cancels in a difference and is omitted.
    Drawn from a CPU generator seeded with ``seed``: same seed, same bytes.

    Shape:
        ``(out_features, in_features)``, float32.

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

    ``forward`` returns ``W f(x) / sqrt(k)`` for the ``(k, D)`` weight ``W``, so the squared L2 distance of
    :func:`pfm_loss` equals the authors' ``mse_loss`` of the projected features, the scale their lambda
    values assume. The weight is a buffer: it moves with ``.to()``, is saved and never trains.
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


def project_encoder_features(encoder: nn.Module, projection_dim: int | None, *, seed: int = 0) -> nn.Module:
    """``encoder``, wrapped in a seeded ProjectedFeatureEncoder unless ``projection_dim`` is None."""
    if projection_dim is None:
        return encoder
    weight = random_feature_projection(encoder.feature_dim, projection_dim, seed=seed)
    return ProjectedFeatureEncoder(encoder, weight).eval().requires_grad_(False)


def load_pfm_encoder(
    path: str | Path, *, image_size: int, projection_dim: int | None = None, seed: int = 0
) -> nn.Module:
    """The frozen SAR encoder ``f`` of Eq. (20) from a ``SAREncoder.save_pretrained`` folder;
    ``projection_dim`` adds the seeded random projection.

    Raises:
        FileNotFoundError: If the folder or its files are missing.
        ValueError: If the encoder was trained at another resolution than ``image_size``.
    """
    encoder = SAREncoder.from_pretrained(path)
    if encoder.config.image_size != image_size:
        raise ValueError(
            f"encoder: {str(path)!r} was trained on {encoder.config.image_size} px chips but training "
            f"runs at image_size={image_size}; train the encoder at {image_size} px or set --image_size "
            f"{encoder.config.image_size}"
        )
    return project_encoder_features(encoder.eval().requires_grad_(False), projection_dim, seed=seed)


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
def encode_target_features(target_images: torch.Tensor, encoder: nn.Module) -> torch.Tensor:
    """Frozen-encoder features h = f(x0) of the real target views (no gradient).

    Shape:
        ``(B, 1, H, W)`` normalised dB in [0, 1] -> ``(B, D)`` float32.
    """
    images = unit_to_signed(target_images)  # to the VAE's [-1, 1] so both branches share one mapping
    encoder_dtype = next(encoder.parameters()).dtype
    inputs = _to_encoder_input(images, encoder.config.image_size)
    return encoder(inputs.to(encoder_dtype)).float()


def pfm_loss(
    x0_hat_latents: torch.Tensor,
    target_images: torch.Tensor,
    vae,
    encoder: nn.Module,
    *,
    target_features: torch.Tensor | None = None,
) -> torch.Tensor:
    """Projected Feature Matching, Eq. (20): ``||f(x0) - f(D(x0_hat))||^2`` per sample.

    ``x0_hat`` is unscaled and decoded by the frozen VAE; the decode ([-1, 1]) is averaged to one channel,
    mapped to normalised dB and resized to the encoder's input. The whole latent is decoded. Gradients
    reach ``x0_hat_latents`` only.

    Args:
        x0_hat_latents: Scaled x0 estimate (:func:`~sar_zero123.training.losses.estimate_x0`).
        target_images: Real target views, normalised dB in [0, 1].
        vae: Frozen ``AutoencoderKL`` in eval mode.
        encoder: Frozen SAR encoder with ``config.image_size``, in eval mode.
        target_features: Optional precomputed :func:`encode_target_features` output.

    Shape:
        ``x0_hat_latents``: ``(B, 4, h, w)``; ``target_images``: ``(B, 1, H, W)`` with
        ``H = h * factor``; returns ``(B,)`` float32.

    Raises:
        ValueError: On frozen-module violations, mismatched batch or sizes.
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
    # 2. features of the real target (no gradient)
    if target_features is None:
        target_features = encode_target_features(target_images, encoder)
    # 3. decode the estimate and encode it; gradients flow to x0_hat_latents
    vae_dtype = next(vae.parameters()).dtype
    decoded = vae.decode(x0_hat_latents.to(vae_dtype) / vae.config.scaling_factor).sample  # (B, C, H, W)
    encoder_dtype = next(encoder.parameters()).dtype
    inputs = _to_encoder_input(decoded, encoder.config.image_size)
    features = encoder(inputs.to(encoder_dtype)).float()
    return (features - target_features).pow(2).sum(dim=1)
