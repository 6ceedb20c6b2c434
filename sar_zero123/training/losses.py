"""Training losses: the x0 estimate (Eq. 19), L_simple, where PFM applies and the total loss (Eq. 21).
PFM itself (Eq. 20) and its frozen encoders are :mod:`sar_zero123.training.pfm`. Losses are ``(B,)``.

For epsilon prediction Eq. (19) divides by ``sqrt(abar_t)``, amplifying the noise-prediction error by
``1 / sqrt(SNR(t))``, which is unbounded on zero-terminal-SNR schedules. :func:`estimate_x0` therefore
floors ``abar_t`` at ``2**-24`` (diffusers' EulerDiscreteScheduler's value), and :func:`total_loss` computes
PFM only where ``SNR(t) >= pfm_min_snr``; the default keeps every timestep of the paper's ``scaled_linear``
schedule and drops PFM only where other schedules go far noisier.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from sar_zero123.config import check_minimum
from sar_zero123.training.pfm import pfm_loss

#: Floor on ``abar_t`` in the epsilon x0 estimate; keeps ``1 / sqrt(abar_t)`` at most 4096.
MIN_ALPHA_CUMPROD = 2.0**-24

#: SNR below which PFM is skipped; keeps every timestep of the paper's scaled_linear schedule.
DEFAULT_PFM_MIN_SNR = 0.004

#: What a diffusers scheduler's ``prediction_type`` may be (the paper: epsilon).
PREDICTION_TYPES = ("epsilon", "v_prediction", "sample")
#: The prediction types a model of this package is trained with.
TRAINED_PREDICTION_TYPES = ("epsilon", "v_prediction")


def check_prediction_type(
    prediction_type: str, allowed: tuple[str, ...] = PREDICTION_TYPES, name: str = "prediction_type"
) -> str:
    """The one check of a prediction type, wherever it is set or read; returns it unchanged. ``name`` is how
    the error names it.

    Raises:
        ValueError: If ``prediction_type`` is not one of ``allowed``.
    """
    if prediction_type not in allowed:
        choices = " or ".join(f"{value!r}" for value in allowed)
        if len(allowed) > 2:
            choices = ", ".join(f"{value!r}" for value in allowed[:-1]) + f" or {allowed[-1]!r}"
        raise ValueError(f"{name} must be {choices}, got {prediction_type!r}")
    return prediction_type


def append_dims(values: torch.Tensor, target_ndim: int) -> torch.Tensor:
    """Append trailing singleton dimensions so per-sample values broadcast against a batch tensor.

    Shape:
        ``(B,) -> (B, 1, ..., 1)`` with ``target_ndim`` dimensions.

    Raises:
        ValueError: If ``values`` already has more than ``target_ndim`` dimensions.
    """
    missing = target_ndim - values.ndim
    if missing < 0:
        raise ValueError(f"values has {values.ndim} dims, more than target_ndim={target_ndim}")
    return values[(...,) + (None,) * missing]


def _alphas_cumprod_at(scheduler, timesteps: torch.Tensor) -> torch.Tensor:
    """``abar_t`` of a diffusers scheduler at integer timesteps, float32 on the timesteps' device."""
    if timesteps.dtype.is_floating_point:
        raise ValueError(f"timesteps must be integer, got dtype {timesteps.dtype}")
    alphas_cumprod = scheduler.alphas_cumprod.to(device=timesteps.device, dtype=torch.float32)
    num_train_timesteps = alphas_cumprod.shape[0]
    if timesteps.numel() and (int(timesteps.min()) < 0 or int(timesteps.max()) >= num_train_timesteps):
        raise ValueError(f"timesteps must lie in [0, {num_train_timesteps - 1}], got "
                         f"[{int(timesteps.min())}, {int(timesteps.max())}]")
    return alphas_cumprod[timesteps]


def signal_to_noise_ratio(scheduler, timesteps: torch.Tensor) -> torch.Tensor:
    """SNR(t) = abar_t / (1 - abar_t) of a diffusers scheduler, float32 (``inf`` at abar_t = 1).

    Shape:
        ``(B,) -> (B,)``.

    Raises:
        ValueError: If the timesteps are not integers in ``[0, num_train_timesteps)``.
    """
    alphas_cumprod = _alphas_cumprod_at(scheduler, timesteps)
    return alphas_cumprod / (1.0 - alphas_cumprod)


