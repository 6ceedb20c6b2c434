"""The zero-1-to-3 training step: per-micro-batch randomness, CFG dropout, frozen encodings, losses (Eq. 21).

The fine-tune stage only assembles a run around these pieces. Every random draw of a micro-batch comes
from :func:`micro_batch_generator`, which makes resuming bitwise exact; cached frozen encodings are
:mod:`sar_zero123.training.latent_cache`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Sequence

import numpy as np
import torch
from diffusers import AutoencoderKL, DDPMScheduler
from diffusers.training_utils import compute_snr
from transformers import CLIPVisionModelWithProjection

from sar_zero123.model.conditioning import embed_pose, encode_image_embeddings, pose_class_labels, vae_input
from sar_zero123.model.input_tokens import input_token_context
from sar_zero123.model.orientation import azimuth_estimation_loss, target_view_features
from sar_zero123.model.reference_attention import (
    attending_to_reference,
    input_reference,
    own_pose,
    reference_weights,
    uses_reference,
)
from sar_zero123.model.spatial_pose import takes_proxy, unet_condition_latents
from sar_zero123.training.losses import (
    TRAINED_PREDICTION_TYPES,
    LossOutput,
    LossSettings,
    check_prediction_type,
    denoising_target,
    total_loss,
)

__all__ = [
    "MAX_GRAD_NORM",
    "ImageEmbedder",
    "cfg_dropout_masks",
    "compute_losses",
    "conditioning_sensitivity",
    "dropped_conditioning",
    "encode_batch",
    "micro_batch_generator",
    "min_snr_weights",
    "timestep_bucket_losses",
]

#: Every training stage clips the norm of all its trained parameters' gradients, together, to this.
MAX_GRAD_NORM = 1.0


def micro_batch_generator(seed: int, batch_index: int, process_index: int) -> torch.Generator:
    """CPU generator for every random draw of one micro-batch; a pure function of its arguments."""
    state = np.random.SeedSequence([seed, batch_index, process_index]).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))


class ImageEmbedder(torch.nn.Module):
    """The CLIP image tower as one module whose forward is :func:`encode_image_embeddings`.

    ``accelerate.prepare`` (DDP, autocast) acts only on a prepared module's ``forward``, and the preprocessing
    reads the tower's ``config``, ``device`` and ``dtype``, which a DDP wrapper hides: so it runs in here.

    Shape:
        ``(B, 1 | 3, H, W)`` normalised dB in [0, 1] -> ``(B, 1, projection_dim)``.
    """

    def __init__(self, image_encoder: CLIPVisionModelWithProjection) -> None:
        super().__init__()
        self.image_encoder = image_encoder

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return encode_image_embeddings(self.image_encoder, images)


def cfg_dropout_masks(
    batch_size: int,
    *,
    drop_image_prob: float,
    drop_both_prob: float,
    drop_latent_prob: float,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """zero-1-to-3's classifier-free-guidance dropout, one uniform draw per sample.

    The three cases are disjoint: the image embedding only (pose kept), both the projected token and the
    condition latent (the pipeline's sampling null), the condition latent only.

    Returns:
        Boolean masks ``(drop_image, drop_both, drop_latent)``, each ``(B,)`` on the CPU.

    Raises:
        ValueError: If a probability is negative or they sum to more than 1.
    """
    probs = (drop_image_prob, drop_both_prob, drop_latent_prob)
    if min(probs) < 0 or sum(probs) > 1:
        raise ValueError(f"CFG dropout probabilities must be >= 0 with sum <= 1, got {probs}")
    u = torch.rand(batch_size, generator=generator)
    drop_image = u < drop_image_prob
    drop_both = (u >= drop_image_prob) & (u < drop_image_prob + drop_both_prob)
    drop_latent = (u >= drop_image_prob + drop_both_prob) & (u < sum(probs))
    return drop_image, drop_both, drop_latent


# ------------------------------------------------------------------------------------------ the step
def encode_batch(
    batch: dict,
    *,
    vae: AutoencoderKL,
    image_encoder: torch.nn.Module,
    generator: torch.Generator | None = None,
    input_depression: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The conditioning and the diffusion target of a pair batch, from its cached encodings or the models.

    With ``input_depression`` the pose's fourth entry is the input chip's absolute depression.

    Returns:
        ``(latents, condition_latents, image_embeds, pose)``: the scaled posterior sample of the target
        (drawn from ``generator``), the unscaled posterior mode of the input, its CLIP embedding and the
        pose vector (Eq. 9), all float32.

    Shape:
        ``(B, C, h, w)``, ``(B, C, h, w)``, ``(B, 1, D)``, ``(B, 1, 4)``.
    """
    device, dtype = vae.device, vae.dtype
    inputs = batch["input"].to(device=device, dtype=dtype)
    if "target_latent_mean" in batch:
        mean = batch["target_latent_mean"].to(device=device, dtype=torch.float32)
        logvar = batch["target_latent_logvar"].to(device=device, dtype=torch.float32)
        std = torch.exp(0.5 * logvar.clamp(-30.0, 20.0))  # diffusers' DiagonalGaussianDistribution clamp
        sample = mean + std * torch.randn(mean.shape, generator=generator).to(device)
        latents = sample * vae.config.scaling_factor
        condition_latents = batch["input_latent_mean"].to(device=device, dtype=torch.float32)
    else:
        targets = batch["target"].to(device=device, dtype=dtype)
        with torch.no_grad():
            posterior = vae.encode(vae_input(vae, targets)).latent_dist
            latents = (posterior.sample(generator=generator) * vae.config.scaling_factor).float()
            condition_latents = vae.encode(vae_input(vae, inputs)).latent_dist.mode().float()
    if "input_image_embeds" in batch:
        image_embeds = batch["input_image_embeds"].to(device=device, dtype=torch.float32)
    else:
        image_embeds = image_encoder(inputs).float()  # (B, 1, D)
    depression = batch["input_depression_deg"] if input_depression else None
    pose = embed_pose(batch["d_az_deg"], batch["d_el_deg"], depression).to(device)  # (B, 1, 4)
    return latents, condition_latents, image_embeds, pose


def chosen_proxy_latents(
    batch: dict,
    pose_projection: torch.nn.Module,
    runner_up_prob: float,
    generator: torch.Generator | None = None,
    oracle_prob: float = 0.0,
) -> torch.Tensor | None:
    """Each pair's proxy pair for a ``spatial_pose="proxy"`` model: the best-fitted candidate, or with
    probability ``runner_up_prob`` a runner-up, so that the UNet learns to transfer the proxy's change rather
    than copy it; with ``oracle_prob`` the vehicle itself (the last candidate, written with ``oracle=True``).

    Returns:
        ``(B, 2C, h, w)`` from ``batch["proxy_latents"]`` ``(B, K, 2C, h, w)``, or ``None`` for another model.

    Raises:
        ValueError: If a proxy model's batch has no ``proxy_latents``.
    """
    if not takes_proxy(pose_projection):
        return None
    if "proxy_latents" not in batch:
        raise ValueError(
            "batch: a spatial_pose='proxy' model trains on cached pairs with each chip's proxies "
            "(ChipLatentCache.encode(..., proxy_images=...)); this batch has no `proxy_latents`"
        )
    proxies = batch["proxy_latents"]
    size, candidates = proxies.shape[:2]
    fitted = candidates - int(oracle_prob > 0)  # the fitted candidates come first, the oracle last
    if fitted < 1:
        raise ValueError("batch: proxy_oracle_prob > 0 needs the fitted proxies and the oracle (K >= 2)")
    u = torch.rand(size, generator=generator)
    pick = torch.randint(1, max(fitted, 2), (size,), generator=generator)
    runner_up = (u >= oracle_prob) & (u < oracle_prob + runner_up_prob) & (fitted > 1)
    choice = torch.where(runner_up, pick, torch.zeros_like(pick))
    if oracle_prob > 0:
        choice = torch.where(u < oracle_prob, torch.full_like(pick, candidates - 1), choice)
    return proxies[torch.arange(size), choice.to(proxies.device)].float()


def uses_input_depression(pose_projection: torch.nn.Module) -> bool:
    """Whether a (possibly DDP-wrapped) :class:`PoseProjection` takes the input's absolute depression."""
    config = getattr(pose_projection, "module", pose_projection).config
    return bool(getattr(config, "input_depression", False))


@torch.no_grad()
def conditioning_sensitivity(
    batch: dict,
    *,
    unet: torch.nn.Module,
    pose_projection: torch.nn.Module,
    vae: AutoencoderKL,
    image_encoder: torch.nn.Module,
    noise_scheduler: DDPMScheduler,
    timesteps: Sequence[int] = (100, 500, 900),
    seed: int = 0,
    azimuth_estimator: torch.nn.Module | None = None,
) -> dict[str, float]:
    """How much the UNet's prediction depends on the pose and on the input view.

    At each timestep, the relative L2 change of the prediction on the same noisy latents when every ``d_az``
    turns by 180 degrees (``pose_t<t>``) and when the input views are swapped between pairs (``input_t<t>``).
    A model that ignores its conditioning scores ~0 on both.

    Raises:
        ValueError: If the batch holds fewer than two pairs.
    """
    if batch["input"].shape[0] < 2:
        raise ValueError("conditioning_sensitivity needs a batch of at least 2 pairs")
    generator = torch.Generator().manual_seed(seed)
    input_depression = uses_input_depression(pose_projection)
    latents, condition, embeds, pose = encode_batch(
        batch, vae=vae, image_encoder=image_encoder, generator=generator, input_depression=input_depression
    )
    proxy_latents = chosen_proxy_latents(batch, pose_projection, 0.0)
    if proxy_latents is not None:
        proxy_latents = proxy_latents.to(condition.device)
    depression = batch["input_depression_deg"] if input_depression else None
    turned = embed_pose(torch.as_tensor(batch["d_az_deg"]) + 180.0, batch["d_el_deg"], depression)
    turned = turned.to(pose.device)
    noise = torch.randn(latents.shape, generator=generator).to(latents.device)

    def predict(t: torch.Tensor, condition: torch.Tensor, embeds: torch.Tensor, pose: torch.Tensor):
        x_t = noise_scheduler.add_noise(latents, noise, t)
        tokens = pose_projection(embeds, pose)
        target_features = None
        if azimuth_estimator is not None:
            target_features = target_view_features(azimuth_estimator(condition), pose)
        return unet(
            torch.cat([x_t, unet_condition_latents(condition, pose, pose_projection, proxy_latents)], dim=1),
            t,
            encoder_hidden_states=tokens,
            class_labels=pose_class_labels(unet, pose, target_features),
        ).sample

    result = {}
    for step in timesteps:
        t = torch.full((latents.shape[0],), int(step), dtype=torch.long, device=latents.device)
        reference = predict(t, condition, embeds, pose)
        norm = reference.norm().clamp_min(1e-12)
        result[f"pose_t{step}"] = ((predict(t, condition, embeds, turned) - reference).norm() / norm).item()
        swapped = predict(t, condition.roll(1, 0), embeds.roll(1, 0), pose)
        result[f"input_t{step}"] = ((swapped - reference).norm() / norm).item()
    return result


def dropped_conditioning(
    image_embeds: torch.Tensor,
    condition_latents: torch.Tensor,
    pose: torch.Tensor,
    *,
    pose_projection: torch.nn.Module,
    settings: LossSettings,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The UNet's conditioning after zero-1-to-3's CFG dropout (:func:`cfg_dropout_masks`, one draw).

    Returns:
        ``(tokens, condition_latents)``.

    Shape:
        ``(B, 1, D)``, ``(B, C, h, w)``, ``(B, 1, 4)`` -> ``(B, 1, C_cross)``, ``(B, C, h, w)``.
    """
    drop_image, drop_both, drop_latent = (
        mask.to(pose.device)
        for mask in cfg_dropout_masks(
            pose.shape[0],
            drop_image_prob=settings.drop_image_prob,
            drop_both_prob=settings.drop_both_prob,
            drop_latent_prob=settings.drop_latent_prob,
            generator=generator,
        )
    )
    image_embeds = image_embeds * (~drop_image).float()[:, None, None]
    tokens = pose_projection(image_embeds, pose) * (~drop_both).float()[:, None, None]  # (B, 1, C)
    return tokens, condition_latents * (~(drop_both | drop_latent)).float()[:, None, None, None]


def compute_losses(
    batch: dict,
    *,
    unet: torch.nn.Module,
    pose_projection: torch.nn.Module,
    vae: AutoencoderKL,
    image_encoder: torch.nn.Module,
    encoder: torch.nn.Module | None,
    noise_scheduler: DDPMScheduler,
    generator: torch.Generator,
    loss_settings: LossSettings | None = None,
    apply_dropout: bool = True,
    azimuth_estimator: torch.nn.Module | None = None,
    timesteps: torch.Tensor | None = None,
) -> LossOutput:
    """Per-sample losses of one micro-batch (zero-1-to-3 conditioning, CFG dropout, Eq. 21).

    The UNet sees ``[x_t, condition latent]`` (the input's unscaled posterior mode) and cross-attends to
    ``pose_projection([CLIP image embedding, pose])``; cached encodings in ``batch`` replace the VAE and a
    frozen ``image_encoder``. ``loss_settings`` (``None``: zero-1-to-3 without PFM) sets everything about the
    loss; CFG dropout is skipped without ``apply_dropout`` (validation). An ``azimuth_estimator`` reads the
    input's azimuth from its condition latent, feeds the UNet's timestep embedding and adds its weighted loss
    against ``batch["input_azimuth_deg"]``. ``timesteps`` replaces the sampled ones, for diagnostics.

    Raises:
        ValueError: If an azimuth estimator's batch has no ``input_azimuth_deg``, or ``timesteps`` is not
            one integer per sample.

    Shape:
        ``batch["input"]``, ``batch["target"]``: ``(B, 1, S, S)``; outputs ``(B,)``.
    """
    settings = loss_settings if loss_settings is not None else LossSettings(pfm_weight=0.0)
    # 1. frozen encodings (a fresh posterior sample of the target latent)
    latents, condition_latents, image_embeds, pose = encode_batch(
        batch, vae=vae, image_encoder=image_encoder, generator=generator,
        input_depression=uses_input_depression(pose_projection),
    )  # fmt: skip
    proxy_latents = chosen_proxy_latents(
        batch, pose_projection, settings.proxy_runner_up_prob, generator, settings.proxy_oracle_prob
    )
    if proxy_latents is not None:
        proxy_latents = proxy_latents.to(condition_latents.device)
    target_features = azimuth_loss = estimate = None
    if azimuth_estimator is not None:
        if "input_azimuth_deg" not in batch:
            raise ValueError("batch: an azimuth estimator is trained on `input_azimuth_deg`, which it lacks")
        estimate = azimuth_estimator(condition_latents)  # before CFG dropout: like the pose, never dropped
        azimuth_loss = azimuth_estimation_loss(estimate, batch["input_azimuth_deg"])
        target_features = target_view_features(estimate, pose)
    input_latents = condition_latents
    # 2. classifier-free-guidance dropout
    if apply_dropout:
        tokens, condition_latents = dropped_conditioning(
            image_embeds, condition_latents, pose, pose_projection=pose_projection, settings=settings,
            generator=generator,
        )  # fmt: skip
    else:
        tokens = pose_projection(image_embeds, pose)  # (B, 1, C)
    reference = contextlib.nullcontext()
    if uses_reference(pose_projection):  # the input's own features; a dropped condition latent drops them
        own = own_pose(pose)
        own_features = None if estimate is None else target_view_features(estimate, own)
        features = input_reference(
            unet, pose_projection, input_latents, own, pose_projection(image_embeds, own),
            pose_class_labels(unet, own, own_features), vae.config.scaling_factor,
            None if proxy_latents is None else proxy_latents[:, : input_latents.shape[1]],
        )  # fmt: skip
        keep = condition_latents.flatten(1).abs().amax(dim=1) > 0  # (B,): False where dropout zeroed it
        rows = torch.arange(input_latents.shape[0], device=input_latents.device)
        reference = attending_to_reference(unet, features, rows, reference_weights(pose_projection, keep))
    input_tokens = input_token_context(unet, pose_projection, condition_latents, pose)
    # 3. forward diffusion and prediction
    noise = torch.randn(latents.shape, generator=generator).to(latents.device)
    # drawn even when replaced, so that the generator's later draws do not depend on it
    sampled = torch.randint(  # uniform, as DDPM's L_simple
        0, noise_scheduler.config.num_train_timesteps, (latents.shape[0],), generator=generator
    )
    if timesteps is None:
        timesteps = sampled
    elif timesteps.shape != sampled.shape or timesteps.is_floating_point() or timesteps.is_complex():
        raise ValueError(
            f"timesteps: expected {tuple(sampled.shape)} integers, got {tuple(timesteps.shape)} "
            f"{timesteps.dtype}"
        )
    timesteps = timesteps.to(latents.device)
    x_t = noise_scheduler.add_noise(latents, noise, timesteps)
    with reference, input_tokens:
        model_output = unet(
            torch.cat(
                [x_t, unet_condition_latents(condition_latents, pose, pose_projection, proxy_latents)], dim=1
            ),
            timesteps,
            encoder_hidden_states=tokens,
            class_labels=pose_class_labels(unet, pose, target_features),
        ).sample
    # 4. Eq. (21), L_simple optionally Min-SNR weighted
    weights = None
    if settings.snr_gamma is not None:
        weights = min_snr_weights(noise_scheduler, timesteps, settings.snr_gamma)
    losses = total_loss(
        model_output, denoising_target(latents, noise, timesteps, noise_scheduler), x_t, timesteps,
        noise_scheduler, pfm_weight=settings.pfm_weight,
        target_images=batch["target"].to(device=latents.device, dtype=vae.dtype), vae=vae, encoder=encoder,
        pfm_min_snr=settings.pfm_min_snr, pfm_fraction=settings.pfm_fraction, generator=generator,
        denoising_weights=weights,
    )  # fmt: skip
    if azimuth_loss is not None:
        losses = dataclasses.replace(
            losses, loss=losses.loss + settings.azimuth_loss_weight * azimuth_loss, azimuth=azimuth_loss
        )
    return dataclasses.replace(losses, timesteps=timesteps)


def min_snr_weights(noise_scheduler: DDPMScheduler, timesteps: torch.Tensor, gamma: float) -> torch.Tensor:
    """Min-SNR-gamma loss weights (Hang et al., 2023), as diffusers' training examples apply them.

    Epsilon L_simple weighs each sample's x0 error by SNR(t), so the loss sits at low noise (speckle) and
    barely at high noise, where the pose is decided. Min-SNR caps it: ``min(SNR, gamma) / SNR`` for epsilon,
    ``min(SNR, gamma) / (SNR + 1)`` for v prediction.

    Raises:
        ValueError: If ``gamma <= 0`` or the prediction type is not epsilon or v_prediction.

    Shape:
        ``(B,)`` float32, on the timesteps' device.
    """
    if not gamma > 0:
        raise ValueError(f"snr_gamma must be > 0, got {gamma}")
    snr = compute_snr(noise_scheduler, timesteps).float()
    capped = torch.clamp(snr, max=gamma)
    prediction_type = check_prediction_type(
        noise_scheduler.config.prediction_type,
        TRAINED_PREDICTION_TYPES,
        name="noise_scheduler.config.prediction_type (min-SNR weights)",
    )
    if prediction_type == "epsilon":
        return capped / snr
    return capped / (snr + 1)  # v_prediction


def timestep_bucket_losses(
    losses: torch.Tensor, timesteps: torch.Tensor, num_train_timesteps: int, num_buckets: int = 4
) -> dict[str, float]:
    """Mean per-sample loss in equal timestep buckets that hold a sample: ``{"t000-249": value, ...}``."""
    width = math.ceil(num_train_timesteps / num_buckets)
    result = {}
    for k in range(num_buckets):
        low, high = k * width, min((k + 1) * width, num_train_timesteps) - 1
        mask = (timesteps >= low) & (timesteps <= high)
        if mask.any():
            result[f"t{low:03d}-{high:03d}"] = losses[mask].float().mean().item()
    return result
