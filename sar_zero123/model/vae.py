"""The SAR autoencoder: a 1-channel ``AutoencoderKL`` built for a chip size or loaded, its reconstructions
and its latent scaling factor.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from diffusers import AutoencoderKL
from torch.utils.data import DataLoader

from sar_zero123.domain import signed_to_unit
from sar_zero123.model.conditioning import encode_condition_latents, vae_input
from sar_zero123.model.loading import load_component
from sar_zero123.pretrained import resolve_pretrained

__all__ = [
    "latent_scaling_factor",
    "load_pretrained_vae",
    "new_sar_vae",
    "reconstruct",
    "reconstruct_in_batches",
]


def new_sar_vae(
    *,
    image_size: int,
    block_out_channels: Sequence[int],
    layers_per_block: int,
    latent_channels: int,
    norm_num_groups: int,
) -> AutoencoderKL:
    """A randomly initialised 1-channel ``AutoencoderKL``: one down/up block per width of
    ``block_out_channels`` (downsampling ``2 ** (len - 1)``), built for ``image_size`` px chips."""
    levels = len(block_out_channels)
    return AutoencoderKL(
        in_channels=1,
        out_channels=1,
        down_block_types=("DownEncoderBlock2D",) * levels,
        up_block_types=("UpDecoderBlock2D",) * levels,
        block_out_channels=tuple(block_out_channels),
        layers_per_block=layers_per_block,
        latent_channels=latent_channels,
        norm_num_groups=norm_num_groups,
        sample_size=image_size,
    )


def load_pretrained_vae(name_or_path: str) -> AutoencoderKL:
    """The ``AutoencoderKL`` of an AutoencoderKL folder, of a pipeline folder (its ``vae/``) or of a bundled
    pipeline name (``sar-zero123/sim-prior-rotated``).

    Raises:
        FileNotFoundError: If the folder or its files are missing, naming what was expected.
        ValueError: If the model does not load, or takes other than one input and one output channel.
    """
    folder = resolve_pretrained(name_or_path)
    if (folder / "vae" / "config.json").is_file():
        folder = folder / "vae"
    vae = load_component(AutoencoderKL, folder, "pretrained")
    if vae.config.in_channels != 1 or vae.config.out_channels != 1:
        raise ValueError(
            f"pretrained: {str(folder)!r} takes {vae.config.in_channels} and returns "
            f"{vae.config.out_channels} channels; SAR chips need 1 and 1"
        )
    return vae


@torch.no_grad()
def reconstruct(vae: AutoencoderKL, images: torch.Tensor) -> torch.Tensor:
    """Posterior-mode reconstruction in normalised dB, clipped to [0, 1]. Shape: ``(B, 1, S, S)``."""
    latents = encode_condition_latents(vae, images)
    return signed_to_unit(vae.decode(latents).sample.float()).clamp(0.0, 1.0)


def reconstruct_in_batches(vae: AutoencoderKL, images: torch.Tensor, batch_size: int) -> torch.Tensor:
    """:func:`reconstruct` over ``batch_size`` images at a time. Shape: ``(N, 1, S, S)`` -> same."""
    return torch.cat(
        [reconstruct(vae, images[i : i + batch_size]) for i in range(0, len(images), batch_size)]
    )


@torch.no_grad()
def latent_scaling_factor(vae: AutoencoderKL, loader: DataLoader, num_batches: int) -> float:
    """1 / std of posterior samples over training batches (the Stable Diffusion recipe)."""
    generator = torch.Generator().manual_seed(0)
    latents = []
    for i, batch in enumerate(loader):
        if i == num_batches:
            break
        posterior = vae.encode(vae_input(vae, batch["image"])).latent_dist
        latents.append(posterior.sample(generator=generator).float().flatten())
    return float(1.0 / torch.cat(latents).std())
