"""What :class:`~sar_zero123.model.pipeline.SARZero123Pipeline` refuses at its boundary, in one line each
naming the argument or component at fault: components that do not fit together, call arguments out of
range, input images of another rank, size or domain, generators and latents that do not fit the batch, a
step callback that hands back something else than latents, and outputs that are not finite.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import PIL.Image
import torch
from diffusers import AutoencoderKL, UNet2DConditionModel
from diffusers.schedulers.scheduling_utils import SchedulerMixin

from sar_zero123.model.conditioning import POSE_DIM, check_vae_signature, downsampling_factor
from sar_zero123.model.input_tokens import check_token_layers
from sar_zero123.model.orientation import estimator_weights_digest
from sar_zero123.model.reference_attention import check_reference_layers
from sar_zero123.model.sampler import MAX_GUIDANCE_SCALE, START_FROM, _check_strength
from sar_zero123.model.spatial_pose import condition_channels

__all__ = [
    "MAX_IMAGES_PER_PROMPT", "OUTPUT_TYPES", "ImageInput", "callback_latents", "check_call_arguments",
    "check_components", "check_finite_output", "check_generators", "check_latents", "check_vae_image_size",
    "image_batch",
]  # fmt: skip

#: Most samples per input image in one call: the call holds every sample's latents and conditions at once.
MAX_IMAGES_PER_PROMPT = 1024
ImageInput = PIL.Image.Image | np.ndarray | torch.Tensor | Sequence[PIL.Image.Image] | Sequence[np.ndarray]
OUTPUT_TYPES = ("pil", "np", "pt", "latent")


# ------------------------------------------------------------------------------------- components
def check_components(
    vae: Any, image_encoder: Any, unet: Any, scheduler: Any, pose_projection: Any, azimuth_estimator: Any
) -> None:
    """Refuse components that are not diffusers' kinds or do not fit together: the UNet's channels against
    the VAE's latents and the pose projection's spatial mode, the chip size, the reference layers, the VAE
    and azimuth estimator the UNet was trained beside, and the pose projection's widths.

    Raises:
        ValueError: Naming the component and both sizes.
    """
    for name, module, kind in (("scheduler", scheduler, SchedulerMixin), ("vae", vae, AutoencoderKL),
                               ("unet", unet, UNet2DConditionModel)):  # fmt: skip
        if not isinstance(module, kind):
            raise ValueError(f"`{name}` must be a diffusers {kind.__name__}, got {type(module).__name__}")
    latent_channels = vae.config.latent_channels
    spatial_pose = getattr(pose_projection.config, "spatial_pose", None)
    expected = latent_channels + condition_channels(spatial_pose, latent_channels)
    if unet.config.in_channels != expected:
        raise ValueError(
            f"`unet.config.in_channels` must be {expected}: the vae's {latent_channels} latent channels "
            f"(noisy latent) + {expected - latent_channels} condition channels (pose_projection "
            f"spatial_pose={spatial_pose!r}), got {unet.config.in_channels}"
        )
    if unet.config.out_channels != latent_channels:
        raise ValueError(
            f"`unet.config.out_channels` must be the vae's {latent_channels} latent channels, got "
            f"{unet.config.out_channels}: the unet and the vae come from different models"
        )
    check_vae_image_size(vae, unet)
    check_reference_layers(unet, pose_projection)
    check_token_layers(unet, pose_projection)
    check_vae_signature(vae.config, getattr(pose_projection.config, "trained_vae", None))
    trained_estimator = getattr(pose_projection.config, "trained_estimator", None)
    if trained_estimator is not None and azimuth_estimator is not None:
        digest = estimator_weights_digest(azimuth_estimator)
        if digest != trained_estimator:
            raise ValueError(
                f"`azimuth_estimator`: weights SHA-256 {digest[:12]}..., but the UNet was trained beside "
                f"the estimator {trained_estimator[:12]}... (pose_projection.config.trained_estimator): "
                "an estimator from another run reads azimuths the UNet never learned; use its own"
            )
    if pose_projection.config.in_features != image_encoder.config.projection_dim + POSE_DIM:
        raise ValueError(
            f"`pose_projection.config.in_features` must be image_encoder projection_dim + {POSE_DIM} = "
            f"{image_encoder.config.projection_dim + POSE_DIM}, got {pose_projection.config.in_features}"
        )
    if pose_projection.config.out_features != unet.config.cross_attention_dim:
        raise ValueError(
            f"`pose_projection.config.out_features` must equal unet cross_attention_dim "
            f"{unet.config.cross_attention_dim}, got {pose_projection.config.out_features}"
        )
    pose_inputs = getattr(unet.config, "projection_class_embeddings_input_dim", None) or POSE_DIM
    if unet.config.class_embed_type != "projection":
        pose_inputs = POSE_DIM
    estimated = 0 if azimuth_estimator is None else azimuth_estimator.output_dim
    if pose_inputs != POSE_DIM + estimated:
        raise ValueError(
            f"`azimuth_estimator` must be given exactly when the UNet's pose embedding takes more than "
            f"the {POSE_DIM} pose inputs, with as many outputs as the extra inputs: the UNet takes "
            f"{pose_inputs}, the azimuth_estimator gives {estimated}"
        )


def check_vae_image_size(vae: AutoencoderKL, unet: UNet2DConditionModel, name: str = "vae") -> None:
    """Refuse a VAE built for another chip size than the UNet: ``vae.config.sample_size`` (pixels) must be
    ``unet.config.sample_size`` (latent pixels) times the VAE's downsampling factor, or a VAE copied in
    from another model would silently change the size every view is made at.

    Raises:
        ValueError: Naming both sizes, if they differ.
    """
    factor = downsampling_factor(vae.config.block_out_channels)
    latent = unet.config.sample_size
    latent = latent[0] if isinstance(latent, list | tuple) else latent
    image = vae.config.sample_size
    image = image[0] if isinstance(image, list | tuple) else image
    if int(latent) * factor != int(image):
        raise ValueError(
            f"{name}: built for {image} px chips (vae.config.sample_size), but the unet works on "
            f"{latent}x{latent} latents, i.e. {int(latent) * factor} px with this vae's downsampling factor "
            f"{factor}: the vae comes from another model"
        )


# ----------------------------------------------------------------------------------------- images
def image_batch(image: ImageInput, size_multiple: int, vae_scale_factor: int) -> torch.Tensor:
    """Validate and convert pipeline input images to a float32 batch in the normalised dB domain
    (``SARZero123Pipeline.preprocess_image``).

    Accepted: a PIL image (modes ``L``, ``RGB``, ``I;16``, ``F``) or a list of them, a numpy array
    ``(H, W)`` / ``(H, W, C)`` or a list of them (float in [0, 1]; ``uint8`` is divided by 255), a
    tensor ``(B, 1 | 3, H, W)`` in [0, 1]; its height and width multiples of ``size_multiple``.

    Args:
        image: The input chip(s).
        size_multiple: The VAE's downsampling factor times the UNet's.
        vae_scale_factor: The VAE's downsampling factor (named in the message).

    Returns:
        The batch on the CPU.

    Shape:
        - Output: ``(B, 1 | 3, H, W)``

    Raises:
        ValueError: (naming ``image``) for an empty batch, a wrong rank or channel count, mixed sizes,
            non-finite or out-of-range values, or a size that is no multiple of ``size_multiple``.
    """
    if isinstance(image, torch.Tensor):
        if image.ndim != 4:
            raise ValueError(f"`image` tensors must be (B, 1 | 3, H, W), got shape {tuple(image.shape)}")
        if image.is_meta:
            raise ValueError("`image` is a tensor on the meta device, which holds no values")
        if image.is_complex():
            raise ValueError("`image` must be real normalised dB values, got a complex tensor")
        batch = image.detach().to("cpu", torch.float32)
    else:
        items = list(image) if isinstance(image, list | tuple) else [image]
        if not items:
            raise ValueError("`image` is an empty list")
        arrays = [_to_hwc_array(item) for item in items]
        if len({a.shape for a in arrays}) != 1:
            shapes = sorted({a.shape for a in arrays})
            raise ValueError(f"`image` items must share one shape, got {shapes}")
        batch = torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2)  # (B, C, H, W)
    # Standard strides whatever the source layout, so equal inputs give bit-equal outputs.
    batch = batch.clone(memory_format=torch.contiguous_format)
    if batch.shape[0] == 0:
        raise ValueError("`image` is an empty batch")
    if batch.shape[1] not in (1, 3):
        raise ValueError(f"`image` must have 1 or 3 channels, got {batch.shape[1]}")
    if not torch.isfinite(batch).all():
        raise ValueError("`image` contains NaN or inf values")
    low, high = float(batch.min()), float(batch.max())
    if low < 0.0 or high > 1.0:
        raise ValueError(f"`image` must lie in [0, 1] (normalised dB), got values in [{low:.4g}, {high:.4g}]")
    height, width = batch.shape[-2:]
    if height % size_multiple or width % size_multiple:
        raise ValueError(
            f"`image` height and width must be positive multiples of {size_multiple} (VAE factor "
            f"{vae_scale_factor} x UNet downsampling), got {height}x{width}"
        )
    return batch


def _to_hwc_array(item: PIL.Image.Image | np.ndarray) -> np.ndarray:
    """One PIL image or numpy array as float32 ``(H, W, C)`` without range checks (done by the caller)."""
    if isinstance(item, PIL.Image.Image):
        scale = {"L": 255.0, "RGB": 255.0, "I;16": 65535.0, "F": 1.0}.get(item.mode)
        if scale is None:
            raise ValueError(f"`image` PIL mode must be one of L, RGB, I;16, F, got {item.mode!r}")
        array = np.asarray(item, dtype=np.float32) / scale
    elif isinstance(item, np.ndarray):
        if item.dtype == np.uint8:
            array = item.astype(np.float32) / 255.0
        elif np.issubdtype(item.dtype, np.floating):
            array = item.astype(np.float32)
        else:
            raise ValueError(f"`image` arrays must be float (in [0, 1]) or uint8, got dtype {item.dtype}")
    else:
        raise ValueError(
            f"`image` must be a PIL image, numpy array or torch tensor, got {type(item).__name__}"
        )
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3:
        raise ValueError(f"`image` arrays must be (H, W) or (H, W, C), got shape {array.shape}")
    if array.size == 0:
        raise ValueError(f"`image` is empty, got shape {array.shape}")
    return array


# -------------------------------------------------------------------------------- call arguments
def check_call_arguments(
    sampler: Mapping[str, Any],
    num_images_per_prompt: int,
    output_type: str,
    callback_on_step_end_tensor_inputs: Sequence[str],
    callback_tensor_inputs: Sequence[str],
    scheduler: SchedulerMixin,
) -> None:
    """Refuse a call's sampler (:func:`~sar_zero123.model.sampler.resolve_sampler`'s values) and counts
    that the pipeline cannot run.

    Args:
        callback_tensor_inputs: The tensors a step callback may ask for.
        scheduler: The pipeline's; a call runs at most its ``num_train_timesteps`` steps.

    Raises:
        ValueError: Naming the argument and what was expected, for a value of another type (a boolean
            included) or out of range.
    """
    num_inference_steps, guidance_scale = sampler["num_inference_steps"], sampler["guidance_scale"]
    if not _is_integer(num_inference_steps) or num_inference_steps < 1:
        raise ValueError(f"`num_inference_steps` must be an integer >= 1, got {num_inference_steps!r}")
    # more steps than the schedule has timesteps repeat timesteps (or hang a loop of millions of steps)
    max_steps = int(getattr(scheduler.config, "num_train_timesteps", 1000))
    if num_inference_steps > max_steps:
        raise ValueError(
            f"`num_inference_steps` must be <= {max_steps} (the scheduler's num_train_timesteps), "
            f"got {num_inference_steps}"
        )
    if isinstance(guidance_scale, bool) or not isinstance(guidance_scale, numbers.Real):
        kind = type(guidance_scale).__name__
        raise ValueError(f"`guidance_scale` must be a real number, got {kind} {guidance_scale!r}")
    if not np.isfinite(guidance_scale):
        raise ValueError(f"`guidance_scale` must be finite, got {guidance_scale}")
    if guidance_scale > MAX_GUIDANCE_SCALE:  # the guided noise estimate overflows to NaN images
        raise ValueError(
            f"`guidance_scale` must be <= {MAX_GUIDANCE_SCALE} (zero-1-to-3 uses 3), got {guidance_scale}"
        )
    if guidance_scale < 0.0:  # a negative weight guides towards the unconditional view
        raise ValueError(f"`guidance_scale` must be >= 0 (<= 1 turns guidance off), got {guidance_scale}")
    if not _is_integer(num_images_per_prompt) or not 1 <= num_images_per_prompt <= MAX_IMAGES_PER_PROMPT:
        raise ValueError(
            f"`num_images_per_prompt` must be an integer in [1, {MAX_IMAGES_PER_PROMPT:,}], got "
            f"{num_images_per_prompt!r}"
        )
    if output_type not in OUTPUT_TYPES:
        raise ValueError(f"`output_type` must be one of {OUTPUT_TYPES}, got {output_type!r}")
    unknown = [k for k in callback_on_step_end_tensor_inputs if k not in callback_tensor_inputs]
    if unknown:
        raise ValueError(
            f"`callback_on_step_end_tensor_inputs` must be among {list(callback_tensor_inputs)}, "
            f"got {unknown}"
        )
    _check_strength(sampler["strength"], {"num_inference_steps": num_inference_steps})
    if sampler["start_from"] not in START_FROM:
        raise ValueError(f"`start_from` must be one of {START_FROM}, got {sampler['start_from']!r}")


def _is_integer(value: Any) -> bool:
    """An integer (Python's or numpy's) that is not a boolean."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_)


