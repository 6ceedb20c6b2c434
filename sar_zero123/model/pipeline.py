"""`SARZero123Pipeline`: novel views of a SAR chip at a requested relative pose (zero-1-to-3 sampling).

The sampler follows zero-1-to-3: the UNet input is the noisy latent concatenated with the unscaled VAE
posterior mode of the input chip (8 channels); cross-attention sees one token,
``PoseProjection([clip_image_embedding, pose])``; classifier-free guidance uses zeros for both the
projected token and the condition latent as the unconditional input and runs conditional and
unconditional branches in one batched UNet call.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import numbers
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import diffusers
import numpy as np
import PIL.Image
import torch
from diffusers import (
    AutoencoderKL,
    DiffusionPipeline,
    UNet2DConditionModel,
)
from diffusers.callbacks import MultiPipelineCallbacks, PipelineCallback
from diffusers.schedulers.scheduling_utils import SchedulerMixin
from diffusers.utils import BaseOutput
from diffusers.utils.torch_utils import randn_tensor
from transformers import CLIPVisionModelWithProjection

from sar_zero123.domain import signed_to_unit
from sar_zero123.model.conditioning import (
    POSE_DIM,
    PoseProjection,
    as_angle_tensor,
    check_vae_signature,
    condition_channels,
    downsampling_factor,
    embed_pose,
    encode_condition_latents,
    encode_image_embeddings,
    match_channels,
    pose_class_labels,
    proxy_pair_latents,
    rotate_condition_latents,
    takes_proxy,
    unet_condition_latents,
)
from sar_zero123.model.loading import check_pipeline_folder, find_failing_component
from sar_zero123.model.orientation import AzimuthEstimator, estimator_weights_digest, target_view_features
from sar_zero123.model.proxy import check_proxy_settings, draft_target_views, fit_scores
from sar_zero123.model.reference_attention import (
    attending_to_reference,
    check_reference_layers,
    input_reference,
    own_pose,
    reference_weights,
    uses_reference,
)
from sar_zero123.model.sampler import (
    MAX_GUIDANCE_SCALE,
    SAMPLER_DEFAULTS,
    SCHEDULERS,
    START_FROM,
    SamplerSettings,
    _check_contrast_scales,
    _check_strength,
    check_sampler_start,
    resolve_sampler,
)
from sar_zero123.model.zero123_checkpoints import CLIPImageProcessor, load_zero123_components
from sar_zero123.pretrained import BUNDLED_NAMESPACE, BUNDLED_PIPELINES, is_bundled_name, resolve_pretrained
from sar_zero123.progress import progress_bar as _progress_bar
from sar_zero123.runs.manifest import MANIFEST_FILE, manifest_problem, unlisted_files, write_manifest

__all__ = [
    "SCHEDULERS",
    "SARZero123Pipeline",
    "SARZero123PipelineOutput",
    "SAMPLER_DEFAULTS",
    "SamplerSettings",
    "check_sampler_start",
    "flipped_heading_pose",
    "same_depression_pose",
]

logger = logging.getLogger(__name__)

ImageInput = PIL.Image.Image | np.ndarray | torch.Tensor | Sequence[PIL.Image.Image] | Sequence[np.ndarray]
OUTPUT_TYPES = ("pil", "np", "pt", "latent")
#: A depression delta is the difference of two depression angles in [0, 90] degrees.
MAX_ABS_D_EL_DEG = 90.0
#: Azimuth deltas beyond this many degrees (~2,800 turns) are almost surely a unit error, and float64
#: loses the angle's fraction of a degree long before 1e15.
MAX_ABS_D_AZ_DEG = 1e6


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


def _denoising_steps(strength: float, num_inference_steps: int) -> int:
    """Steps an image-to-image call runs: ``int(num_inference_steps * strength)``, as diffusers does.

    Raises:
        ValueError: If ``strength`` is not a real number in (0, 1], or leaves no step to run.
    """
    _check_strength(strength, {"num_inference_steps": num_inference_steps})
    return min(int(num_inference_steps * strength), int(num_inference_steps))


def check_vae_image_size(vae: AutoencoderKL, unet: UNet2DConditionModel, name: str = "vae") -> None:
    """Refuse a VAE built for another chip size than the UNet: ``vae.config.sample_size`` (pixels) must be
    ``unet.config.sample_size`` (latent pixels) times the VAE's downsampling factor.

    The networks would run at any size, but the pipeline's default image size, the training resolution and
    the evaluation all follow these two records, so a VAE copied in from another model would silently
    change the size every view is made at.

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


