"""`SARZero123Pipeline`: novel views of a SAR chip at a requested relative pose (zero-1-to-3 sampling).

The sampler follows zero-1-to-3: the UNet input is the noisy latent concatenated with the unscaled VAE
posterior mode of the input chip (8 channels); cross-attention sees one token,
``PoseProjection([clip_image_embedding, pose])``; classifier-free guidance uses zeros for both the
projected token and the condition latent as the unconditional input and runs conditional and
unconditional branches in one batched UNet call.

``__call__`` runs in numbered stages that delegate, as diffusers' Stable Diffusion pipeline does (checks in
:mod:`.view_request` and :mod:`.pipeline_checks`, the guidance branches in :mod:`.guidance`; loading, saving
and the recorded settings in :mod:`.pipeline_loading`).
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
from sar_zero123.model.spatial_pose import rotate_condition_latents, takes_proxy
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
        images: Generated views in the normalised dB domain, ``B * num_images_per_prompt`` of them,
            grouped by input image (all samples of input 0 first). A list of single-channel PIL images
            (``"pil"``), a float32 array ``(N, H, W, 1)`` (``"np"``), a tensor ``(N, 1, H, W)``
            (``"pt"``), or the final latents ``(N, 4, h, w)`` (``"latent"``).
        proxy_fit_scores: Where a simulator proxy was fitted to the inputs, how well each fits its input
            ``(B,)``: the blurred correlation in [-1, 1] of the fitted vehicle with the chip at its pose
            (:func:`~sar_zero123.model.proxy.fit_scores`); ``None`` where no fit ran (``proxy_views`` given,
            or a call that uses no proxy).
    """

    images: list[PIL.Image.Image] | np.ndarray | torch.Tensor
    proxy_fit_scores: np.ndarray | None = None


