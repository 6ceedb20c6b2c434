"""`SARZero123Pipeline`: novel views of a SAR chip at a requested relative pose (zero-1-to-3 sampling).

The UNet takes the noisy latent concatenated with the input's unscaled VAE posterior mode and
cross-attends to one token, ``PoseProjection([clip_image_embedding, pose])``; classifier-free guidance
zeroes both for the unconditional branch, all branches in one batched UNet call. ``__call__`` runs in
numbered stages that delegate, as diffusers' Stable Diffusion pipeline does.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import diffusers
import numpy as np
import PIL.Image
import torch
from diffusers import AutoencoderKL, DiffusionPipeline, UNet2DConditionModel
from diffusers.callbacks import MultiPipelineCallbacks, PipelineCallback
from diffusers.schedulers.scheduling_utils import SchedulerMixin
from diffusers.utils import BaseOutput
from diffusers.utils.torch_utils import randn_tensor
from transformers import CLIPVisionModelWithProjection

from sar_zero123.domain import signed_to_unit
from sar_zero123.model.conditioning import (
    PoseProjection,
    downsampling_factor,
    encode_condition_latents,
    encode_image_embeddings,
    match_channels,
)
from sar_zero123.model.guidance import BranchEncoder, GuidedCondition, contrast_branches, guided_condition
from sar_zero123.model.orientation import AzimuthEstimator
from sar_zero123.model.pipeline_checks import (
    ImageInput,
    callback_latents,
    check_call_arguments,
    check_components,
    check_finite_output,
    check_generators,
    check_latents,
    image_batch,
)
from sar_zero123.model.pipeline_loading import PipelineLoadingMixin, anchored_proxy, check_recorded_settings
from sar_zero123.model.proxy import fit_scores, proxy_drafts, proxy_latents
from sar_zero123.model.sampler import (
    SAMPLER_DEFAULTS,
    START_FROM,
    _check_contrast_scales,
    check_sampler_start,
    resolve_sampler,
)
from sar_zero123.model.spatial_pose import proxy_form, rotate_condition_latents, takes_proxy
from sar_zero123.model.view_request import (
    MAX_ABS_D_AZ_DEG,
    MAX_ABS_D_EL_DEG,
    ViewRequest,
    per_input_angles,
    view_request,
)
from sar_zero123.model.zero123_checkpoints import CLIPImageProcessor
from sar_zero123.progress import progress_bar as _progress_bar

__all__ = [
    "MAX_ABS_D_AZ_DEG", "MAX_ABS_D_EL_DEG", "SAMPLER_DEFAULTS", "START_FROM", "SARZero123Pipeline",
    "SARZero123PipelineOutput", "check_sampler_start",
]  # fmt: skip


@dataclass
class SARZero123PipelineOutput(BaseOutput):
    """Output of :class:`SARZero123Pipeline`.

    Args:
        images: Normalised dB views, ``B * num_images_per_prompt``, grouped by input: single-channel PIL
            images (``"pil"``), ``(N, H, W, 1)`` float32 (``"np"``), ``(N, 1, H, W)`` (``"pt"``) or the
            final latents (``"latent"``).
        proxy_fit_scores: ``(B,)`` each fitted proxy's score (:func:`~sar_zero123.model.proxy.fit_scores`),
            or ``None`` where no fit ran.
    """

    images: list[PIL.Image.Image] | np.ndarray | torch.Tensor
    proxy_fit_scores: np.ndarray | None = None


class SARZero123Pipeline(PipelineLoadingMixin, DiffusionPipeline):
    """Novel-view synthesis of SAR chips with a zero-1-to-3 latent diffusion model.

    Args:
        vae: Autoencoder taking 1 (SAR) or 3 (Stable Diffusion) channels.
        image_encoder: CLIP vision tower whose ``image_embeds`` condition the UNet.
        unet: Denoiser taking the latent and the condition latents
            (:func:`.pipeline_checks.check_components`).
        scheduler: Any diffusers scheduler.
        pose_projection: Projection of ``[image_embeds, pose]`` to the cross-attention dimension.
        feature_extractor: Optional CLIP image processor; only its ``image_mean`` / ``image_std`` are used.
        azimuth_estimator: Given exactly when the UNet's timestep embedding takes the estimated azimuth.
        sampler: The sampler measured best for these weights (keys of :data:`SAMPLER_DEFAULTS`), what a
            call argument left ``None`` takes.
        proxy: The simulator proxy's settings (:data:`~sar_zero123.model.proxy.PROXY_FIELDS`).
        lineage: ``{"start": name or path, "start_weights": SHA-256}`` of what the weights were trained
            from, or ``None``; ``interpolate`` checks it.

    Raises:
        ValueError: If the components do not fit together or a recorded setting is invalid.
    """

    model_cpu_offload_seq = "image_encoder->pose_projection->unet->vae"
    _optional_components = ["feature_extractor", "azimuth_estimator"]
    _callback_tensor_inputs = ["latents"]

    def __init__(
        self,
        vae: AutoencoderKL,
        image_encoder: CLIPVisionModelWithProjection,
        unet: UNet2DConditionModel,
        scheduler: SchedulerMixin,
        pose_projection: PoseProjection,
        feature_extractor: CLIPImageProcessor | None = None,
        azimuth_estimator: AzimuthEstimator | None = None,
        sampler: dict[str, Any] | None = None,
        proxy: dict[str, Any] | None = None,
        lineage: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        check_components(vae, image_encoder, unet, scheduler, pose_projection, azimuth_estimator)
        proxy = check_recorded_settings(sampler, proxy, lineage)
        self.register_modules(vae=vae, image_encoder=image_encoder, unet=unet, scheduler=scheduler,
                              pose_projection=pose_projection, feature_extractor=feature_extractor,
                              azimuth_estimator=azimuth_estimator)  # fmt: skip
        self.register_to_config(
            sampler=None if sampler is None else dict(sampler), proxy=proxy,
            lineage=None if lineage is None else dict(lineage),
        )  # fmt: skip

    # ----------------------------------------------------------------------------------------- sizes
    @property
    def vae_scale_factor(self) -> int:
        """Downsampling factor from pixels to latents."""
        return downsampling_factor(self.vae.config.block_out_channels)

    @property
    def size_multiple(self) -> int:
        """Image height and width must be multiples of this (VAE factor times UNet downsamplings)."""
        return self.vae_scale_factor * downsampling_factor(self.unet.config.block_out_channels)

    @property
    def default_image_size(self) -> int:
        """Image size the model was built for (``unet.config.sample_size * vae_scale_factor``)."""
        sample_size = self.unet.config.sample_size
        sample_size = sample_size[0] if isinstance(sample_size, list | tuple) else sample_size
        return int(sample_size) * self.vae_scale_factor

    # ---------------------------------------------------------------------------- images and latents
    def preprocess_image(self, image: ImageInput) -> torch.Tensor:
        """Checked input images as a float32 CPU batch ``(B, 1 | 3, H, W)``
        (:func:`.pipeline_checks.image_batch`)."""
        return image_batch(image, self.size_multiple, self.vae_scale_factor)

    def encode_conditioning(
        self, images: torch.Tensor, pose: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Cross-attention token ``(B, 1, D)`` and condition latent ``(B, C, h, w)`` of input chips
        ``(B, 1 | 3, H, W)``."""
        image_embeds, condition_latents = self._encode_images(images)
        return self.pose_projection(image_embeds, pose.to(image_embeds.device)), condition_latents

    def _encode_images(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The pose-free part of :meth:`encode_conditioning`: CLIP embeddings and condition latents."""
        if self.feature_extractor is not None:
            mean, std = tuple(self.feature_extractor.image_mean), tuple(self.feature_extractor.image_std)
            image_embeds = encode_image_embeddings(self.image_encoder, images, image_mean=mean, image_std=std)
        else:
            image_embeds = encode_image_embeddings(self.image_encoder, images)
        return image_embeds, encode_condition_latents(self.vae, images)

    def decode_latents(self, latents: torch.Tensor) -> torch.Tensor:
        """Decode scaled latents ``(N, C, h, w)`` to single-channel images in [0, 1] ``(N, 1, H, W)``."""
        decoded = self.vae.decode(latents.to(self.vae.dtype) / self.vae.config.scaling_factor).sample
        images = signed_to_unit(decoded.float()).clamp(0.0, 1.0)
        return match_channels(images, 1)

    # ------------------------------------------------------------------------------ sampling stages
    def check_inputs(
        self,
        sampler: Mapping[str, Any],
        num_images_per_prompt: int,
        output_type: str,
        callback_on_step_end_tensor_inputs: Sequence[str],
    ) -> None:
        """Refuse a call's resolved sampler values and counts, naming the argument."""
        check_call_arguments(sampler, num_images_per_prompt, output_type, callback_on_step_end_tensor_inputs,
                             self._callback_tensor_inputs, self.scheduler)  # fmt: skip
        scales = sampler["heading_guidance_scale"], sampler["depression_guidance_scale"]
        _check_contrast_scales(*scales, "`{}`")

    def prepare_start_images(
        self, request: ViewRequest, start_image: ImageInput | None, start_from: str, image_to_image: bool
    ) -> tuple[torch.Tensor | None, bool]:
        """The drafts an image-to-image call starts from: ``start_image``, else for ``start_from="proxy"``
        each input's proxy at the request (given in ``proxy_views``, or fitted).

        Returns:
            ``(start_images (B, 1 | 3, H, W) or None, whether the call fits a proxy)``.

        Raises:
            ValueError: For drafts of another count or size than the inputs.
        """
        fitted = takes_proxy(self.pose_projection) and request.proxy_views is None
        if image_to_image and start_image is None and start_from == "proxy":
            if request.proxy_views is not None:  # the given proxy at the request: no fit runs
                start_image = request.proxy_views[:, 1:2]
            else:
                start_image = proxy_drafts(
                    request.images, request.d_az, request.d_el, request.input_azimuth_deg,
                    request.input_depression_deg, self._proxy(),
                )  # fmt: skip
                fitted = True
        if start_image is None or not image_to_image:
            return None, fitted
        start_images = self.preprocess_image(start_image)
        expected = (request.batch_size, *request.images.shape[-2:])
        if start_images.shape[0] != expected[0] or start_images.shape[-2:] != expected[1:]:
            raise ValueError(
                f"`start_image` must be one draft per input image of the input's size {expected}, got "
                f"{tuple(start_images.shape)}"
            )
        return start_images, fitted

    def prepare_condition(
        self, request: ViewRequest, sampler: dict[str, Any], num_images_per_prompt: int, device: torch.device
    ) -> GuidedCondition:
        """The UNet's condition at every step for every guidance branch: the inputs' encodings (once per
        input, then repeated per sample), each branch's token, class labels, pose and proxy pair.
        """
        image_embeds, condition_latents = self._encode_images(request.images.to(device))  # for every branch
        dtype = self.unet.dtype
        input_latents = condition_latents.repeat_interleave(num_images_per_prompt, dim=0).to(dtype)
        estimate = None
        if self.azimuth_estimator is not None:  # once per input image, like the encodings above
            estimate = self.azimuth_estimator(input_latents[::num_images_per_prompt])
        encoder = BranchEncoder(self.pose_projection, self.unet, image_embeds, estimate,
                                num_images_per_prompt, dtype)  # fmt: skip
        pose = request.pose.to(device)
        scales = sampler["heading_guidance_scale"], sampler["depression_guidance_scale"]
        contrasts = contrast_branches(pose, *scales)
        proxy_pairs = None
        if takes_proxy(self.pose_projection):  # the proxy pair of each branch's request
            kinds = [kind for kind, _, _ in contrasts]
            form = proxy_form(self.pose_projection)
            proxy_pairs = proxy_latents(self.vae, request, kinds, self._proxy(), device, form).to(dtype)
        return guided_condition(
            encoder, pose, contrasts, input_latents, sampler["guidance_scale"], proxy_pairs,
            self.vae.config.scaling_factor,
        )  # fmt: skip

    def prepare_timesteps(
        self, num_inference_steps: int, denoising_steps: int, device: torch.device
    ) -> torch.Tensor:
        """The scheduler's timesteps; an image-to-image call runs the last ``denoising_steps`` only."""
        self.scheduler.set_timesteps(int(num_inference_steps), device=device)
        timesteps = self.scheduler.timesteps
        if denoising_steps < num_inference_steps:  # strength < 1: the last denoising_steps only
            start = (int(num_inference_steps) - denoising_steps) * self.scheduler.order
            timesteps = timesteps[start:]
            if hasattr(self.scheduler, "set_begin_index"):
                self.scheduler.set_begin_index(start)
        return timesteps

    def prepare_latents(
        self,
        condition: GuidedCondition,
        timesteps: torch.Tensor,
        num_images_per_prompt: int,
        generator: torch.Generator | list[torch.Generator] | None,
        latents: torch.Tensor | None,
        start_images: torch.Tensor | None,
        start_from: str,
        image_to_image: bool,
        device: torch.device,
    ) -> torch.Tensor:
        """The initial latents: noise scaled by ``init_noise_sigma``; for an image-to-image call, a draft's
        latent (``start_images``, the input's, or it turned for ``start_from="turned_input"``) noised to the
        first timestep (SDEdit).

        Raises:
            ValueError: For given ``latents`` of another shape than the samples' or not finite.
        """
        num_samples, dtype = condition.input_latents.shape[0], condition.dtype
        shape = (num_samples, self.vae.config.latent_channels, *condition.input_latents.shape[-2:])
        if latents is None:
            latents = randn_tensor(shape, generator=generator, device=device, dtype=dtype)
        else:
            check_latents(latents, shape)
            latents = latents.to(device=device, dtype=dtype)
        if not image_to_image:
            return latents * self.scheduler.init_noise_sigma
        start_latents = condition.input_latents
        if start_images is not None:
            start_latents = encode_condition_latents(self.vae, start_images.to(device))
            start_latents = start_latents.repeat_interleave(num_images_per_prompt, dim=0).to(dtype)
        elif start_from == "turned_input":
            rotation_sign = self.pose_projection.config.rotation_sign
            start_latents = rotate_condition_latents(start_latents, condition.request.pose, rotation_sign)
        start_latents = start_latents * self.vae.config.scaling_factor
        return self.scheduler.add_noise(start_latents, latents, timesteps[:1].repeat(num_samples))

    def denoise(
        self,
        latents: torch.Tensor,
        timesteps: torch.Tensor,
        condition: GuidedCondition,
        generator: torch.Generator | list[torch.Generator] | None,
        callback_on_step_end: Callable[..., dict] | PipelineCallback | MultiPipelineCallbacks | None,
        callback_on_step_end_tensor_inputs: Sequence[str],
    ) -> torch.Tensor:
        """The denoising loop: one UNet call per step with every guidance branch stacked, their guided mix,
        one scheduler step, the step callback.
        """
        # Stochastic schedulers (DDPM, Euler ancestral, SDE DPM-Solver) take the generator in `step`.
        accepts_generator = "generator" in inspect.signature(self.scheduler.step).parameters
        step_kwargs = {"generator": generator} if accepts_generator and generator is not None else {}
        branches, dtype = condition.branches, condition.dtype
        self._num_timesteps = len(timesteps)
        with (
            self.progress_bar(total=len(timesteps)) as progress_bar,
            condition.reference,
            condition.input_tokens,
        ):
            for step_index, timestep in enumerate(timesteps):
                model_input = torch.cat([latents] * branches) if branches > 1 else latents
                model_input = self.scheduler.scale_model_input(model_input, timestep)
                model_input = torch.cat([model_input, condition.unet_condition], dim=1)  # (N..4N, 8.., h, w)
                noise_pred = self.unet(
                    model_input, timestep, encoder_hidden_states=condition.tokens,
                    class_labels=condition.class_labels,
                ).sample  # fmt: skip
                noise_pred = condition.guide(noise_pred)
                latents = self.scheduler.step(noise_pred, timestep, latents, **step_kwargs).prev_sample
                latents = latents.to(dtype)

                if callback_on_step_end is not None:
                    step_tensors = {"latents": latents}
                    callback_kwargs = {k: step_tensors[k] for k in callback_on_step_end_tensor_inputs}
                    callback_outputs = callback_on_step_end(self, step_index, timestep, callback_kwargs)
                    latents = callback_latents(callback_outputs, latents)
                progress_bar.update()
        return latents

    def decode(self, latents: torch.Tensor, output_type: str, guidance_scale: float) -> Any:
        """The final latents as ``output_type``, never NaN or inf (the message names the component)."""
        names = ("unet", "vae", "image_encoder", "pose_projection", "azimuth_estimator")
        components = {name: getattr(self, name) for name in names}
        check_finite_output(latents, "latents", guidance_scale, components)
        if output_type == "latent":
            return latents
        decoded = self.decode_latents(latents)  # (N, 1, H, W)
        check_finite_output(decoded, "decoded images", guidance_scale, components)
        if output_type == "pt":
            return decoded
        array = decoded.permute(0, 2, 3, 1).cpu().numpy()  # (N, H, W, 1)
        if output_type == "np":
            return array
        return [PIL.Image.fromarray((a[..., 0] * 255.0).round().astype(np.uint8), mode="L") for a in array]

    def progress_bar(self, iterable: Any = None, total: int | None = None) -> Any:
        """The denoising loop's bar: live on a terminal, a line per interval in a log."""
        config = dict(getattr(self, "_progress_bar_config", {}))
        if iterable is not None:
            return _progress_bar(iterable, **config)
        if total is None:
            raise ValueError("Either `total` or `iterable` has to be defined.")
        return _progress_bar(total=total, **config)

    def _proxy(self) -> Mapping[str, Any] | None:
        """The recorded proxy settings, a relative shortlist path read in the pipeline's own folder."""
        return anchored_proxy(getattr(self.config, "proxy", None), self.config.get("_name_or_path"))

    @torch.no_grad()
    def __call__(
        self,
        image: ImageInput,
        d_az: float | Sequence[float] | torch.Tensor,
        d_el: float | Sequence[float] | torch.Tensor = 0.0,
        input_depression_deg: float | Sequence[float] | torch.Tensor | None = None,
        num_inference_steps: int | None = None,
        guidance_scale: float | None = None,
        num_images_per_prompt: int = 1,
        generator: torch.Generator | list[torch.Generator] | None = None,
        latents: torch.Tensor | None = None,
        output_type: Literal["pil", "np", "pt", "latent"] = "pil",
        return_dict: bool = True,
        callback_on_step_end: Callable[[DiffusionPipeline, int, torch.Tensor, dict[str, torch.Tensor]], dict]
        | PipelineCallback
        | MultiPipelineCallbacks
        | None = None,
        callback_on_step_end_tensor_inputs: Sequence[str] = ("latents",),
        strength: float | None = None,
        heading_guidance_scale: float | None = None,
        start_from: Literal["input", "turned_input", "proxy"] | None = None,
        depression_guidance_scale: float | None = None,
        start_image: ImageInput | None = None,
        input_azimuth_deg: float | Sequence[float] | torch.Tensor | None = None,
        proxy_views: torch.Tensor | None = None,
    ) -> SARZero123PipelineOutput | tuple:
        """Generate views of each input chip at ``(d_az, d_el)`` relative to it.

        A sampler argument left ``None`` (``num_inference_steps``, ``guidance_scale``, ``strength``,
        ``heading_guidance_scale``, ``depression_guidance_scale``, ``start_from``) takes the pipeline's
        recorded ``config.sampler``, else :data:`SAMPLER_DEFAULTS`. A recorded strength runs at least one
        step; a given one is never changed.

        Args:
            image: Input chip(s), normalised dB (:meth:`preprocess_image`).
            d_az: Azimuth delta in degrees (target - input), a scalar or one per input; 370 == 10.
            d_el: Depression delta in degrees (target - input), a scalar or one per input.
            input_depression_deg: Each input's absolute depression; required where the pose carries it.
                Requests outside the trained ranges are refused.
            num_inference_steps: Number of denoising steps.
            guidance_scale: Classifier-free guidance weight; off when ``<= 1``.
            num_images_per_prompt: Samples per input image.
            generator: One generator, or one per output sample.
            latents: Initial noise ``(B * num_images_per_prompt, C, h, w)``, before ``init_noise_sigma``.
            output_type: ``"pil"``, ``"np"``, ``"pt"`` or ``"latent"``.
            return_dict: Return a :class:`SARZero123PipelineOutput` instead of a tuple.
            callback_on_step_end: ``f(pipe, step, timestep, callback_kwargs)`` after each step; may return
                a dict replacing ``"latents"``.
            callback_on_step_end_tensor_inputs: Tensors passed in ``callback_kwargs``.
            strength: In (0, 1]. Below 1, start from a draft's latent noised to the
                ``int(num_inference_steps * strength)``-th last timestep and run only those steps (SDEdit);
                ``latents`` is then the noise added.
            heading_guidance_scale: ``h >= 0``: the prediction gains ``h * (eps(d_az) - eps(d_az + 180))``,
                away from the flipped heading (one more UNet evaluation per step).
            start_from: The draft at ``strength < 1``: ``"input"`` (its latent), ``"turned_input"`` (it
                turned in the image plane by the request, :func:`rotate_condition_latents`) or ``"proxy"``
                (each input's simulator proxy at the request; needs both absolute angles; a recorded
                ``"proxy"`` falls back to the input without ``input_azimuth_deg``).
            depression_guidance_scale: ``g >= 0``: the prediction gains ``g * (eps(d_az, d_el) -
                eps(d_az, 0))``, away from what a model that ignores ``d_el`` returns; no extra branch when
                every ``d_el`` is 0.
            start_image: One normalised dB draft per input, of its size, started from at ``strength < 1``
                instead of ``start_from``'s.
            input_azimuth_deg: Each input's absolute azimuth in degrees, where the proxy is fitted.
            proxy_views: A ``spatial_pose="proxy"`` pipeline's proxies given instead of fitted,
                ``(B, 2, H, W)`` (at the input's pose, at the request) or ``(B, 3, H, W)`` (at
                ``d_az + 180`` third); no fit runs.

        Returns:
            :class:`SARZero123PipelineOutput`, or ``(images,)`` when ``return_dict`` is False.

        Raises:
            ValueError: For invalid images, angles, sizes, counts, sampler values, generators or latents,
                naming the argument, before any UNet call.
        """
        # 1. check inputs; a sampler argument left None is the pipeline's recorded value, else the library's
        if isinstance(callback_on_step_end, PipelineCallback | MultiPipelineCallbacks):
            callback_on_step_end_tensor_inputs = callback_on_step_end.tensor_inputs
        given = {"num_inference_steps": num_inference_steps, "guidance_scale": guidance_scale,
                 "strength": strength, "heading_guidance_scale": heading_guidance_scale,
                 "depression_guidance_scale": depression_guidance_scale,
                 "start_from": start_from}  # fmt: skip
        sampler = resolve_sampler(given, getattr(self.config, "sampler", None), input_azimuth_deg is not None)
        self.check_inputs(sampler, num_images_per_prompt, output_type, callback_on_step_end_tensor_inputs)
        num_inference_steps = sampler["num_inference_steps"]
        denoising_steps = min(int(num_inference_steps * sampler["strength"]), int(num_inference_steps))
        image_to_image = denoising_steps < num_inference_steps  # strength < 1 (SDEdit)
        images = self.preprocess_image(image)
        request = view_request(
            images, d_az, d_el, input_depression_deg, input_azimuth_deg, proxy_views, self.pose_projection
        )
        start_images, fitted = self.prepare_start_images(
            request, start_image, sampler["start_from"], image_to_image
        )
        check_generators(generator, request.batch_size, num_images_per_prompt)
        if latents is not None:  # refused before any encoding or UNet call
            height, width = (side // self.vae_scale_factor for side in images.shape[-2:])
            num_samples = request.batch_size * num_images_per_prompt
            check_latents(latents, (num_samples, self.vae.config.latent_channels, height, width))
        device = self._execution_device

        # 2. encode the condition of every guidance branch (once per input image, then repeated per sample)
        condition = self.prepare_condition(request, sampler, num_images_per_prompt, device)

        # 3. timesteps
        timesteps = self.prepare_timesteps(num_inference_steps, denoising_steps, device)

        # 4. initial latents: noise, or (strength < 1) a draft's latent noised to the first timestep
        latents = self.prepare_latents(
            condition, timesteps, num_images_per_prompt, generator, latents, start_images,
            sampler["start_from"], image_to_image, device,
        )  # fmt: skip

        # 5. denoising loop: one UNet call per step with every guidance branch stacked
        latents = self.denoise(
            latents, timesteps, condition, generator, callback_on_step_end, callback_on_step_end_tensor_inputs
        )

        # 6. decode to single-channel normalised dB; never return NaN or inf as an image
        output = self.decode(latents, output_type, sampler["guidance_scale"])
        self.maybe_free_model_hooks()
        if not return_dict:
            return (output,)
        scores = None
        if fitted:  # the fits this call ran, remembered by the proxy module: read back, not run again
            depression = per_input_angles(request.input_depression_deg, "input_depression_deg", len(images))
            scores = fit_scores(request.images, request.input_azimuth_deg, depression, self._proxy())
        return SARZero123PipelineOutput(images=output, proxy_fit_scores=scores)


# diffusers resolves model_index.json's `_class_name` in its own namespace; registering the class there
# lets `DiffusionPipeline.from_pretrained(folder)` load a SAR pipeline without `trust_remote_code`.
if getattr(diffusers, SARZero123Pipeline.__name__, None) is None:
    setattr(diffusers, SARZero123Pipeline.__name__, SARZero123Pipeline)