class SARZero123Pipeline(DiffusionPipeline):
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
        ValueError: If the component sizes do not fit together.
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
        for name, module, kind in (("scheduler", scheduler, SchedulerMixin), ("vae", vae, AutoencoderKL),
                                   ("unet", unet, UNet2DConditionModel)):  # fmt: skip
            if not isinstance(module, kind):
                raise ValueError(f"`{name}` must be a diffusers {kind.__name__}, got {type(module).__name__}")
        if sampler is not None:
            if not isinstance(sampler, dict) or set(sampler) - set(SAMPLER_DEFAULTS):
                raise ValueError(
                    f"`sampler` must be a dict of some of {list(SAMPLER_DEFAULTS)}, got {sampler!r}"
                )
            if sampler.get("start_from", "input") not in START_FROM:
                raise ValueError(
                    f"`sampler.start_from` must be one of {START_FROM}, got {sampler['start_from']!r}"
                )
            try:  # each recorded value within what a call may ask for (steps, guidance, strength)
                SamplerSettings(**{key: value for key, value in sampler.items() if key != "proxy_strength"})
            except (TypeError, ValueError) as error:
                raise ValueError(f"`sampler` (recorded in model_index.json): {error}") from None
            if sampler.get("proxy_strength") is not None:
                _check_strength(sampler["proxy_strength"], {}, "sampler.proxy_")
            if sampler.get("start_from") == "proxy" and proxy is None:
                raise ValueError(
                    "`sampler.start_from` is 'proxy', but the pipeline records no `proxy` settings"
                )
        if proxy is not None:
            proxy = check_proxy_settings(proxy)
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
        self.register_modules(
            vae=vae,
            image_encoder=image_encoder,
            unet=unet,
            scheduler=scheduler,
            pose_projection=pose_projection,
            feature_extractor=feature_extractor,
            azimuth_estimator=azimuth_estimator,
        )
        # the measured-best sampler and the proxy bank travel with the weights (model_index.json)
        if lineage is not None and not (
            isinstance(lineage, dict) and all(isinstance(v, str | None) for v in lineage.values())
        ):
            raise ValueError(f"`lineage` must be a dict of strings (where the weights began), got {lineage}")
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

    # ------------------------------------------------------------------------------------ loading
    @classmethod
    def from_pretrained(
        cls, pretrained_model_name_or_path: str | os.PathLike, **kwargs: Any
    ) -> SARZero123Pipeline:
        """diffusers' ``from_pretrained``, after resolving the name of a pipeline bundled with the package.

        Args:
            pretrained_model_name_or_path: A registered name such as ``"sar-zero123/sim-prior"``
                (:data:`sar_zero123.pretrained.SIM_PRIOR`), a ``save_pretrained`` folder, or anything
                else diffusers loads (passed on unchanged; an existing path wins over a name).
            **kwargs: diffusers' loading options (``torch_dtype``, ...), and ``verify_manifest`` (default
                True): a local folder's files must match the ``manifest.json`` that :meth:`save_pretrained`
                wrote; ``False`` loads a changed folder anyway, with a logged warning naming what differs.
                A folder without a manifest (written before manifests existed) loads with a warning.

        Returns:
            The pipeline.

        Raises:
            FileNotFoundError: For a registered name whose weights are missing from this install, an
                unknown name under ``"sar-zero123/"`` (listing the bundled ones), or a
                folder without ``model_index.json`` or missing a component's folder, config or weights;
                the message names the component, the file expected and the folder.
            ValueError: For a folder whose JSON is invalid (naming the file), a component whose files
                do not load (a config that does not fit its weights, a truncated weight file), naming it,
                or a file that differs from the folder's ``manifest.json`` (changed, truncated or missing),
                naming it, unless ``verify_manifest=False``. A weight or config added since is named in a
                warning.
        """
        if isinstance(pretrained_model_name_or_path, str | os.PathLike) and (
            is_bundled_name(pretrained_model_name_or_path)
            or os.fspath(pretrained_model_name_or_path).startswith(BUNDLED_NAMESPACE)
        ):  # a bundled name, or a refusal listing them (never a hub lookup of an unknown bundled name)
            pretrained_model_name_or_path = resolve_pretrained(pretrained_model_name_or_path)
        folder = pretrained_model_name_or_path
        verify_manifest = kwargs.pop("verify_manifest", True)
        if isinstance(folder, str | os.PathLike) and not os.path.isdir(folder):
            _refuse_a_missing_local_name(os.fspath(folder))
        if not (isinstance(folder, str | os.PathLike) and os.path.isdir(folder)):
            return super().from_pretrained(folder, **kwargs)
        # 1. a local folder: every file it was saved with is checked against its manifest (a changed weight,
        # config or scaling would load and give other views), then each component's files, naming the
        # component, before diffusers reads them (diffusers names a fallback `.bin` file or the folder)
        _check_manifest(folder, verify_manifest)
        components = check_pipeline_folder(folder, given=kwargs)
        try:
            return super().from_pretrained(folder, **kwargs)
        except (OSError, ValueError, RuntimeError, TypeError, KeyError):
            # 2. the files are there but something does not load: say which component
            find_failing_component(folder, components)
            raise

    def save_pretrained(self, save_directory: str | os.PathLike, **kwargs: Any) -> None:
        """diffusers' ``save_pretrained``, then ``manifest.json`` (written last, atomically): the size and
        SHA-256 of every file of the folder, which :meth:`from_pretrained` checks before loading.

        A writer that adds a file to the folder afterwards (a ``decibel_scaling.json``) seals it again with
        :func:`sar_zero123.runs.manifest.write_manifest`.
        """
        super().save_pretrained(save_directory, **kwargs)
        write_manifest(save_directory)

    @classmethod
    def from_zero123(
        cls,
        path: str | Path,
        use_ema: bool = True,
        image_encoder_path: str | Path | None = None,
        torch_dtype: torch.dtype | None = None,
        **conversion: Any,
    ) -> SARZero123Pipeline:
        """Load an Objaverse zero-1-to-3 checkpoint (diffusers folder, threestudio folder, or LDM file).

        See :func:`sar_zero123.model.zero123_checkpoints.load_zero123_components` for the accepted layouts.

        Args:
            path: A diffusers folder (``cc_projection`` or ``clip_camera_projection``) or an LDM
                ``.ckpt`` / ``.safetensors`` state dict.
            use_ema: For LDM files holding ``model_ema.*``, load the EMA UNet weights.
            image_encoder_path: Folder of a ``CLIPVisionModelWithProjection`` (and optionally its
                ``CLIPImageProcessor``) for LDM files; ignored for folders that ship one.
            torch_dtype: Optional dtype for all modules.
            **conversion: LDM files only: ``unet_config``, ``vae_config``, ``image_encoder_config``
                overrides and ``weights_only`` (see ``load_zero123_components``).

        Returns:
            The pipeline in eval mode, with a DDIM scheduler for LDM files.
        """
        components = load_zero123_components(
            path, use_ema=use_ema, image_encoder_path=image_encoder_path, **conversion
        )
        pipe = cls(**components)
        if torch_dtype is not None:
            pipe.to(dtype=torch_dtype)
        return pipe

    # ----------------------------------------------------------------------------- input checking
    def preprocess_image(self, image: ImageInput) -> torch.Tensor:
        """Validate and convert pipeline input images to a float32 batch in the normalised dB domain.

        Accepted: a PIL image (modes ``L``, ``RGB``, ``I;16``, ``F``) or a list of them, a numpy array
        ``(H, W)`` / ``(H, W, C)`` or a list of them (float in [0, 1]; ``uint8`` is divided by 255), a
        tensor ``(B, 1 | 3, H, W)`` in [0, 1].

        Args:
            image: The input chip(s).

        Returns:
            The batch on the CPU.

        Shape:
            - Output: ``(B, 1 | 3, H, W)``

        Raises:
            ValueError: (naming ``image``) for an empty batch, a wrong rank or channel count, mixed sizes,
                non-finite or out-of-range values, or a size the VAE and UNet cannot take.
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
            raise ValueError(
                f"`image` must lie in [0, 1] (normalised dB), got values in [{low:.4g}, {high:.4g}]"
            )
        height, width = batch.shape[-2:]
        multiple = self.size_multiple
        if height % multiple or width % multiple:
            raise ValueError(
                f"`image` height and width must be positive multiples of {multiple} (VAE factor "
                f"{self.vae_scale_factor} x UNet downsampling), got {height}x{width}"
            )
        return batch

    def _check_proxy_views(self, proxy_views: Any, images: torch.Tensor, proxy_model: bool) -> torch.Tensor:
        """``proxy_views`` checked as ``image`` is: a real tensor or array of normalised dB views, one set per
        input, of the input's size.

        Returns:
            ``(B, 2 | 3, H, W)`` float32 on the CPU.

        Raises:
            ValueError: Naming ``proxy_views`` and what was expected.
        """
        if not proxy_model:
            raise ValueError(
                "`proxy_views`: this pipeline's UNet takes no proxy (pose_projection.config.spatial_pose="
                f"{getattr(self.pose_projection.config, 'spatial_pose', None)!r}); leave it out"
            )
        expected = (images.shape[0], 2, *images.shape[-2:])
        what = (
            f"`proxy_views` must be real normalised dB views in [0, 1] of shape {expected}: each input's "
            "proxy at the input's pose, then at the requested pose (and, as a third, at the flipped heading "
            "d_az + 180 for heading guidance)"
        )
        if isinstance(proxy_views, np.ndarray):
            proxy_views = torch.from_numpy(proxy_views)
        if not isinstance(proxy_views, torch.Tensor):
            raise ValueError(f"{what}; got a {type(proxy_views).__name__}")
        if proxy_views.is_complex() or proxy_views.dtype == torch.bool or proxy_views.is_meta:
            raise ValueError(f"{what}; got a {proxy_views.dtype} tensor")
        shape = tuple(proxy_views.shape)
        if shape not in (expected, (expected[0], 3, *expected[2:])):
            raise ValueError(f"{what}; got shape {shape}")
        views = proxy_views.detach().to("cpu", torch.float32)
        if not torch.isfinite(views).all() or float(views.min()) < 0.0 or float(views.max()) > 1.0:
            raise ValueError(f"{what}; got values outside [0, 1] or not finite")
        return views

    def _check_inputs(
        self,
        num_inference_steps: int,
        guidance_scale: float,
        num_images_per_prompt: int,
        output_type: str,
        callback_on_step_end_tensor_inputs: Sequence[str],
    ) -> None:
        if not isinstance(num_inference_steps, numbers.Integral) or num_inference_steps < 1:
            raise ValueError(f"`num_inference_steps` must be an integer >= 1, got {num_inference_steps!r}")
        # more steps than the schedule has timesteps repeat timesteps (or hang a loop of millions of steps)
        max_steps = int(getattr(self.scheduler.config, "num_train_timesteps", 1000))
        if num_inference_steps > max_steps:
            raise ValueError(
                f"`num_inference_steps` must be <= {max_steps} (the scheduler's num_train_timesteps), "
                f"got {num_inference_steps}"
            )
        if isinstance(guidance_scale, bool) or not isinstance(guidance_scale, numbers.Real):
            kind = type(guidance_scale).__name__
            raise TypeError(f"`guidance_scale` must be a real number, got {kind} {guidance_scale!r}")
        if not np.isfinite(guidance_scale):
            raise ValueError(f"`guidance_scale` must be finite, got {guidance_scale}")
        if guidance_scale > MAX_GUIDANCE_SCALE:  # the guided noise estimate overflows to NaN images
            raise ValueError(
                f"`guidance_scale` must be <= {MAX_GUIDANCE_SCALE} (zero-1-to-3 uses 3), got {guidance_scale}"
            )
        if not isinstance(num_images_per_prompt, numbers.Integral) or num_images_per_prompt < 1:
            raise ValueError(
                f"`num_images_per_prompt` must be an integer >= 1, got {num_images_per_prompt!r}"
            )
        if output_type not in OUTPUT_TYPES:
            raise ValueError(f"`output_type` must be one of {OUTPUT_TYPES}, got {output_type!r}")
        unknown = [k for k in callback_on_step_end_tensor_inputs if k not in self._callback_tensor_inputs]
        if unknown:
            raise ValueError(
                f"`callback_on_step_end_tensor_inputs` must be among {self._callback_tensor_inputs}, "
                f"got {unknown}"
            )

    def _check_finite_output(self, samples: torch.Tensor, what: str, guidance_scale: float) -> None:
        """Raise instead of returning samples with NaN or inf, saying which component is at fault."""
        bad = ~torch.isfinite(samples.flatten(1)).all(dim=1)
        if not bad.any():
            return
        broken = [
            name
            for name in ("unet", "vae", "image_encoder", "pose_projection", "azimuth_estimator")
            if getattr(self, name) is not None
            and any(not torch.isfinite(p).all() for p in getattr(self, name).parameters())
        ]
        cause = (
            f"these components hold NaN/inf weights (a diverged training run?): {broken}"
            if broken
            else f"the weights are finite; guidance_scale={guidance_scale} or the inputs may be too extreme"
        )
        raise FloatingPointError(
            f"the pipeline produced non-finite {what} for {int(bad.sum())} of {len(bad)} samples; {cause}"
        )

    # ---------------------------------------------------------------------------------- sampling
    def progress_bar(self, iterable: Any = None, total: int | None = None) -> Any:
        """The denoising loop's bar (``set_progress_bar_config`` applies): a live bar on a terminal, a line
        per interval in a log (:func:`sar_zero123.progress.progress_bar`)."""
        config = dict(getattr(self, "_progress_bar_config", {}))
        if iterable is not None:
            return _progress_bar(iterable, **config)
        if total is None:
            raise ValueError("Either `total` or `iterable` has to be defined.")
        return _progress_bar(total=total, **config)

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

    @staticmethod
    def _callback_latents(outputs: Any, latents: torch.Tensor) -> torch.Tensor:
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

    def _scheduler_step_kwargs(
        self, generator: torch.Generator | list[torch.Generator] | None
    ) -> dict[str, Any]:
        # Stochastic schedulers (DDPM, Euler ancestral, SDE DPM-Solver) take the generator in `step`.
        accepts_generator = "generator" in inspect.signature(self.scheduler.step).parameters
        return {"generator": generator} if accepts_generator and generator is not None else {}

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
                same body axis with its front and back swapped (:func:`flipped_heading_pose`). One more
                UNet evaluation per step; 0 (the default) leaves sampling unchanged.
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
                same request at the input's own depression (:func:`same_depression_pose`), the view a model
                that ignores ``d_el`` returns. Requests with ``d_el == 0`` are unchanged (both branches are
                the same; a call whose every ``d_el`` is 0 runs no extra branch). Otherwise one more UNet
                evaluation per step; 0 (the default) leaves sampling unchanged.
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
            ValueError: For invalid images, angles, sizes, counts or generators (the message names the
                argument).
        """
        if isinstance(callback_on_step_end, PipelineCallback | MultiPipelineCallbacks):
            callback_on_step_end_tensor_inputs = callback_on_step_end.tensor_inputs

        # 1. check inputs; a sampler argument left None is the pipeline's recorded value, else the library's
        given = {"num_inference_steps": num_inference_steps, "guidance_scale": guidance_scale,
                 "strength": strength, "heading_guidance_scale": heading_guidance_scale,
                 "depression_guidance_scale": depression_guidance_scale,
                 "start_from": start_from}  # fmt: skip
        recorded = getattr(self.config, "sampler", None)
        values = resolve_sampler(given, recorded, input_azimuth_given=input_azimuth_deg is not None)
        (num_inference_steps, guidance_scale, strength, heading_guidance_scale, depression_guidance_scale,
         start_from) = (values[name] for name in given)  # fmt: skip
        self._check_inputs(
            num_inference_steps,
            guidance_scale,
            num_images_per_prompt,
            output_type,
            callback_on_step_end_tensor_inputs,
        )
        denoising_steps = _denoising_steps(strength, num_inference_steps)
        if start_from not in START_FROM:
            raise ValueError(f"`start_from` must be one of {START_FROM}, got {start_from!r}")
        _check_contrast_scales(heading_guidance_scale, depression_guidance_scale, "`{}`")
        images = self.preprocess_image(image)
        batch_size = images.shape[0]
        pose = _broadcast_pose(d_az, d_el, batch_size)  # (B, 1, 4)
        pose = self._pose_with_depression(pose, d_el, input_depression_deg)
        if input_azimuth_deg is not None:  # checked whether or not this call's start uses it
            input_azimuth_deg = _per_input_angles(input_azimuth_deg, "input_azimuth_deg", batch_size)
        proxy_model = takes_proxy(self.pose_projection)
        if proxy_views is not None:
            proxy_views = self._check_proxy_views(proxy_views, images, proxy_model)
        start_images, fitted = None, proxy_model and proxy_views is None
        if start_image is None and start_from == "proxy" and denoising_steps < num_inference_steps:
            if proxy_views is not None:  # the given proxy at the request: no fit runs
                start_image = proxy_views[:, 1:2]
            else:
                start_image = self._proxy_drafts(images, d_az, d_el, input_azimuth_deg, input_depression_deg)
                fitted = True
        if start_image is not None and denoising_steps < num_inference_steps:
            start_images = self.preprocess_image(start_image)
            if start_images.shape[0] != batch_size or start_images.shape[-2:] != images.shape[-2:]:
                raise ValueError(
                    f"`start_image` must be one draft per input image of the input's size "
                    f"{(batch_size, *images.shape[-2:])}, got {tuple(start_images.shape)}"
                )
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
        device = self._execution_device
        do_classifier_free_guidance = guidance_scale > 1.0

        # 2. encode conditioning (once per input image, then repeated per sample)
        image_embeds, condition_latents = self._encode_images(images.to(device))  # once for every branch
        tokens = self.pose_projection(image_embeds, pose.to(image_embeds.device))
        # Read once: `ModelMixin.dtype` walks every parameter of the UNet on each access.
        dtype = self.unet.dtype
        tokens = tokens.repeat_interleave(num_images_per_prompt, dim=0).to(dtype)
        condition_latents = condition_latents.repeat_interleave(num_images_per_prompt, dim=0).to(dtype)
        # None unless the UNet embeds the pose; with an estimator, the target's estimated azimuth follows it
        pose = pose.to(device)
        estimate = None
        if self.azimuth_estimator is not None:  # once per input image, like the encodings above
            estimate = self.azimuth_estimator(condition_latents[::num_images_per_prompt])

        def branch(branch_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
            """One guidance branch's per-sample pose and the UNet's class labels for it."""
            features = None if estimate is None else target_view_features(estimate, branch_pose)
            if features is not None:
                features = features.repeat_interleave(num_images_per_prompt, dim=0)
            per_sample = branch_pose.repeat_interleave(num_images_per_prompt, dim=0)
            labels = pose_class_labels(self.unet, per_sample, features)
            return per_sample, None if labels is None else labels.to(dtype)

        sample_pose, class_labels = branch(pose)
        # contrast branches: the same request with one part changed, each guided away from with its weight;
        # one equal to the request itself (every d_el == 0 for the depression) adds exactly 0 and is skipped
        candidates = (
            ("heading", heading_guidance_scale, flipped_heading_pose(pose)),
            ("depression", depression_guidance_scale, same_depression_pose(pose)),
        )
        kept = [c for c in candidates if c[1] > 0.0 and not torch.equal(c[2], pose)]
        contrasts = [(scale, contrast_pose) for _, scale, contrast_pose in kept]
        contrast_kinds = [kind for kind, _, _ in kept]
        if do_classifier_free_guidance:
            # zero-1-to-3's sampling null: zeros after the projection and for the condition latent; the
            # pose itself is never dropped
            tokens = torch.cat([torch.zeros_like(tokens), tokens])
            condition_latents = torch.cat([torch.zeros_like(condition_latents), condition_latents])
            if class_labels is not None:
                class_labels = torch.cat([class_labels, class_labels])
        # the condition latent (zeros for the null), turned by the pose where the model takes it spatially
        guided_pose = torch.cat([sample_pose] * 2) if do_classifier_free_guidance else sample_pose
        for _, contrast_pose in contrasts:  # [null;] cond; then one block per contrast branch
            contrast_tokens = self.pose_projection(image_embeds, contrast_pose.to(image_embeds.device))
            contrast_tokens = contrast_tokens.repeat_interleave(num_images_per_prompt, dim=0).to(dtype)
            contrast_sample_pose, contrast_labels = branch(contrast_pose)
            tokens = torch.cat([tokens, contrast_tokens])
            condition_latents = torch.cat([condition_latents, condition_latents[-num_samples:]])
            if class_labels is not None:
                class_labels = torch.cat([class_labels, contrast_labels])
            guided_pose = torch.cat([guided_pose, contrast_sample_pose])
        branches = 1 + int(do_classifier_free_guidance) + len(contrasts)
        proxy_latents = None
        if proxy_model:  # the proxy pair of each branch's request (the null keeps the request's: a pose)
            proxy_latents = self._proxy_latents(
                images, d_az, d_el, proxy_views, contrast_kinds, input_azimuth_deg, input_depression_deg
            ).to(dtype)
            proxy_latents = proxy_latents.repeat_interleave(num_images_per_prompt, dim=1).flatten(0, 1)
            if do_classifier_free_guidance:
                proxy_latents = torch.cat([proxy_latents[:num_samples], proxy_latents])
        unet_condition = unet_condition_latents(
            condition_latents, guided_pose, self.pose_projection, proxy_latents
        )
        reference = contextlib.nullcontext()
        if uses_reference(self.pose_projection):  # once per call: the input's own features
            reference = self._input_reference(
                image_embeds, pose, branch, condition_latents[-num_samples:], proxy_latents,
                num_images_per_prompt, branches, do_classifier_free_guidance,
            )  # fmt: skip

        # 3. timesteps
        self.scheduler.set_timesteps(int(num_inference_steps), device=device)
        timesteps = self.scheduler.timesteps
        if denoising_steps < num_inference_steps:  # strength < 1: the last denoising_steps only
            start = (int(num_inference_steps) - denoising_steps) * self.scheduler.order
            timesteps = timesteps[start:]
            if hasattr(self.scheduler, "set_begin_index"):
                self.scheduler.set_begin_index(start)

        # 4. initial noise
        shape = (num_samples, self.vae.config.latent_channels, *condition_latents.shape[-2:])
        if latents is None:
            latents = randn_tensor(shape, generator=generator, device=device, dtype=dtype)
        else:
            if tuple(latents.shape) != shape:
                raise ValueError(f"`latents` must have shape {shape}, got {tuple(latents.shape)}")
            if not torch.isfinite(latents).all():
                raise ValueError("`latents` contains NaN or inf values")
            latents = latents.to(device=device, dtype=dtype)
        if denoising_steps < num_inference_steps:  # the input's own latent, noised to the first timestep
            start_latents = condition_latents[-num_samples:]
            if start_images is not None:
                start_latents = encode_condition_latents(self.vae, start_images.to(device))
                start_latents = start_latents.repeat_interleave(num_images_per_prompt, dim=0).to(dtype)
            elif start_from == "turned_input":
                rotation_sign = self.pose_projection.config.rotation_sign
                start_latents = rotate_condition_latents(start_latents, sample_pose, rotation_sign)
            start_latents = start_latents * self.vae.config.scaling_factor
            latents = self.scheduler.add_noise(start_latents, latents, timesteps[:1].repeat(num_samples))
        else:
            latents = latents * self.scheduler.init_noise_sigma
        step_kwargs = self._scheduler_step_kwargs(generator)

        # 5. denoising loop: one UNet call per step with [unconditional; conditional] stacked
        self._num_timesteps = len(timesteps)
        with self.progress_bar(total=len(timesteps)) as progress_bar, reference:
            for step_index, timestep in enumerate(timesteps):
                model_input = torch.cat([latents] * branches) if branches > 1 else latents
                model_input = self.scheduler.scale_model_input(model_input, timestep)
                model_input = torch.cat([model_input, unet_condition], dim=1)  # (N..3N, 8 | 12, h, w)
                noise_pred = self.unet(
                    model_input, timestep, encoder_hidden_states=tokens, class_labels=class_labels
                ).sample
                parts = list(noise_pred.chunk(branches))
                noise_contrasts = parts[len(parts) - len(contrasts) :]
                parts = parts[: len(parts) - len(contrasts)]
                if do_classifier_free_guidance:
                    noise_uncond, noise_cond = parts
                    noise_pred = noise_uncond + guidance_scale * (noise_cond - noise_uncond)
                else:
                    noise_cond = noise_pred = parts[0]
                for (scale, _), noise_contrast in zip(contrasts, noise_contrasts, strict=True):
                    noise_pred = noise_pred + scale * (noise_cond - noise_contrast)
                latents = self.scheduler.step(noise_pred, timestep, latents, **step_kwargs).prev_sample
                latents = latents.to(dtype)

                if callback_on_step_end is not None:
                    step_tensors = {"latents": latents}
                    callback_kwargs = {k: step_tensors[k] for k in callback_on_step_end_tensor_inputs}
                    callback_outputs = callback_on_step_end(self, step_index, timestep, callback_kwargs)
                    latents = self._callback_latents(callback_outputs, latents)
                progress_bar.update()

        # 6. decode to single-channel normalised dB; never return NaN or inf as an image
        self._check_finite_output(latents, "latents", guidance_scale)
        if output_type == "latent":
            output: Any = latents
        else:
            decoded = self.decode_latents(latents)  # (N, 1, H, W)
            self._check_finite_output(decoded, "decoded images", guidance_scale)
            if output_type == "pt":
                output = decoded
            else:
                array = decoded.permute(0, 2, 3, 1).cpu().numpy()  # (N, H, W, 1)
                output = array if output_type == "np" else _to_pil(array)
        self.maybe_free_model_hooks()
        if not return_dict:
            return (output,)
        scores = None
        if fitted:  # the fits this call ran, remembered by the proxy module: read back, not run again
            depression = _per_input_angles(input_depression_deg, "input_depression_deg", batch_size)
            proxy = _anchored_proxy(self.config.proxy, self.config.get("_name_or_path"))
            scores = fit_scores(images, input_azimuth_deg, depression, proxy)
        return SARZero123PipelineOutput(images=output, proxy_fit_scores=scores)

    def _input_reference(
        self,
        image_embeds: torch.Tensor,
        pose: torch.Tensor,
        branch: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]],
        condition_latents: torch.Tensor,
        proxy_latents: torch.Tensor | None,
        num_images_per_prompt: int,
        branches: int,
        do_classifier_free_guidance: bool,
    ) -> contextlib.AbstractContextManager:
        """The reference pass (:mod:`..reference_attention`) and the context in which every branch but the
        null attends to its input's features.

        Args:
            condition_latents: One per output sample, the real inputs' (not the null).
            proxy_latents: The branches' proxy pairs (their first half: the proxy at the input's pose).
        """
        own = own_pose(pose)
        tokens = self.pose_projection(image_embeds, own.to(image_embeds.device))
        tokens = tokens.repeat_interleave(num_images_per_prompt, dim=0).to(condition_latents.dtype)
        own_sample_pose, own_labels = branch(own)
        proxy_at_input = None
        if proxy_latents is not None:
            proxy_at_input = proxy_latents[-condition_latents.shape[0] :, : condition_latents.shape[1]]
        features = input_reference(
            self.unet, self.pose_projection, condition_latents, own_sample_pose, tokens, own_labels,
            self.vae.config.scaling_factor, proxy_at_input,
        )  # fmt: skip
        num_samples = condition_latents.shape[0]
        rows = torch.arange(num_samples, device=condition_latents.device).repeat(branches)
        keep = torch.ones(branches * num_samples, dtype=torch.bool)
        if do_classifier_free_guidance:  # the null runs without the reference
            keep[:num_samples] = False
        weights = reference_weights(self.pose_projection, keep).detach()
        return attending_to_reference(self.unet, features, rows, weights)

    @torch.no_grad()
    def _proxy_drafts(
        self,
        images: torch.Tensor,
        d_az: float | Sequence[float] | torch.Tensor,
        d_el: float | Sequence[float] | torch.Tensor,
        input_azimuth_deg: torch.Tensor | None,
        input_depression_deg: float | Sequence[float] | torch.Tensor | None,
        why: str = "start_from='proxy'",
    ) -> torch.Tensor:
        """Each input's simulator proxy at the requested pose (``start_from="proxy"``, :mod:`..proxy`).

        Args:
            input_azimuth_deg: One checked azimuth per input (:func:`_per_input_angles`), or ``None``.

        Raises:
            ValueError: Naming what to pass, where the pipeline records no proxy, or the input's depression
                or azimuth is not given.
        """
        start = why.startswith("start_from")
        proxy = _anchored_proxy(getattr(self.config, "proxy", None), self.config.get("_name_or_path"))
        if proxy is None:
            raise ValueError(
                f"{why}: this pipeline records no proxy settings (pipe.config.proxy); build it with "
                "proxy=sar_zero123.model.proxy.DEFAULT_PROXY" + (", or start from 'input'" if start else "")
            )
        batch_size = images.shape[0]
        if input_depression_deg is None:
            raise ValueError(
                f"`input_depression_deg`: {why} fits a simulator vehicle at the input's pose; give the "
                "input chip's depression in degrees (its metadata)"
                + (", or start from 'input'" if start else "")
            )
        depression = _per_input_angles(input_depression_deg, "input_depression_deg", batch_size)
        if input_azimuth_deg is None:
            # an estimated azimuth is no substitute: the bundled estimator is 63 deg off on unseen vehicles
            # and fitting the heading to it turns the proxy wrong more often (docs/results/proxy.md)
            raise ValueError(
                f"`input_azimuth_deg`: {why} fits a simulator vehicle at the input's pose; give each "
                "input chip's absolute azimuth in degrees (its metadata, or an estimate you trust)"
                + (", or start from 'input'" if start else "")
            )
        d_az_values = as_angle_tensor(d_az, "d_az").expand(batch_size)
        d_el_values = as_angle_tensor(d_el, "d_el").expand(batch_size)
        drafts, _ = draft_target_views(images, input_azimuth_deg, depression, d_az_values, d_el_values, proxy)
        return drafts

    @torch.no_grad()
    def _proxy_latents(
        self,
        images: torch.Tensor,
        d_az: float | Sequence[float] | torch.Tensor,
        d_el: float | Sequence[float] | torch.Tensor,
        proxy_views: torch.Tensor | None,
        contrast_kinds: Sequence[str],
        input_azimuth_deg: torch.Tensor | None,
        input_depression_deg: float | Sequence[float] | torch.Tensor | None,
    ) -> torch.Tensor:
        """The proxy pair of the request and of each contrast branch, for a ``spatial_pose="proxy"`` UNet.

        Each input's proxy is fitted once (:mod:`..proxy`) and rendered at the input's pose and at each
        branch's request: the request itself, then each contrast's (``"heading"``: ``d_az + 180``;
        ``"depression"``: ``d_el = 0``), so that a contrast branch sees its own proxy. Given ``proxy_views``
        (each input's proxy at its pose and at the request), every branch takes them.

        Returns:
            ``(1 + len(contrast_kinds), B, 2C, h, w)``.
        """
        device = self._execution_device
        if proxy_views is not None:
            views = proxy_views.to(device=device, dtype=torch.float32)
            pair = proxy_pair_latents(self.vae, views[:, :1], views[:, 1:2])
            flipped = pair
            if views.shape[1] == 3:  # the proxy at the flipped heading, for the heading contrast
                flipped = proxy_pair_latents(self.vae, views[:, :1], views[:, 2:3])
            return torch.stack([pair] + [flipped if kind == "heading" else pair for kind in contrast_kinds])
        batch_size = images.shape[0]
        d_az_values = as_angle_tensor(d_az, "d_az").expand(batch_size)
        d_el_values = as_angle_tensor(d_el, "d_el").expand(batch_size)
        zeros = torch.zeros_like(d_el_values)
        requests = [(torch.zeros_like(d_az_values), zeros), (d_az_values, d_el_values)]  # input pose, request
        for kind in contrast_kinds:
            requests.append((d_az_values + 180.0, d_el_values) if kind == "heading" else (d_az_values, zeros))
        # one call, each chip's requests side by side: one fit per chip however large the batch (the fit
        # cache keeps the last 1,024), and one VAE encoding of every render
        count = len(requests)
        d_az_all = torch.stack([az for az, _ in requests], dim=1).reshape(-1)  # (B * R,), chip-major
        d_el_all = torch.stack([el for _, el in requests], dim=1).reshape(-1)
        if input_depression_deg is not None:
            depression = _per_input_angles(input_depression_deg, "input_depression_deg", batch_size)
            input_depression_deg = depression.repeat_interleave(count)
        if input_azimuth_deg is not None:
            input_azimuth_deg = input_azimuth_deg.repeat_interleave(count)
        drafts = self._proxy_drafts(
            images.repeat_interleave(count, dim=0), d_az_all, d_el_all, input_azimuth_deg,
            input_depression_deg, "spatial_pose='proxy'",
        )  # fmt: skip
        latents = encode_condition_latents(self.vae, drafts.to(device))
        latents = latents.reshape(batch_size, count, *latents.shape[1:])
        return torch.stack([torch.cat([latents[:, 0], latents[:, r]], dim=1) for r in range(1, count)])

    def _pose_with_depression(
        self,
        pose: torch.Tensor,
        d_el: float | Sequence[float] | torch.Tensor,
        input_depression_deg: float | Sequence[float] | torch.Tensor | None,
    ) -> torch.Tensor:
        """``pose`` with the input's depression in its fourth entry when the pipeline takes it, after
        checking the request against the ranges the pipeline was trained on.

        Raises:
            ValueError: naming the argument, for a missing, non-finite or mis-sized input depression, or a
                ``d_el``, input depression or target depression outside the trained range.
        """
        config = self.pose_projection.config
        batch_size = pose.shape[0]
        # on the CPU, as as_angle_tensor's angles: an evaluation's pair batch arrives on the accelerator
        d_el_values = torch.as_tensor(d_el, dtype=torch.float64).cpu().reshape(-1).expand(batch_size)
        depression = None
        if input_depression_deg is not None:
            _check_real_angles(input_depression_deg, "input_depression_deg")
            depression = as_angle_tensor(input_depression_deg, "input_depression_deg").double().reshape(-1)
            if depression.numel() not in (1, batch_size):
                raise ValueError(
                    f"`input_depression_deg` has {depression.numel()} values; expected 1 or one per input "
                    f"image ({batch_size})"
                )
            if float(depression.min()) <= 0.0 or float(depression.max()) >= 90.0:
                raise ValueError(
                    f"`input_depression_deg` must lie in (0, 90) degrees, got {depression.tolist()}"
                )
            depression = depression.expand(batch_size)
        elif getattr(config, "input_depression", False):
            raise ValueError(
                "`input_depression_deg`: this pipeline's pose carries the input chip's absolute depression "
                "(pose_projection.config.input_depression); give it in degrees, from the chip's metadata"
            )
        trained_d_el = getattr(config, "trained_d_el_deg", None)
        if trained_d_el is not None:
            low, high = float(trained_d_el[0]), float(trained_d_el[1])
            if float(d_el_values.min()) < low - 1e-6 or float(d_el_values.max()) > high + 1e-6:
                raise ValueError(
                    f"`d_el` must lie in the trained range [{low:g}, {high:g}] degrees "
                    f"(pose_projection.config.trained_d_el_deg), got {sorted(set(d_el_values.tolist()))}"
                )
        trained_depression = getattr(config, "trained_depression_deg", None)
        if trained_depression is not None and depression is not None:
            low, high = float(trained_depression[0]), float(trained_depression[1])
            for name, values in (
                ("input_depression_deg", depression),
                ("input_depression_deg + d_el", depression + d_el_values),
            ):
                if float(values.min()) < low - 1e-6 or float(values.max()) > high + 1e-6:
                    raise ValueError(
                        f"`{name}` must lie in the trained depression range [{low:g}, {high:g}] degrees "
                        f"(pose_projection.config.trained_depression_deg), got {sorted(set(values.tolist()))}"
                    )
        if not getattr(config, "input_depression", False):
            return pose
        pose = pose.clone()
        pose[:, 0, 3] = torch.deg2rad(depression).to(pose.dtype)
        return pose