def estimate_x0(
    x_t: torch.Tensor,
    model_output: torch.Tensor,
    timesteps: torch.Tensor,
    scheduler,
) -> torch.Tensor:
    """One-step estimate of the clean latent from the network output, Eq. (19).

    ``epsilon``: ``x0 = x_t / sqrt(abar_t) - sqrt(1 / abar_t - 1) * eps`` with ``abar_t`` floored at
    :data:`MIN_ALPHA_CUMPROD`; ``v_prediction``: ``x0 = sqrt(abar_t) * x_t - sqrt(1 - abar_t) * v``;
    ``sample``: the output itself. Computed in float32, returned in ``model_output``'s dtype so gradients
    reach the network in its own precision.

    Shape:
        ``x_t``, ``model_output``: ``(B, C, h, w)``; ``timesteps``: ``(B,)``; returns ``(B, C, h, w)``.

    Raises:
        ValueError: On mismatched shapes, bad timesteps or an unknown prediction type.
    """
    if x_t.shape != model_output.shape:
        raise ValueError(f"x_t {tuple(x_t.shape)} and model_output {tuple(model_output.shape)} differ")
    if timesteps.shape != (x_t.shape[0],):
        raise ValueError(f"timesteps must have shape ({x_t.shape[0]},), got {tuple(timesteps.shape)}")
    prediction_type = check_prediction_type(
        scheduler.config.prediction_type, name="scheduler.config.prediction_type"
    )
    if prediction_type == "sample":
        return model_output
    alphas_cumprod = append_dims(_alphas_cumprod_at(scheduler, timesteps), x_t.ndim)
    x_t32, output32 = x_t.float(), model_output.float()
    if prediction_type == "epsilon":
        alphas_cumprod = alphas_cumprod.clamp(min=MIN_ALPHA_CUMPROD)
        x0 = (x_t32 - (1.0 - alphas_cumprod).sqrt() * output32) / alphas_cumprod.sqrt()
    else:  # v_prediction
        x0 = alphas_cumprod.sqrt() * x_t32 - (1.0 - alphas_cumprod).sqrt() * output32
    return x0.to(model_output.dtype)


def denoising_target(latents: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor,
                     scheduler) -> torch.Tensor:
    """Regression target of L_simple: the noise (epsilon), the velocity (v) or the latents (sample).

    Shape:
        ``(B, C, h, w)``.
    """
    prediction_type = check_prediction_type(
        scheduler.config.prediction_type, name="scheduler.config.prediction_type"
    )
    if prediction_type == "epsilon":
        return noise
    if prediction_type == "v_prediction":
        return scheduler.get_velocity(latents, noise, timesteps)
    return latents  # sample