class SARZero123Pipeline(PipelineLoadingMixin, DiffusionPipeline):
    """Novel-view synthesis of SAR chips with a zero-1-to-3 latent diffusion model.

    Args:
        vae: Autoencoder; 1-channel (trained on SAR) or 3-channel (Stable Diffusion) input.
        image_encoder: CLIP vision tower whose ``image_embeds`` condition the UNet.
        unet: Denoiser with ``in_channels = 2 * vae.config.latent_channels`` (3 times with the pose
            projection's ``spatial_pose="rotated_input"``).
        scheduler: Any diffusers scheduler (DDIM, DPM-Solver++, Euler, ...).
        pose_projection: Projection of ``[image_embeds, pose]`` to the cross-attention dimension.
        feature_extractor: Optional CLIP image processor; only its ``image_mean`` / ``image_std`` are
            used (preprocessing runs in torch, see :func:`encode_image_embeddings`).
        azimuth_estimator: Optional :class:`~sar_zero123.model.orientation.AzimuthEstimator`, given exactly
            when the UNet's timestep embedding takes the target's estimated azimuth after the pose.
        sampler: The sampler measured best for these weights (a dict of :data:`SAMPLER_DEFAULTS`' keys):
            every call argument left ``None`` takes it (saved in ``model_index.json``).
        proxy: The simulator proxy's settings (:data:`~sar_zero123.model.proxy.PROXY_FIELDS`), for a start
            from the proxy or a ``spatial_pose="proxy"`` UNet.
        lineage: What the weights were trained from: ``{"start": name or path, "start_weights": SHA-256 of
            its weight files}`` (:func:`~sar_zero123.runs.folder.weights_identity`), recorded by a fine-tune's
            export and checked by ``interpolate``; ``None`` for weights of unknown origin.

    Raises:
        ValueError: If the component sizes do not fit together (:func:`~.pipeline_checks.check_components`),
            or a recorded setting is invalid (:func:`~.pipeline_loading.check_recorded_settings`).
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
        # the measured-best sampler, the proxy bank and the weights' origin travel with them
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
        """Validate and convert pipeline input images to a float32 batch ``(B, 1 | 3, H, W)`` on the CPU, in
        the normalised dB domain, of a size the VAE and UNet can take (:func:`.pipeline_checks.image_batch`
        says what is accepted and refused)."""
        return image_batch(image, self.size_multiple, self.vae_scale_factor)

    def encode_conditioning(
        self, images: torch.Tensor, pose: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Cross-attention token and condition latent of a batch of input chips.

        Args:
            images: Normalised dB images in [0, 1].
            pose: Pose vectors from :func:`embed_pose`.

        Returns:
            ``(tokens, condition_latents)``.

        Shape:
            - images: ``(B, 1 | 3, H, W)``; pose: ``(B, 1, 4)``
            - tokens: ``(B, 1, cross_attention_dim)``; condition_latents: ``(B, 4, H / f, W / f)``
        """
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
        """Decode scaled latents to single-channel images in the normalised dB domain.

        Args:
            latents: Scaled latents (``z * vae.config.scaling_factor``).

        Returns:
            Images in [0, 1], float32; 3-channel VAE outputs are averaged to one channel.

        Shape:
            - latents: ``(N, 4, h, w)``
            - Output: ``(N, 1, h * f, w * f)``
        """
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
        """Refuse a call's sampler values (:func:`.sampler.resolve_sampler`'s) and counts, naming the argument
        (:func:`.pipeline_checks.check_call_arguments`)."""
        check_call_arguments(sampler, num_images_per_prompt, output_type, callback_on_step_end_tensor_inputs,
                             self._callback_tensor_inputs, self.scheduler)  # fmt: skip
        scales = sampler["heading_guidance_scale"], sampler["depression_guidance_scale"]
        _check_contrast_scales(*scales, "`{}`")

    def prepare_start_images(
        self, request: ViewRequest, start_image: ImageInput | None, start_from: str, image_to_image: bool
    ) -> tuple[torch.Tensor | None, bool]:
        """The drafts an image-to-image call starts from: ``start_image``, else for ``start_from="proxy"``
        each input's proxy at the request (given in ``proxy_views``, or fitted), checked as the input is.

        Returns:
            ``(start_images, fitted)``: the drafts ``(B, 1 | 3, H, W)``, or ``None`` where the call starts
            from the input's latent or from pure noise; and whether the call fits a proxy.

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
        """What the UNet is conditioned on at every step, for every guidance branch: the inputs' CLIP
        embeddings and latents (encoded once per input image, then repeated per sample), each branch's
        token, class labels and pose, and for a ``spatial_pose="proxy"`` UNet each branch's proxy pair.

        A new conditioning input enters here, as a field of the branches (:mod:`.guidance`).
        """
        image_embeds, condition_latents = self._encode_images(request.images.to(device))  # for every branch
        # Read once: `ModelMixin.dtype` walks every parameter of the UNet on each access.
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
            proxy_pairs = proxy_latents(self.vae, request, kinds, self._proxy(), device).to(dtype)
        return guided_condition(
            encoder, pose, contrasts, input_latents, sampler["guidance_scale"], proxy_pairs,
            self.vae.config.scaling_factor,
        )  # fmt: skip

    def prepare_timesteps(
        self, num_inference_steps: int, denoising_steps: int, device: torch.device
    ) -> torch.Tensor:
        """The scheduler's timesteps for ``num_inference_steps``, of which an image-to-image call
        (``denoising_steps < num_inference_steps``) runs the last ``denoising_steps`` only."""
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
        """The initial latents: pure noise (``latents``, else drawn from ``generator``) scaled by the
        scheduler's ``init_noise_sigma``; for an image-to-image call, a draft's latent (``start_images``,
        the input's own, or it turned by the request for ``start_from="turned_input"``) noised to the first
        of ``timesteps`` with the scheduler's ``add_noise`` (SDEdit).

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
        """The denoising loop: one UNet call per step with every guidance branch stacked, their guided mix
        (:meth:`GuidedCondition.guide <sar_zero123.model.guidance.GuidedCondition.guide>`), one scheduler
        step, and the step callback."""
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
        """The final latents as ``output_type`` (single-channel normalised dB images, or the latents), never
        NaN or inf (:func:`.pipeline_checks.check_finite_output` names the component at fault)."""
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
        """The denoising loop's bar (``set_progress_bar_config`` applies): a live bar on a terminal, a line
        per interval in a log (:func:`sar_zero123.progress.progress_bar`)."""
        config = dict(getattr(self, "_progress_bar_config", {}))
        if iterable is not None:
            return _progress_bar(iterable, **config)
        if total is None:
            raise ValueError("Either `total` or `iterable` has to be defined.")
        return _progress_bar(total=total, **config)

    def _proxy(self) -> Mapping[str, Any] | None:
        """The recorded proxy settings, a relative learned shortlist read in the pipeline's own folder."""
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

        Args:
            image: Input chip(s) in the normalised dB domain (see :meth:`preprocess_image`).
            d_az: Azimuth delta in degrees (target - input); a scalar or one value per input image.
                Any real value (370 == 10).
            d_el: Depression delta in degrees (target - input); a scalar or one value per input image.
            input_depression_deg: The input chip's absolute depression in degrees (a scalar or one value
                per input image), from its metadata; required by a pipeline whose pose carries it
                (``pose_projection.config.input_depression``), ignored otherwise. Requests outside the
                ranges the pipeline was trained on (``trained_d_el_deg``, ``trained_depression_deg`` of
                its pose projection) are refused.
            num_inference_steps: Number of denoising steps.
            guidance_scale: Classifier-free guidance weight; guidance is off when ``<= 1``.

            Every sampler argument left ``None`` (``num_inference_steps``, ``guidance_scale``, ``strength``,
            ``heading_guidance_scale``, ``depression_guidance_scale``, ``start_from``) takes the value the
            pipeline records as measured best for it (``pipe.config.sampler``, saved in
            ``model_index.json``), else the library's default (:data:`SAMPLER_DEFAULTS`: 50 steps, guidance
            3, strength 1, no heading or depression guidance, start from the input). A pipeline may record
            a ``proxy_strength`` for a start from the proxy, a nearer draft than the input. A recorded
            strength runs at least one denoising step of the call's ``num_inference_steps``; a given one is
            never changed.
            num_images_per_prompt: Samples per input image.
            generator: One generator, or one per output sample (``B * num_images_per_prompt``).
            latents: Optional initial noise ``(B * num_images_per_prompt, 4, h, w)``, unscaled by
                ``init_noise_sigma`` (the scheduler's scaling is applied here).
            output_type: ``"pil"``, ``"np"``, ``"pt"`` or ``"latent"``.
            return_dict: Return a :class:`SARZero123PipelineOutput` instead of a tuple.
            callback_on_step_end: Called as ``f(pipe, step, timestep, callback_kwargs)`` after each step;
                may return a dict replacing entries of ``callback_kwargs`` (``"latents"``).
            callback_on_step_end_tensor_inputs: Tensors passed in ``callback_kwargs``.
            strength: In (0, 1]. Below 1, sampling starts from the input chip's own latent noised to the
                ``int(num_inference_steps * strength)``-th last timestep, and runs only those steps
                (SDEdit, as diffusers' image-to-image pipelines do): the view keeps more of the input,
                which suits small pose changes. ``latents``, if given, is then the noise added. 1 (the
                default) starts from pure noise.
            heading_guidance_scale: Weight ``h >= 0`` of guidance away from the flipped heading: the
                prediction gains ``h * (eps(d_az) - eps(d_az + 180))``, which pushes each view from the
                same body axis with its front and back swapped (:func:`.guidance.flipped_heading_pose`). One
                more UNet evaluation per step; 0 (the default) leaves sampling unchanged.
            start_from: Which latent a call with ``strength < 1`` noises and starts from: ``"input"`` (the
                default), the input chip's latent as it is, or ``"turned_input"``, the same latent turned in
                the image plane by the requested azimuth change (:func:`rotate_condition_latents`, with the
                pose projection's ``rotation_sign``): a first draft of the target view whose footprint lies
                where the target's does, for the last denoising steps to correct (shadow and layover stay tied
                to the range direction). Ignored at ``strength == 1``. Measured not to help on the quickstart
                (docs/results/). ``"proxy"``: each
                input's simulator proxy (:mod:`sar_zero123.model.proxy`: the vehicle of the pipeline's
                ``proxy`` bank that images most like the input at its pose) rendered at the requested pose,
                a draft whose shadow, layover and front are the requested pose's; it needs
                ``input_depression_deg`` and ``input_azimuth_deg``. A pipeline that records ``"proxy"`` as its
                start starts from the input when a call gives no ``input_azimuth_deg``.
            depression_guidance_scale: Weight ``g >= 0`` of guidance away from the input's depression: the
                prediction gains ``g * (eps(d_az, d_el) - eps(d_az, 0))``, which pushes each view from the
                same request at the input's own depression (:func:`.guidance.same_depression_pose`), the
                view a model that ignores ``d_el`` returns. Requests with ``d_el == 0`` are unchanged (both
                branches are the same; a call whose every ``d_el`` is 0 runs no extra branch). Otherwise one
                more UNet evaluation per step; 0 (the default) leaves sampling unchanged.
            start_image: A first draft of each target view (one per input image, the input's size, normalised
                dB) that a call with ``strength < 1`` noises and starts from instead of ``start_from``'s
                latent: a simulator proxy re-rendered at the requested pose
                (:class:`~sar_zero123.sim.proxy.ProxyBank`), whose shadow, layover and front are the
                requested pose's, for the last denoising steps, conditioned on the input, to carry the
                input's identity onto. Ignored at ``strength == 1``.
            input_azimuth_deg: Each input chip's absolute azimuth in degrees (a scalar or one per input),
                from its metadata (the MSTAR header, ``index.csv``, the simulator): where
                ``start_from="proxy"`` fits the proxy, and a ``spatial_pose="proxy"`` pipeline needs it.
            proxy_views: For a ``spatial_pose="proxy"`` pipeline only: each input's proxy given instead of
                fitted, ``(B, 2, H, W)`` normalised dB (at the input's pose, then at the requested pose; every
                guidance branch takes them), or ``(B, 3, H, W)`` with the proxy at ``d_az + 180`` third (the
                heading contrast's, as a fitted proxy gives it). No fit runs then: the view at the request
                is also the draft a ``start_from="proxy"`` call starts from. An evaluation passes the true
                vehicle here to bound what a perfect proxy gives, or proxies it fitted once in parallel.

        Returns:
            :class:`SARZero123PipelineOutput`, or ``(images,)`` when ``return_dict`` is False.

        Raises:
            ValueError: For invalid images, angles, sizes, counts, sampler values, generators or latents
                (the message names the argument and what was expected), before any UNet call.
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


# diffusers resolves the `_class_name` of model_index.json inside its own namespace
# (`_get_pipeline_class` in diffusers 0.42), so a saved SAR pipeline would only load through
# `SARZero123Pipeline.from_pretrained`. Registering the class there lets the generic
# `DiffusionPipeline.from_pretrained(folder)` load it too, once `sar_zero123` is imported, without
# `trust_remote_code` or code copied into the folder.
if getattr(diffusers, SARZero123Pipeline.__name__, None) is None:
    setattr(diffusers, SARZero123Pipeline.__name__, SARZero123Pipeline)