# ------------------------------------------------------------------------------------- helpers
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


def flipped_heading_pose(pose: torch.Tensor) -> torch.Tensor:
    """The same pose with the azimuth change turned by 180 deg: ``sin d_az`` and ``cos d_az`` negated.

    Shape:
        ``(B, 1, 4)`` (:func:`embed_pose`) -> the same.
    """
    flipped = pose.clone()
    flipped[..., 1:3] = -flipped[..., 1:3]
    return flipped


def same_depression_pose(pose: torch.Tensor) -> torch.Tensor:
    """The same pose at the input's own depression: the depression change ``d_el`` (first entry) set to 0.

    Shape:
        ``(B, 1, 4)`` (:func:`embed_pose`) -> the same.
    """
    same = pose.clone()
    same[..., 0] = 0.0
    return same


#: Files of a pipeline folder that loading may read (weights, configs, scaling): one that its manifest does
#: not list is named in a warning.
_SEALED_SUFFIXES = (".json", ".safetensors", ".bin", ".pt", ".pth", ".ckpt", ".pkl", ".py", ".msgpack")


def _anchored_proxy(proxy: Mapping[str, Any] | None, folder: str | None) -> Mapping[str, Any] | None:
    """A pipeline's proxy settings with a relative ``retrieval`` folder read against the pipeline's own
    folder (where it was loaded from), never against the working directory; names and absolute paths as
    recorded."""
    retrieval = None if proxy is None else proxy.get("retrieval")
    if (
        not isinstance(retrieval, str)
        or retrieval.startswith(BUNDLED_NAMESPACE)
        or os.path.isabs(retrieval)
        or not (isinstance(folder, str) and os.path.isdir(folder))
    ):
        return proxy
    return {**proxy, "retrieval": os.path.join(folder, retrieval)}


