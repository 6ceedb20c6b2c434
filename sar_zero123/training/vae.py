"""The VAE's training objective (reconstruction + KL) and its loop."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from accelerate import Accelerator
from diffusers import AutoencoderKL
from torch.utils.data import DataLoader

from sar_zero123.domain import unit_to_signed
from sar_zero123.progress import progress_bar
from sar_zero123.runs.checkpoints import check_finite_step, resumable_batches, save_checkpoint
from sar_zero123.training.step import MAX_GRAD_NORM, micro_batch_generator

__all__ = ["VAEObjective", "train_vae_steps"]


class VAEObjective(torch.nn.Module):
    """``forward`` = per-sample VAE losses, so that data-parallel wrappers see one forward call.

    Args:
        kl_weight: Weight of the KL term (per-sample sum over latent elements).
        reconstruction_loss: ``"l1"`` or ``"l2"`` on the [-1, 1] images.
    """

    def __init__(self, vae: AutoencoderKL, kl_weight: float, reconstruction_loss: str) -> None:
        super().__init__()
        self.vae = vae
        self.kl_weight = kl_weight
        self.loss_fn = F.l1_loss if reconstruction_loss == "l1" else F.mse_loss

    def forward(
        self, images: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-sample ``(total, reconstruction)`` losses; ``generator`` draws the posterior sample.

        Shape:
            ``(B, 1, S, S)`` normalised dB ``-> ((B,), (B,))``.
        """
        pixels = unit_to_signed(images)
        posterior = self.vae.encode(pixels).latent_dist
        recon = self.vae.decode(posterior.sample(generator=generator)).sample
        reconstruction = self.loss_fn(recon.float(), pixels.float(), reduction="none").flatten(1).mean(dim=1)
        total = reconstruction + self.kl_weight * posterior.kl().float()
        return total, reconstruction


def train_vae_steps(
    config: Any,
    accelerator: Accelerator,
    objective: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    train_loader: DataLoader,
    global_step: int,
) -> int:
    """Steps ``global_step`` to ``config.max_train_steps`` of a ``TrainVAEConfig``, checkpointing; returns the
    last step. Posterior samples come from a generator seeded per step and process, so a run resumes exactly.
    """
    output_dir = Path(config.output_dir)
    progress = progress_bar(
        total=config.max_train_steps,
        initial=global_step,
        desc="steps",
        disable=not accelerator.is_local_main_process,
    )
    for step, _, batch in resumable_batches(accelerator, train_loader, global_step, config.max_train_steps):
        generator = micro_batch_generator(config.seed, step, accelerator.process_index)
        total, reconstruction = objective(batch["image"], generator=generator)
        accelerator.backward(total.mean())
        accelerator.clip_grad_norm_(objective.parameters(), MAX_GRAD_NORM)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        global_step = step + 1
        progress.update(1)
        loss = accelerator.gather(reconstruction.detach()).mean().item()
        progress.set_postfix(reconstruction=f"{loss:.4f}")
        accelerator.log({"train/reconstruction": loss}, step=global_step)
        check_finite_step(global_step, loss=accelerator.gather(total.detach()).mean())
        if global_step % config.checkpointing_steps == 0 or global_step == config.max_train_steps:
            save_checkpoint(
                accelerator, output_dir, global_step, config.checkpoints_total_limit, config=config
            )
    progress.close()
    return global_step