def check_generators(
    generator: torch.Generator | list[torch.Generator] | None, batch_size: int, num_images_per_prompt: int
) -> None:
    """One generator, or a list of one per output sample (``batch_size * num_images_per_prompt``).

    Raises:
        ValueError: For anything else, saying how to make a generator from a seed.
    """
    num_samples = batch_size * num_images_per_prompt
    generators = generator if isinstance(generator, list) else [generator]
    if generator is not None and not all(isinstance(g, torch.Generator) for g in generators):
        raise ValueError(
            "`generator` must be a torch.Generator or a list of them (one per output sample), got "
            f"{generator!r}; a seed s is torch.Generator().manual_seed(s)"
        )
    if isinstance(generator, list) and len(generator) != num_samples:
        raise ValueError(
            f"`generator` is a list of {len(generator)} generators; expected one per output sample, "
            f"batch {batch_size} x num_images_per_prompt {num_images_per_prompt} = {num_samples}"
        )


def check_latents(latents: Any, shape: tuple[int, ...]) -> None:
    """Given initial noise must be a floating-point tensor of the samples' latent shape, and finite.

    Raises:
        ValueError: Naming ``latents``.
    """
    if not isinstance(latents, torch.Tensor):
        raise ValueError(f"`latents` must be a torch.Tensor of shape {shape}, got {type(latents).__name__}")
    if not latents.is_floating_point():  # an integer, boolean or complex draw is no Gaussian noise
        raise ValueError(f"`latents` must be a floating-point tensor (Gaussian noise), got {latents.dtype}")
    if latents.is_meta:
        raise ValueError("`latents` is a tensor on the meta device, which holds no values")
    if tuple(latents.shape) != shape:
        raise ValueError(f"`latents` must have shape {shape}, got {tuple(latents.shape)}")
    if not torch.isfinite(latents).all():
        raise ValueError("`latents` contains NaN or inf values")