def _check_manifest(folder: str | os.PathLike, verify: bool) -> None:
    """Refuse (``verify``) or warn about a pipeline folder whose files differ from its ``manifest.json``."""
    if not (Path(folder) / MANIFEST_FILE).is_file():
        logger.warning(
            "pipeline %s has no %s (saved before manifests): its files are loaded unchecked; "
            "save it again with save_pretrained to seal it", folder, MANIFEST_FILE,
        )  # fmt: skip
        return
    added = [name for name in unlisted_files(folder) if name.endswith(_SEALED_SUFFIXES)]
    if added:  # files beside the sealed ones (a scaling written after save_pretrained): loaded, named
        logger.warning("pipeline %s: %s not in its %s (added after it was saved)", folder, added,
                       MANIFEST_FILE)  # fmt: skip
    problem = manifest_problem(folder)
    if problem is None:
        return
    if verify:
        raise ValueError(
            f"pipeline {os.fspath(folder)!r}: {problem}. A pipeline's files are loaded only as they were "
            "saved; pass verify_manifest=False to load it anyway"
        )
    logger.warning("pipeline %s loaded with verify_manifest=False although %s", folder, problem)


def _refuse_a_missing_local_name(text: str) -> None:
    """Refuse, listing the bundled pipelines, a name that is meant as a local folder or a bundled pipeline but
    is neither (a hub lookup would answer with a network error naming neither).

    Raises:
        FileNotFoundError: For a path-like name (``./x``, ``../x``, ``/x``, ``~/x``), a bundled name in
            another case (``SAR-ZERO123/sim-prior``) or without its namespace (``sim-prior-rotated``).
    """
    bundled = sorted(BUNDLED_PIPELINES)
    listing = f"the bundled pipelines are {bundled}"
    short_names = {name.split("/")[-1] for name in bundled}
    if text.lower().startswith(BUNDLED_NAMESPACE.lower()) or text in short_names:
        matches = [name for name in bundled if name.lower() == text.lower() or name.endswith("/" + text)]
        hint = f"did you mean {matches[0]!r}? " if matches else ""
        raise FileNotFoundError(f"{text!r} is neither a pipeline folder nor a bundled name: {hint}{listing}")
    if text.startswith(("./", "../", "/", "~", ".\\")) or text in (".", ".."):
        raise FileNotFoundError(f"{text!r}: no such pipeline folder (a save_pretrained folder); {listing}")