def denoising_loss(model_output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_simple: per-sample mean squared error between network output and target, in float32.

    Shape:
        ``(B, ...) -> (B,)``.

    Raises:
        ValueError: If the shapes differ.
    """
    if model_output.shape != target.shape:
        raise ValueError(f"model_output {tuple(model_output.shape)} and target {tuple(target.shape)} differ")
    return F.mse_loss(model_output.float(), target.float(), reduction="none").flatten(1).mean(dim=1)


def pfm_timestep_mask(timesteps: torch.Tensor, scheduler,
                      min_snr: float = DEFAULT_PFM_MIN_SNR) -> torch.Tensor:
    """Samples whose timestep is informative enough for PFM: ``SNR(t) >= min_snr`` (0 keeps every one).

    Shape:
        ``(B,) -> (B,)``.

    Raises:
        ValueError: If ``min_snr`` is negative.
    """
    if min_snr < 0:
        raise ValueError(f"min_snr must be >= 0, got {min_snr}")
    return signal_to_noise_ratio(scheduler, timesteps) >= min_snr


@dataclass
class LossSettings:
    """Everything that shapes the loss of a training step, declared once and passed whole to
    :func:`~sar_zero123.training.step.compute_losses`; ``FinetuneConfig`` inherits these fields.

    The defaults are the paper's (lambda = 4); ``LossSettings(pfm_weight=0.0)`` is zero-1-to-3's loss.

    Raises:
        ValueError: Naming the first field out of range.
    """

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "pfm_min_snr", "pfm_fraction", "drop_image_prob", "drop_both_prob", "drop_latent_prob", "snr_gamma",
        "azimuth_loss_weight", "proxy_runner_up_prob", "proxy_oracle_prob",
    )  # fmt: skip

    pfm_weight: float = 4.0  # lambda of Eq. (21) (paper: 4); 0 = plain zero-1-to-3 fine-tuning (no PFM)
    pfm_min_snr: float = DEFAULT_PFM_MIN_SNR  # PFM only where SNR(t) >= this (0 = every timestep)
    pfm_fraction: float = 1.0  # fraction in (0, 1] of the eligible samples on which PFM is computed
    drop_image_prob: float = 0.05  # CFG dropout: image embedding only (pose kept)
    drop_both_prob: float = 0.05  # CFG dropout: projected token and condition latent (the sampling null)
    drop_latent_prob: float = 0.05  # CFG dropout: condition latent only
    snr_gamma: float | None = None  # Min-SNR-gamma weighting of L_simple (e.g. 5); None: the paper's L_simple
    azimuth_loss_weight: float = 1.0  # weight of an azimuth estimator's loss on the input's known azimuth
    # a spatial_pose="proxy" model: share of the pairs given a runner-up proxy instead of the best fit
    proxy_runner_up_prob: float = 0.25
    # share of the pairs given the vehicle itself as its proxy (proxies written with oracle=True), so that the
    # UNet learns when to trust a proxy and when the input must supply what differs
    proxy_oracle_prob: float = 0.0

    def __post_init__(self) -> None:
        check_minimum(self, "pfm_weight", "pfm_min_snr", "azimuth_loss_weight", minimum=0)
        proxy_probs = (self.proxy_runner_up_prob, self.proxy_oracle_prob)
        if not (min(proxy_probs) >= 0 and sum(proxy_probs) <= 1):
            raise ValueError(
                f"proxy_runner_up_prob, proxy_oracle_prob must be >= 0 with sum <= 1, got {proxy_probs}"
            )
        if not 0 < self.pfm_fraction <= 1:
            raise ValueError(f"pfm_fraction must be in (0, 1], got {self.pfm_fraction}")
        probs = (self.drop_image_prob, self.drop_both_prob, self.drop_latent_prob)
        if not (min(probs) >= 0 and sum(probs) <= 1):
            raise ValueError(
                f"drop_image_prob, drop_both_prob, drop_latent_prob must be >= 0 with sum <= 1, got {probs}"
            )
        check_minimum(self, "snr_gamma", minimum=0, strict=True, optional=True)


@dataclass
class LossOutput:
    """Per-sample losses of one training step (all ``(B,)`` float32).

    Attributes:
        loss: ``denoising + pfm_weight * pfm`` (Eq. 21), plus the weighted azimuth loss if any.
        denoising: L_simple (Min-SNR weighted when asked).
        pfm: L_PFM, zero where not computed; sampled entries are scaled by ``B_eligible / B_sampled`` so the
            batch mean stays unbiased.
        pfm_mask: Where PFM was computed.
        timesteps: The sampled timesteps, when the caller records them.
        azimuth: The input-azimuth estimation loss of a model with an azimuth estimator.
    """

    loss: torch.Tensor
    denoising: torch.Tensor
    pfm: torch.Tensor
    pfm_mask: torch.Tensor
    timesteps: torch.Tensor | None = None
    azimuth: torch.Tensor | None = None


def total_loss(
    model_output: torch.Tensor,
    target: torch.Tensor,
    x_t: torch.Tensor,
    timesteps: torch.Tensor,
    scheduler,
    *,
    pfm_weight: float,
    target_images: torch.Tensor | None = None,
    vae=None,
    encoder: nn.Module | None = None,
    pfm_min_snr: float = DEFAULT_PFM_MIN_SNR,
    pfm_fraction: float = 1.0,
    generator: torch.Generator | None = None,
    denoising_weights: torch.Tensor | None = None,
) -> LossOutput:
    """L = L_simple + lambda * L_PFM, Eq. (21), the only place it is assembled.

    ``pfm_weight = 0`` is plain zero-1-to-3 fine-tuning and skips every PFM computation.

    Args:
        target: L_simple target (:func:`denoising_target`).
        target_images: Real target views, normalised dB; with ``vae`` and ``encoder``, needed when
            ``pfm_weight > 0``.
        pfm_fraction: Fraction in (0, 1] of the eligible samples given PFM (at least one), drawn with
            ``generator``.
        denoising_weights: Optional per-sample weights of L_simple (Min-SNR-gamma).

    Shape:
        ``model_output``, ``target``, ``x_t``: ``(B, C, h, w)``; ``timesteps``: ``(B,)``; outputs ``(B,)``.

    Raises:
        ValueError: On a bad ``pfm_weight`` or ``pfm_fraction``, or missing PFM inputs.
    """
    if not pfm_weight >= 0:
        raise ValueError(f"pfm_weight must be >= 0, got {pfm_weight}")
    if not 0 < pfm_fraction <= 1:
        raise ValueError(f"pfm_fraction must be in (0, 1], got {pfm_fraction}")
    denoising = denoising_loss(model_output, target)
    if denoising_weights is not None:
        denoising = denoising * denoising_weights
    pfm = torch.zeros_like(denoising)
    mask = torch.zeros_like(denoising, dtype=torch.bool)
    if pfm_weight > 0:
        if target_images is None or vae is None or encoder is None:
            raise ValueError("pfm_weight > 0 needs target_images, vae and encoder")
        eligible = pfm_timestep_mask(timesteps, scheduler, pfm_min_snr).nonzero().flatten()
        num_eligible = eligible.numel()
        if num_eligible:
            keep = max(1, math.ceil(pfm_fraction * num_eligible))
            if keep < num_eligible:
                order = torch.randperm(eligible.numel(), generator=generator, device="cpu")
                eligible = eligible[order[:keep].to(eligible.device)]
            mask[eligible] = True
            x0_hat = estimate_x0(x_t[eligible], model_output[eligible], timesteps[eligible], scheduler)
            values = pfm_loss(x0_hat, target_images[eligible], vae, encoder)
            pfm = pfm.index_put((eligible,), values * (num_eligible / keep))
    return LossOutput(loss=denoising + pfm_weight * pfm, denoising=denoising, pfm=pfm, pfm_mask=mask)