def callback_latents(outputs: Any, latents: torch.Tensor) -> torch.Tensor:
    """The latents a ``callback_on_step_end`` hands back: its ``"latents"`` entry, else the step's own.

    Raises:
        ValueError: For a callback that returns no dict, or latents of another shape or dtype.
    """
    if not isinstance(outputs, dict):
        raise ValueError(
            "`callback_on_step_end` must return a dict (callback_kwargs, or {} to change nothing), got "
            f"{type(outputs).__name__}"
        )
    new = outputs.pop("latents", latents)
    if not isinstance(new, torch.Tensor) or new.shape != latents.shape or new.dtype != latents.dtype:
        got = tuple(new.shape) if isinstance(new, torch.Tensor) else type(new).__name__
        raise ValueError(
            f"`callback_on_step_end` returned latents {got}; expected a tensor {tuple(latents.shape)} of "
            f"{latents.dtype}, as it was given"
        )
    return new


# ---------------------------------------------------------------------------------------- outputs
def check_finite_output(
    samples: torch.Tensor, what: str, guidance_scale: float, components: Mapping[str, torch.nn.Module | None]
) -> None:
    """Raise instead of returning samples with NaN or inf, saying which of ``components`` is at fault.

    Raises:
        FloatingPointError: Naming the components that hold non-finite weights, if any.
    """
    bad = ~torch.isfinite(samples.flatten(1)).all(dim=1)
    if not bad.any():
        return
    broken = [
        name
        for name, module in components.items()
        if module is not None and any(not torch.isfinite(p).all() for p in module.parameters())
    ]
    cause = (
        f"these components hold NaN/inf weights (a diverged training run?): {broken}"
        if broken
        else f"the weights are finite; guidance_scale={guidance_scale} or the inputs may be too extreme"
    )
    raise FloatingPointError(
        f"the pipeline produced non-finite {what} for {int(bad.sum())} of {len(bad)} samples; {cause}"
    )