def _per_input_angles(value: Any, name: str, batch_size: int) -> torch.Tensor:
    """Angles given as a scalar or one per input image, checked and broadcast to ``(batch_size,)`` float64.

    Raises:
        ValueError: Naming ``name``, for non-real or non-finite angles or a count other than 1 or the batch.
    """
    _check_real_angles(value, name)
    tensor = as_angle_tensor(value, name)
    if tensor.numel() not in (1, batch_size):
        raise ValueError(f"`{name}` has {tensor.numel()} values; expected 1 or one per input ({batch_size})")
    return tensor.expand(batch_size)


def _broadcast_pose(
    d_az: float | Sequence[float] | torch.Tensor,
    d_el: float | Sequence[float] | torch.Tensor,
    batch_size: int,
) -> torch.Tensor:
    """Pose vectors for a batch, checking that each angle is a scalar or has one value per image, real,
    and physically possible."""
    for name, value in (("d_az", d_az), ("d_el", d_el)):
        _check_real_angles(value, name)
        count = as_angle_tensor(value, name).numel()  # checked under the pipeline's own argument names
        if count not in (1, batch_size):
            raise ValueError(f"`{name}` has {count} values; expected 1 or one per input image ({batch_size})")
    pose = embed_pose(d_az, d_el)  # (1 | B, 1, 4); cannot fail on angles that passed the checks above
    for name, value, limit, why in (
        ("d_el", d_el, MAX_ABS_D_EL_DEG, "a difference of two depression angles in [0, 90]"),
        ("d_az", d_az, MAX_ABS_D_AZ_DEG, "larger values lose the angle's precision: a unit error?"),
    ):
        largest = float(torch.as_tensor(value, dtype=torch.float64).abs().max())
        if largest > limit:
            raise ValueError(f"`{name}` must lie in [-{limit:g}, {limit:g}] degrees ({why}), got {largest:g}")
    return pose.expand(batch_size, -1, -1) if pose.shape[0] == 1 else pose


