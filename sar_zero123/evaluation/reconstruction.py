"""How well a VAE reconstructs chips: mean PSNR and SSIM (scikit-image) of posterior-mode round trips."""

from __future__ import annotations

import numpy as np
import torch
from diffusers import AutoencoderKL
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from torch.utils.data import DataLoader

from sar_zero123.data import ChipDataset
from sar_zero123.model.vae import reconstruct

__all__ = ["evaluate_reconstruction"]


@torch.no_grad()
def evaluate_reconstruction(
    vae: AutoencoderKL, dataset: ChipDataset, num_images: int, batch_size: int
) -> dict[str, float]:
    """Mean PSNR and SSIM (scikit-image, data range 1) of posterior-mode reconstructions.

    Returns:
        ``{"psnr_db", "ssim", "num_images"}``.
    """
    count = min(num_images, len(dataset))
    loader = DataLoader(torch.utils.data.Subset(dataset, range(count)), batch_size=batch_size)
    psnrs, ssims = [], []
    for batch in loader:
        images = batch["image"].to(vae.device)
        recon = reconstruct(vae, images).cpu().numpy()[:, 0].astype(np.float64)
        reference = batch["image"].numpy()[:, 0].astype(np.float64)
        for a, b in zip(reference, recon):
            psnrs.append(peak_signal_noise_ratio(a, b, data_range=1.0))
            ssims.append(structural_similarity(a, b, data_range=1.0))
    return {"psnr_db": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "num_images": count}
