"""The input view's azimuth, estimated and turned by the requested pose: the SAR-sized absolute-pose path.

zero-1-to-3 gives its UNet only the *relative* pose. To place the target view, a UNet trained from
scratch must then read the input's azimuth ``a`` off the condition latent and add ``d_az`` to it inside
its own layers; ``sin(a + d) = sin a cos d + cos a sin d`` is a product of two inputs, which additive
conditioning learns slowly. An oracle ablation on the simulator shows it: a small UNet given the target's
absolute azimuth learns to place views, while the same UNet given ``a`` and ``d_az`` as separate inputs
stays near the input copy's error.

:class:`AzimuthEstimator` reads ``a`` from the condition latent (trained with the UNet and supervised by
the input chip's known azimuth, :func:`azimuth_estimation_loss`), and :func:`turn_azimuth` adds ``d_az``
in closed form, so the UNet receives the target's estimated azimuth ``[sin(a + d), cos(a + d)]`` in its
timestep embedding (:func:`~sar_zero123.model.conditioning.pose_class_labels`). The conditioning contract is
unchanged: an input view and a relative pose; no absolute azimuth is needed at sampling time.
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
    """Azimuths in degrees as unit vectors ``[sin a, cos a]``.

    Shape:
        ``(B,)`` -> ``(B, 2)`` float32.
    """
    radians = torch.as_tensor(azimuth_deg, dtype=torch.float64).reshape(-1) * (math.pi / 180.0)
    return torch.stack([torch.sin(radians), torch.cos(radians)], dim=-1).float()


def azimuth_deg(vector: torch.Tensor) -> torch.Tensor:
    """The azimuth in [0, 360) degrees of ``[sin a, cos a, ...]`` (the inverse of :func:`azimuth_vector`).

    Only the first two entries are read, so an :class:`AzimuthEstimator`'s output (with its code) works.

    Shape:
        ``(B, >= 2)`` -> ``(B,)`` float64.
    """
    return torch.rad2deg(torch.atan2(vector[:, 0].double(), vector[:, 1].double())) % 360.0


def turn_azimuth(vector: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Turns azimuth unit vectors by the pose's ``d_az``: ``[sin(a + d), cos(a + d)]``.

    The angle-sum identities, with ``sin d`` and ``cos d`` read from slots 1 and 2 of the zero-1-to-3 pose
    vector (:func:`~sar_zero123.model.conditioning.embed_pose`).

    Args:
        vector: ``[sin a, cos a]`` per sample (need not be exactly unit length).
        pose: Pose vectors ``[d_el_rad, sin d_az, cos d_az, 0]``.

    Shape:
        vector ``(B, 2)``, pose ``(B, 1, 4)`` -> ``(B, 2)``.
    """
    sin_a, cos_a = vector[:, 0], vector[:, 1]
    pose = pose.reshape(pose.shape[0], -1).to(vector.dtype)
    sin_d, cos_d = pose[:, 1], pose[:, 2]
    return torch.stack([sin_a * cos_d + cos_a * sin_d, cos_a * cos_d - sin_a * sin_d], dim=-1)


def target_view_features(estimate: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """What the UNet's timestep embedding receives after the pose: the turned azimuth, then the input's code.

    Args:
        estimate: :class:`AzimuthEstimator` outputs ``[sin a, cos a, code...]``.
        pose: Pose vectors ``[d_el_rad, sin d_az, cos d_az, 0]``.

    Shape:
        estimate ``(B, 2 + code_dim)``, pose ``(B, 1, 4)`` -> ``(B, 2 + code_dim)``.
    """
    return torch.cat([turn_azimuth(estimate[:, :AZIMUTH_DIM], pose), estimate[:, AZIMUTH_DIM:]], dim=-1)


def azimuth_estimation_loss(
    vector: torch.Tensor, azimuth_deg: torch.Tensor | Sequence[float]
) -> torch.Tensor:
    """Per-sample ``1 - cos(a_hat - a)`` between estimated unit vectors and true azimuths.

    0 for a perfect estimate, 2 for one off by 180 degrees; smooth everywhere (unlike an angle difference).
    Only the first two entries of ``vector`` are read (an :class:`AzimuthEstimator`'s code is not supervised).

    Shape:
        vector ``(B, 2 + code_dim)``, azimuth_deg ``(B,)`` -> ``(B,)`` float32.
    """
    truth = azimuth_vector(azimuth_deg).to(vector.device)
    return 1.0 - (vector[:, :AZIMUTH_DIM].float() * truth).sum(dim=-1)


class AzimuthEstimator(ModelMixin, ConfigMixin):
    """Small CNN reading the input view's azimuth ``[sin a, cos a]`` (and a code) from its condition latent.

    Sized for SAR chip latents (16x16x4 for a 64 px chip): strided 3x3 convolutions, an adaptive pool to a
    4x4 map (the layout of the target, not only its texture, tells its azimuth) and a linear head. The
    azimuth part is normalised to unit length and supervised (:func:`azimuth_estimation_loss`); the
    ``code_dim`` further outputs are a code of the input view (its class and appearance) that only the
    denoising loss trains. Without it, the UNet must read the object's identity from the condition latent
    of a view at another azimuth, and its outputs follow the pose but lose the class.

    Args:
        latent_channels: Channels of the VAE latent.
        hidden_channels: Channels of the convolutions; each after the first halves the resolution.
        code_dim: Size of the input-view code (0: the azimuth only).

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
    """SHA-256 of an azimuth estimator's weights (names and values at float16, so that a bundled copy stored
    in float16 and the float32 weights it came from agree): the estimator a UNet was trained beside, recorded
    in ``PoseProjection.config.trained_estimator`` and checked when a pipeline is assembled."""
    digest = hashlib.sha256()
    for name, tensor in sorted(estimator.state_dict().items()):
        digest.update(name.encode() + b"\0")
        digest.update(tensor.detach().to(device="cpu", dtype=torch.float16).contiguous().numpy().tobytes())
    return digest.hexdigest()