def _check_real_angles(value: Any, name: str) -> None:
    """Angles are real numbers (a scalar, a sequence of them, or a real tensor/array).

    Raises:
        TypeError: naming the argument, for strings, ``None``, booleans, complex numbers and the like.
    """
    if isinstance(value, torch.Tensor):
        if value.dtype == torch.bool or value.dtype.is_complex:
            raise TypeError(f"`{name}` must hold real angles in degrees, got dtype {value.dtype}")
        return
    if isinstance(value, np.ndarray):
        if not (np.issubdtype(value.dtype, np.integer) or np.issubdtype(value.dtype, np.floating)):
            raise TypeError(f"`{name}` must hold real angles in degrees, got dtype {value.dtype}")
        return
    items = list(value) if isinstance(value, list | tuple) else [value]
    for item in items:
        if isinstance(item, bool) or not isinstance(item, numbers.Real):
            raise TypeError(
                f"`{name}` must be a real number of degrees or a list of them, got {type(item).__name__} "
                f"{item!r}"
            )


def _to_pil(array: np.ndarray) -> list[PIL.Image.Image]:
    """(N, H, W, 1) float in [0, 1] -> list of 8-bit single-channel PIL images."""
    return [PIL.Image.fromarray((a[..., 0] * 255.0).round().astype(np.uint8), mode="L") for a in array]


# diffusers resolves the `_class_name` of model_index.json inside its own namespace
# (`_get_pipeline_class` in diffusers 0.42), so a saved SAR pipeline would only load through
# `SARZero123Pipeline.from_pretrained`. Registering the class there lets the generic
# `DiffusionPipeline.from_pretrained(folder)` load it too, once `sar_zero123` is imported, without
# `trust_remote_code` or code copied into the folder.
if getattr(diffusers, SARZero123Pipeline.__name__, None) is None:
    setattr(diffusers, SARZero123Pipeline.__name__, SARZero123Pipeline)
