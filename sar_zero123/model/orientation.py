"""The input view's azimuth, estimated and turned by the requested pose: the SAR-sized absolute-pose path.

zero-1-to-3 gives its UNet only the relative pose, so a UNet trained from scratch must read the input's
azimuth ``a`` off the condition latent and form ``sin(a + d) = sin a cos d + cos a sin d``, a product that
additive conditioning learns slowly. :class:`AzimuthEstimator` reads ``a`` from the condition latent
(supervised by the input's known azimuth, :func:`azimuth_estimation_loss`) and :func:`turn_azimuth` adds
``d_az`` in closed form, so the UNet's timestep embedding receives ``[sin(a + d), cos(a + d)]``. Sampling
still needs only an input view and a relative pose.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence

import torch
from diffusers.configuration_utils import ConfigMixin, register_to_config
from diffusers.models.modeling_utils import ModelMixin

__all__ = [
    "AZIMUTH_DIM",
    "AzimuthEstimator",
    "azimuth_deg",
    "estimator_weights_digest",
    "azimuth_estimation_loss",
    "azimuth_vector",
    "target_view_features",
    "turn_azimuth",
]

#: Size of an azimuth as a unit vector ``[sin a, cos a]``.
AZIMUTH_DIM = 2


def azimuth_vector(azimuth_deg: torch.Tensor | Sequence[float]) -> torch.Tensor:
    """Azimuths in degrees as unit vectors ``[sin a, cos a]``. ``(B,) -> (B, 2)`` float32."""
    radians = torch.as_tensor(azimuth_deg, dtype=torch.float64).reshape(-1) * (math.pi / 180.0)
    return torch.stack([torch.sin(radians), torch.cos(radians)], dim=-1).float()


def azimuth_deg(vector: torch.Tensor) -> torch.Tensor:
    """The azimuth in [0, 360) degrees of ``[sin a, cos a, ...]`` (only the first two entries are read).

    Shape:
        ``(B, >= 2)`` -> ``(B,)`` float64.
    """
    return torch.rad2deg(torch.atan2(vector[:, 0].double(), vector[:, 1].double())) % 360.0


def turn_azimuth(vector: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Turns azimuth vectors ``[sin a, cos a]`` (not necessarily unit) by the pose's ``d_az`` with the
    angle-sum identities: ``[sin(a + d), cos(a + d)]``.

    Shape:
        vector ``(B, 2)``, pose ``(B, 1, 4)`` -> ``(B, 2)``.
    """
    sin_a, cos_a = vector[:, 0], vector[:, 1]
    pose = pose.reshape(pose.shape[0], -1).to(vector.dtype)
    sin_d, cos_d = pose[:, 1], pose[:, 2]
    return torch.stack([sin_a * cos_d + cos_a * sin_d, cos_a * cos_d - sin_a * sin_d], dim=-1)


def target_view_features(estimate: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """What the UNet's timestep embedding receives after the pose: the turned azimuth, then the input's code.

    Shape:
        estimate ``(B, 2 + code_dim)``, pose ``(B, 1, 4)`` -> ``(B, 2 + code_dim)``.
    """
    return torch.cat([turn_azimuth(estimate[:, :AZIMUTH_DIM], pose), estimate[:, AZIMUTH_DIM:]], dim=-1)


def azimuth_estimation_loss(
    vector: torch.Tensor, azimuth_deg: torch.Tensor | Sequence[float]
) -> torch.Tensor:
    """Per-sample ``1 - cos(a_hat - a)``: 0 for a perfect estimate, 2 off by 180 degrees, smooth everywhere.
    Only the first two entries of ``vector`` are read (the code is not supervised).

    Shape:
        vector ``(B, 2 + code_dim)``, azimuth_deg ``(B,)`` -> ``(B,)`` float32.
    """
    truth = azimuth_vector(azimuth_deg).to(vector.device)
    return 1.0 - (vector[:, :AZIMUTH_DIM].float() * truth).sum(dim=-1)


class AzimuthEstimator(ModelMixin, ConfigMixin):
    """Small CNN reading the input view's azimuth ``[sin a, cos a]`` (and a code) from its condition latent.

    Strided 3x3 convolutions (each after the first halves the resolution), an adaptive pool to 4x4 (the
    target's layout, not only its texture, tells its azimuth) and a linear head. The azimuth part is
    normalised and supervised; the ``code_dim`` further outputs, trained by the denoising loss only, carry
    the input's class and appearance, which the UNet otherwise loses.

    Raises:
        ValueError: If ``latent_channels < 1``, ``hidden_channels`` is empty or not positive, or
            ``code_dim < 0``.

    Shape:
        ``(B, latent_channels, h, w)`` unscaled condition latents -> ``(B, 2 + code_dim)``.
    """

    @register_to_config
    def __init__(
        self, latent_channels: int = 4, hidden_channels: Sequence[int] = (32, 64, 64), code_dim: int = 0
    ) -> None:
        super().__init__()
        if latent_channels < 1:
            raise ValueError(f"`latent_channels` must be >= 1, got {latent_channels}")
        if len(hidden_channels) == 0 or min(hidden_channels) < 1:
            raise ValueError(
                f"`hidden_channels` must be a non-empty list of positive ints, got {hidden_channels}"
            )
        if code_dim < 0:
            raise ValueError(f"`code_dim` must be >= 0, got {code_dim}")
        layers: list[torch.nn.Module] = []
        channels = latent_channels
        for index, width in enumerate(hidden_channels):
            layers += [
                torch.nn.Conv2d(channels, width, 3, stride=1 if index == 0 else 2, padding=1),
                torch.nn.SiLU(),
            ]
            channels = width
        self.features = torch.nn.Sequential(*layers, torch.nn.AdaptiveAvgPool2d(4), torch.nn.Flatten())
        self.head = torch.nn.Linear(channels * 16, AZIMUTH_DIM + code_dim)

    @property
    def output_dim(self) -> int:
        """``2 + code_dim``: the inputs it adds to the UNet's pose embedding."""
        return AZIMUTH_DIM + self.config.code_dim

    def forward(self, condition_latents: torch.Tensor) -> torch.Tensor:
        raw = self.head(self.features(condition_latents.to(self.head.weight.dtype))).float()
        azimuth = torch.nn.functional.normalize(raw[:, :AZIMUTH_DIM], dim=-1, eps=1e-6)
        return torch.cat([azimuth, raw[:, AZIMUTH_DIM:]], dim=-1)


def estimator_weights_digest(estimator: torch.nn.Module) -> str:
    """SHA-256 of an azimuth estimator's weights at float16 (so a bundled float16 copy and its float32
    source agree), recorded in ``PoseProjection.config.trained_estimator``.
    """
    digest = hashlib.sha256()
    for name, tensor in sorted(estimator.state_dict().items()):
        digest.update(name.encode() + b"\0")
        digest.update(tensor.detach().to(device="cpu", dtype=torch.float16).contiguous().numpy().tobytes())
    return digest.hexdigest()
