"""Tiny random components shared by the pipeline, loss and training tests.

``SARZero123Pipeline(**get_dummy_components())`` is a 32 px model (1-channel VAE, 16x16x4 latents) with
about 0.4 M parameters, built from the ``"tiny"`` entry of ``SAR_ZERO123_SIZES`` with
``torch.manual_seed(0)`` before each component, as diffusers' pipeline tests do.
"""

from __future__ import annotations

from typing import Any

import torch
from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.conditioning import POSE_DIM, PoseProjection
from sar_zero123.model.zero123_checkpoints import ZERO123_SCHEDULER_CONFIG

__all__ = ["DUMMY_IMAGE_SIZE", "dummy_images", "get_dummy_components", "read_the_pose"]

DUMMY_IMAGE_SIZE = 32


def get_dummy_components() -> dict[str, Any]:
    """Components for ``SARZero123Pipeline(**components)``.

    Returns:
        ``vae``, ``image_encoder``, ``unet``, ``scheduler``, ``pose_projection`` and
        ``feature_extractor`` (None).
    """
    spec = SAR_ZERO123_SIZES["tiny"]
    torch.manual_seed(0)
    unet = UNet2DConditionModel(**spec["unet"], sample_size=16, in_channels=8, out_channels=4)
    torch.manual_seed(0)
    vae = AutoencoderKL(**spec["vae"], sample_size=DUMMY_IMAGE_SIZE)
    torch.manual_seed(0)
    clip_config = CLIPVisionConfig(**spec["image_encoder"])
    image_encoder = CLIPVisionModelWithProjection(clip_config)
    torch.manual_seed(0)
    cross_attention_dim = spec["unet"]["cross_attention_dim"]
    pose_projection = PoseProjection(clip_config.projection_dim + POSE_DIM, cross_attention_dim)
    return {
        "vae": vae.eval(),
        "image_encoder": image_encoder.eval(),
        "unet": unet.eval(),
        "scheduler": DDIMScheduler(**ZERO123_SCHEDULER_CONFIG),
        "pose_projection": pose_projection.eval(),
        "feature_extractor": None,
    }


def dummy_images(batch_size: int = 1, channels: int = 1, seed: int = 0) -> torch.Tensor:
    """Deterministic normalised dB chips in [0, 1] for the dummy pipeline.

    Args:
        batch_size: Number of chips.
        channels: 1 (SAR) or 3 (replicated).
        seed: Seed of a local generator.

    Returns:
        ``(batch_size, channels, 32, 32)`` float32 in [0, 1].
    """
    generator = torch.Generator().manual_seed(seed)
    images = torch.rand(batch_size, 1, DUMMY_IMAGE_SIZE, DUMMY_IMAGE_SIZE, generator=generator)
    return images.expand(-1, channels, -1, -1).contiguous()


def read_the_pose(pose_projection: PoseProjection, seed: int = 2) -> PoseProjection:
    """``pose_projection`` with random weights on its pose inputs, in place: a fresh one starts at zero
    there and ignores the pose, as a trained one does not (so that a change of pose can show in a test)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        pose_projection.projection.weight[:, -POSE_DIM:].normal_(generator=generator)
    return pose_projection


def proxy_pipeline(proxy: dict):
    """A tiny ``spatial_pose="proxy"`` pipeline whose proxy pair moves the output, with ``proxy`` settings."""
    import torch

    from sar_zero123.model.build import build_sar_zero123
    from sar_zero123.model.pipeline import SARZero123Pipeline
    from sar_zero123.model.spatial_pose import widen_for_proxy

    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    widen_for_proxy(pipe.unet, pipe.pose_projection)
    with torch.no_grad():
        pipe.unet.conv_in.weight[:, 12:].normal_(0.0, 0.05, generator=torch.Generator().manual_seed(1))
    return SARZero123Pipeline(**pipe.components, proxy=proxy)
