"""Cached frozen encodings of a fine-tune's chips: :class:`ChipLatentCache` and :class:`CachedViewPairs`.

The VAE and a frozen CLIP tower never change during fine-tuning, so each chip is encoded once; the target
latent stays a fresh posterior sample per step, drawn from the cached mean and log-variance.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from diffusers import AutoencoderKL
from torch.utils.data import Dataset, default_collate
from transformers import CLIPVisionModelWithProjection

from sar_zero123.data import ViewPairDataset, load_chip
from sar_zero123.model.conditioning import encode_condition_latents, encode_image_embeddings, vae_input

__all__ = ["CachedViewPairs", "ChipLatentCache", "collate_pairs", "load_chip_images"]


@dataclass
class ChipLatentCache:
    """Frozen encodings of every chip of a split, computed once before fine-tuning.

    Attributes:
        images: Normalised dB chips ``(N, 1, S, S)`` (a trained tower's input, and the PFM target).
        latent_mean: VAE posterior mean ``(N, C, h, w)``, unscaled (the condition latent is this mode).
        latent_logvar: VAE posterior log-variance ``(N, C, h, w)``.
        image_embeds: Frozen CLIP embeddings ``(N, 1, D)``, or ``None`` when the tower is trained.
        scaling_factor: ``vae.config.scaling_factor`` (multiplies the target latent only).
        proxy_latents: For a ``spatial_pose="proxy"`` model, the posterior modes of each chip's ``K``
            simulator proxies at its pose ``(N, K, C, h, w)``, else ``None``.
    """

    images: torch.Tensor
    latent_mean: torch.Tensor
    latent_logvar: torch.Tensor
    image_embeds: torch.Tensor | None
    scaling_factor: float
    proxy_latents: torch.Tensor | None = None

    def to(self, device: torch.device | str) -> ChipLatentCache:
        """The same encodings on ``device`` (a GPU-resident cache: batches are drawn without copies)."""
        moved = {name: getattr(self, name).to(device) for name in ("images", "latent_mean", "latent_logvar")}
        embeds = None if self.image_embeds is None else self.image_embeds.to(device)
        proxies = None if self.proxy_latents is None else self.proxy_latents.to(device)
        return dataclasses.replace(self, **moved, image_embeds=embeds, proxy_latents=proxies)

    @classmethod
    @torch.no_grad()
    def encode(
        cls,
        images: torch.Tensor,
        vae: AutoencoderKL,
        image_encoder: CLIPVisionModelWithProjection | None = None,
        batch_size: int = 64,
        proxy_images: torch.Tensor | None = None,
    ) -> ChipLatentCache:
        """Encodes ``images`` ``(N, 1, S, S)`` with the frozen VAE (and CLIP tower), and ``proxy_images``
        ``(N, K, S, S)`` with the VAE; both normalised dB.

        Raises:
            ValueError: If either is empty, of the wrong shape or not finite.
        """
        proxy_latents = None
        if proxy_images is not None:
            if (
                proxy_images.ndim != 4
                or proxy_images.shape[0] != images.shape[0]
                or proxy_images.shape[-2:] != images.shape[-2:]
                or not torch.isfinite(proxy_images).all()
            ):
                raise ValueError(
                    f"proxy_images: expected finite (N, K, S, S) = ({images.shape[0]}, K, "
                    f"{tuple(images.shape[-2:])}), got {tuple(proxy_images.shape)}"
                )
            flat = proxy_images.reshape(-1, 1, *proxy_images.shape[-2:])
            modes = [
                encode_condition_latents(vae, flat[start : start + batch_size]).float().cpu()
                for start in range(0, flat.shape[0], batch_size)
            ]
            latents = torch.cat(modes)
            proxy_latents = latents.reshape(*proxy_images.shape[:2], *latents.shape[1:])
        if images.ndim != 4 or images.shape[0] == 0:
            raise ValueError(
                f"images must be a non-empty (N, C, S, S) tensor, got shape {tuple(images.shape)}"
            )
        if not torch.isfinite(images).all():
            raise ValueError("images contain non-finite values")
        means, logvars, embeds = [], [], []
        for start in range(0, images.shape[0], batch_size):
            chunk = images[start : start + batch_size]
            posterior = vae.encode(vae_input(vae, chunk)).latent_dist
            means.append(posterior.mean.float().cpu())
            logvars.append(posterior.logvar.float().cpu())
            if image_encoder is not None:
                embeds.append(encode_image_embeddings(image_encoder, chunk).float().cpu())
        return cls(
            images=images.float().cpu(),
            latent_mean=torch.cat(means),
            latent_logvar=torch.cat(logvars),
            image_embeds=torch.cat(embeds) if embeds else None,
            scaling_factor=float(vae.config.scaling_factor),
            proxy_latents=proxy_latents,
        )


def load_chip_images(pairs: ViewPairDataset) -> torch.Tensor:
    """Every record of a pair dataset, read once and normalised as its items are.

    Shape:
        ``(len(pairs.records), 1, S, S)`` float32.
    """
    chips = [
        pairs.scaling.normalize(torch.from_numpy(load_chip(record.path, pairs.size, pairs.crop_size))[None])
        for record in pairs.records
    ]
    return torch.stack(chips).float()


class CachedViewPairs(Dataset):
    """The pairs of a :class:`ViewPairDataset` served from a :class:`ChipLatentCache` (no file reads).

    Items hold the wrapped dataset's keys plus ``input_latent_mean``, ``target_latent_mean``,
    ``target_latent_logvar``, with a frozen tower ``input_image_embeds`` and with proxies ``proxy_latents``
    ``(K, 2C, h, w)``. :meth:`set_epoch` redraws the wrapped pair list, so the pairs are the uncached ones.
    """

    def __init__(self, pairs: ViewPairDataset, cache: ChipLatentCache) -> None:
        if cache.images.shape[0] != len(pairs.records):
            raise ValueError(
                f"cache holds {cache.images.shape[0]} chips but the pair dataset has "
                f"{len(pairs.records)} records"
            )
        self.pairs = pairs
        self.cache = cache

    def set_epoch(self, epoch: int) -> None:
        self.pairs.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict:
        source, target = (int(i) for i in self.pairs.pairs[index])
        return self._encodings(source, target) | self.pairs.pair_fields(index)

    def __getitems__(self, indices: list[int]) -> dict:
        """A whole batch at once, as ``default_collate`` of the items would give, with one indexing per
        key and on the cache's device (per-pair fetching bottlenecks a GPU run).
        """
        pairs = torch.from_numpy(self.pairs.pairs[np.asarray(indices, dtype=np.int64)])
        source, target = pairs.to(self.cache.images.device).unbind(1)  # a GPU-resident cache is indexed there
        return self._encodings(source, target) | self.pairs.pair_fields_batch(indices)

    def _encodings(self, source: int | torch.Tensor, target: int | torch.Tensor) -> dict:
        """The cached chips and encodings of the input(s) ``source`` and target(s) ``target``."""
        cache = self.cache
        encodings = {
            "input": cache.images[source],
            "target": cache.images[target],
            "input_latent_mean": cache.latent_mean[source],
            "target_latent_mean": cache.latent_mean[target],
            "target_latent_logvar": cache.latent_logvar[target],
        }
        if cache.image_embeds is not None:
            encodings["input_image_embeds"] = cache.image_embeds[source]
        if cache.proxy_latents is not None:  # (K, 2C, h, w) per pair: each candidate at both poses
            encodings["proxy_latents"] = torch.cat(
                [cache.proxy_latents[source], cache.proxy_latents[target]], dim=-3
            )
        return encodings


def collate_pairs(batch: list[dict] | dict) -> dict:
    """``default_collate`` of pair items; a batch that ``__getitems__`` stacked passes through."""
    if isinstance(batch, dict):
        return batch
    return default_collate(batch)
