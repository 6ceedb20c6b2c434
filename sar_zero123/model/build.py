"""Named model sizes (:data:`SAR_ZERO123_SIZES`, :func:`build_sar_zero123`), from ``tiny`` (unit tests) to
``zero123`` (the Objaverse zero-1-to-3 shapes), and replacing a pipeline's VAE.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Literal

import torch
from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

from sar_zero123.data import ViewPairDataset
from sar_zero123.model.conditioning import POSE_DIM, PoseProjection, downsampling_factor
from sar_zero123.model.loading import PIPELINE_SETTINGS, load_component
from sar_zero123.model.orientation import AZIMUTH_DIM, AzimuthEstimator
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.pipeline_checks import check_vae_image_size
from sar_zero123.model.spatial_pose import condition_channels
from sar_zero123.model.zero123_checkpoints import (
    SD_VAE_SCALING_FACTOR,
    ZERO123_SCHEDULER_CONFIG,
    CLIPImageProcessor,
)
from sar_zero123.pretrained import resolve_pretrained

__all__ = [
    "SAR_ZERO123_SIZES",
    "build_sar_zero123",
    "check_vae_fits",
    "load_sar_zero123",
    "record_trained_pose_ranges",
    "replace_vae",
    "same_weights",
]

SAR_ZERO123_SIZES: dict[str, dict[str, Any]] = {
    # Unit tests: 32 px chips, 16x16x4 latents; well under 1 M parameters in total.
    "tiny": {
        "image_size": 32,
        "vae": {
            "in_channels": 1,
            "out_channels": 1,
            "down_block_types": ("DownEncoderBlock2D",) * 2,
            "up_block_types": ("UpDecoderBlock2D",) * 2,
            "block_out_channels": (16, 32),
            "layers_per_block": 1,
            "latent_channels": 4,
            "norm_num_groups": 8,
        },
        "unet": {
            "block_out_channels": (16, 32),
            "layers_per_block": 1,
            "down_block_types": ("CrossAttnDownBlock2D", "DownBlock2D"),
            "up_block_types": ("UpBlock2D", "CrossAttnUpBlock2D"),
            "cross_attention_dim": 16,
            "attention_head_dim": 4,
            "norm_num_groups": 8,
        },
        "image_encoder": {
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 4,
            "image_size": 32,
            "patch_size": 8,
            "projection_dim": 16,
        },
    },
    # 64 px CPU model: 1-channel VAE (64 px -> 16x16x4 latents), three-level UNet, small ViT from scratch.
    "small": {
        "image_size": 64,
        "vae": {
            "in_channels": 1,
            "out_channels": 1,
            "down_block_types": ("DownEncoderBlock2D",) * 3,
            "up_block_types": ("UpDecoderBlock2D",) * 3,
            "block_out_channels": (32, 64, 128),
            "layers_per_block": 2,
            "latent_channels": 4,
            "norm_num_groups": 32,
        },
        "unet": {
            "block_out_channels": (64, 128, 256),
            "layers_per_block": 2,
            "down_block_types": ("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
            "up_block_types": ("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
            "cross_attention_dim": 256,
            "attention_head_dim": 8,
            "norm_num_groups": 32,
        },
        "image_encoder": {
            "hidden_size": 256,
            "intermediate_size": 1024,
            "num_hidden_layers": 4,
            "num_attention_heads": 4,
            "image_size": 64,
            "patch_size": 8,
            "projection_dim": 256,
        },
    },
    # Faster CPU models with `small`'s VAE: UNets of about a third (`compact`) and a tenth (`micro`) of
    # `small`'s parameters.
    "compact": {
        "image_size": 64,
        "vae": "small",
        "unet": {
            "block_out_channels": (64, 128, 128),
            "layers_per_block": 1,
            "down_block_types": ("DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D"),
            "up_block_types": ("CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"),
            "cross_attention_dim": 128,
            "attention_head_dim": 8,
            "norm_num_groups": 32,
        },
        "image_encoder": {
            "hidden_size": 128,
            "intermediate_size": 512,
            "num_hidden_layers": 2,
            "num_attention_heads": 4,
            "image_size": 64,
            "patch_size": 8,
            "projection_dim": 128,
        },
    },
    "micro": {
        "image_size": 64,
        "vae": "small",
        "unet": {
            "block_out_channels": (32, 64, 64),
            "layers_per_block": 1,
            "down_block_types": ("DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D"),
            "up_block_types": ("CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"),
            "cross_attention_dim": 64,
            "attention_head_dim": 8,
            "norm_num_groups": 16,
        },
        "image_encoder": {
            "hidden_size": 64,
            "intermediate_size": 256,
            "num_hidden_layers": 2,
            "num_attention_heads": 4,
            "image_size": 64,
            "patch_size": 8,
            "projection_dim": 64,
        },
    },
    # A GPU-sized prior with `small`'s latent shape and `compact`'s image encoder.
    "medium": {
        "image_size": 64,
        "vae": "small",
        "unet": {
            "block_out_channels": (64, 128, 192),
            "layers_per_block": 1,
            "down_block_types": ("DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D"),
            "up_block_types": ("CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"),
            "cross_attention_dim": 128,
            "attention_head_dim": 8,
            "norm_num_groups": 32,
        },
        "image_encoder": "compact",
    },
    # The Objaverse zero-1-to-3 shapes: SD 1.x UNet (8 inputs), SD VAE, CLIP ViT-L/14, Linear(772, 768).
    "zero123": {
        "image_size": 256,
        "vae": {
            "in_channels": 3,
            "out_channels": 3,
            "down_block_types": ("DownEncoderBlock2D",) * 4,
            "up_block_types": ("UpDecoderBlock2D",) * 4,
            "block_out_channels": (128, 256, 512, 512),
            "layers_per_block": 2,
            "latent_channels": 4,
            "norm_num_groups": 32,
        },
        "unet": {
            "block_out_channels": (320, 640, 1280, 1280),
            "layers_per_block": 2,
            "down_block_types": ("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
            "up_block_types": ("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3,
            "cross_attention_dim": 768,
            "attention_head_dim": 8,
            "norm_num_groups": 32,
        },
        "image_encoder": {
            "hidden_size": 1024,
            "intermediate_size": 4096,
            "num_hidden_layers": 24,
            "num_attention_heads": 16,
            "image_size": 224,
            "patch_size": 14,
            "projection_dim": 768,
            "hidden_act": "quick_gelu",
        },
    },
}

for _spec in SAR_ZERO123_SIZES.values():  # a size may share another size's VAE (then one VAE fits both)
    for _part in ("vae", "image_encoder"):  # ... or its image encoder
        if isinstance(_spec[_part], str):
            _spec[_part] = SAR_ZERO123_SIZES[_spec[_part]][_part]


def build_sar_zero123(
    size: str,
    image_size: int | None = None,
    seed: int = 0,
    pose_in_time_embedding: bool = False,
    estimate_input_azimuth: bool = False,
    input_code_dim: int = 16,
    input_depression: bool = False,
    spatial_pose: str | None = None,
) -> SARZero123Pipeline:
    """Build a randomly initialised :class:`SARZero123Pipeline` of a named size.

    Each component is initialised from ``torch.manual_seed(seed)`` inside ``torch.random.fork_rng``: the
    result depends only on ``seed`` and the global RNG state is left untouched.

    Args:
        size: A key of :data:`SAR_ZERO123_SIZES` (``"zero123"``: load real weights with
            :meth:`SARZero123Pipeline.from_zero123`).
        image_size: Chip size in pixels (the VAE's and UNet's ``sample_size``); defaults to the size's own.
        seed: Initialisation seed.
        pose_in_time_embedding: Also add a projection of the pose to the UNet's timestep embedding
            (:func:`~sar_zero123.model.conditioning.pose_class_labels`).
        estimate_input_azimuth: Also build an :class:`~sar_zero123.model.orientation.AzimuthEstimator`
            whose estimate follows the pose there (implies ``pose_in_time_embedding``).
        input_code_dim: The estimator's input-view code size.
        input_depression: The pose's fourth entry is the input's absolute depression.
        spatial_pose: The pose projection's ``spatial_pose`` (``None``: zero-1-to-3's input).

    Returns:
        The pipeline (float32, CPU) with a zero-1-to-3 DDIM scheduler.

    Raises:
        ValueError: If ``size`` is unknown or ``image_size`` is not a positive multiple of the
            model's total downsampling factor.
    """
    if size not in SAR_ZERO123_SIZES:
        raise ValueError(f"`size` must be one of {sorted(SAR_ZERO123_SIZES)}, got {size!r}")
    spec = SAR_ZERO123_SIZES[size]
    vae_factor = downsampling_factor(spec["vae"]["block_out_channels"])
    multiple = vae_factor * downsampling_factor(spec["unet"]["block_out_channels"])
    image_size = spec["image_size"] if image_size is None else image_size
    if not isinstance(image_size, int) or image_size < multiple or image_size % multiple:
        raise ValueError(
            f"`image_size` must be a positive multiple of {multiple} for size {size!r}, got {image_size}"
        )
    latent_channels = spec["vae"]["latent_channels"]
    clip_config = CLIPVisionConfig(**spec["image_encoder"])
    cross_attention_dim = spec["unet"]["cross_attention_dim"]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        vae = AutoencoderKL(**spec["vae"], sample_size=image_size, scaling_factor=SD_VAE_SCALING_FACTOR)
        torch.manual_seed(seed)
        pose_inputs = POSE_DIM + (AZIMUTH_DIM + input_code_dim if estimate_input_azimuth else 0)
        pose_embedding = (
            {"class_embed_type": "projection", "projection_class_embeddings_input_dim": pose_inputs}
            if pose_in_time_embedding or estimate_input_azimuth
            else {}
        )
        unet = UNet2DConditionModel(
            **spec["unet"],
            **pose_embedding,
            sample_size=image_size // vae_factor,
            in_channels=latent_channels + condition_channels(spatial_pose, latent_channels),
            out_channels=latent_channels,
        )
        torch.manual_seed(seed)
        image_encoder = CLIPVisionModelWithProjection(clip_config)
        # nn.Linear draws its default init before PoseProjection overwrites it: keep that inside too.
        pose_projection = PoseProjection(
            clip_config.projection_dim + POSE_DIM, cross_attention_dim, input_depression=input_depression,
            spatial_pose=spatial_pose,
        )
        azimuth_estimator = None
        if estimate_input_azimuth:
            torch.manual_seed(seed)
            azimuth_estimator = AzimuthEstimator(latent_channels, code_dim=input_code_dim).eval()
    feature_extractor = None
    if size == "zero123":
        feature_extractor = CLIPImageProcessor(
            size={"shortest_edge": 224}, crop_size={"height": 224, "width": 224}, do_center_crop=True
        )
    return SARZero123Pipeline(
        vae=vae.eval(),
        image_encoder=image_encoder.eval(),
        unet=unet.eval(),
        scheduler=DDIMScheduler(**ZERO123_SCHEDULER_CONFIG),
        pose_projection=pose_projection.eval(),
        feature_extractor=feature_extractor,
        azimuth_estimator=azimuth_estimator,
    )


def load_sar_zero123(
    pretrained: str | os.PathLike | None,
    *,
    size: str = "small",
    image_size: int | None = None,
    seed: int = 0,
    pose_in_time_embedding: bool = False,
    estimate_input_azimuth: bool = False,
    input_code_dim: int = 16,
    prediction_type: Literal["epsilon", "v_prediction"] | None = None,
    vae: str | os.PathLike | None = None,
    input_depression: bool = False,
    spatial_pose: str | None = None,
) -> SARZero123Pipeline:
    """The pipeline a run starts from: a saved or zero-1-to-3 checkpoint, or a new model of a named size.

    Args:
        pretrained: A ``save_pretrained`` folder, a bundled pipeline's name, any zero-1-to-3 layout, or
            ``None`` to :func:`build_sar_zero123` (with ``size`` ... ``spatial_pose``).
        prediction_type: Replace the scheduler's prediction type (meaningful for a new model only).
        vae: An ``AutoencoderKL`` folder replacing the pipeline's VAE (:func:`replace_vae`).

    Raises:
        FileNotFoundError: If ``pretrained`` or ``vae`` does not exist, or a bundled pipeline's weights
            are missing from this install.
        ValueError: If the VAE does not fit the UNet (:func:`check_vae_fits`).
    """
    if pretrained is None:
        pipe = build_sar_zero123(
            size,
            image_size=image_size,
            seed=seed,
            pose_in_time_embedding=pose_in_time_embedding,
            estimate_input_azimuth=estimate_input_azimuth,
            input_code_dim=input_code_dim,
            input_depression=input_depression,
            spatial_pose=spatial_pose,
        )
    else:
        path = resolve_pretrained(pretrained)
        if not path.exists():
            raise FileNotFoundError(f"pretrained: no such file or folder {str(path)!r}")
        if (path / "model_index.json").is_file():
            pipe = SARZero123Pipeline.from_pretrained(path)
        else:
            pipe = SARZero123Pipeline.from_zero123(path)
    if prediction_type is not None:
        scheduler_class = type(pipe.scheduler)
        pipe.scheduler = scheduler_class.from_config(pipe.scheduler.config, prediction_type=prediction_type)
    return pipe if vae is None else replace_vae(pipe, vae)


def check_vae_fits(vae: AutoencoderKL, pipe: SARZero123Pipeline, name: str = "vae") -> None:
    """Refuse a VAE that cannot replace ``pipe.vae`` (``name`` in the message).

    Raises:
        ValueError: If the latent channels or the downsampling factor differ from ``pipe.vae``'s, or the VAE
            was built for another chip size.
    """
    new_factor = downsampling_factor(vae.config.block_out_channels)
    old_factor = pipe.vae_scale_factor
    if vae.config.latent_channels != pipe.vae.config.latent_channels or new_factor != old_factor:
        raise ValueError(
            f"{name} has {vae.config.latent_channels} latent channels and downsampling factor {new_factor}; "
            f"the UNet needs {pipe.vae.config.latent_channels} and {old_factor}"
        )
    check_vae_image_size(vae, pipe.unet, name=name)


def replace_vae(pipe: SARZero123Pipeline, path: str | os.PathLike) -> SARZero123Pipeline:
    """``pipe`` with the ``AutoencoderKL`` saved in ``path`` as its VAE.

    Raises:
        FileNotFoundError: If ``path`` holds no ``AutoencoderKL`` ``config.json`` (the message points a run
            folder to its ``vae`` subfolder) or no weights.
        ValueError: If the weights do not load or the VAE does not fit.
    """
    path = Path(path)
    config_file = path / "config.json"
    if not config_file.is_file():
        raise FileNotFoundError(f"vae: {str(path)!r} is not an AutoencoderKL folder (no config.json)")
    try:
        class_name = json.loads(config_file.read_text()).get("_class_name")
    except (ValueError, AttributeError):  # not JSON, or JSON that is not an object
        class_name = None
    if class_name != "AutoencoderKL":
        hint = f"; the VAE of a train_vae.py run is {str(path / 'vae')!r}" if (path / "vae").is_dir() else ""
        raise FileNotFoundError(
            f"vae: {str(path)!r} is not an AutoencoderKL folder (its config.json is not an AutoencoderKL "
            f"config){hint}"
        )
    vae = load_component(AutoencoderKL, path, "vae")
    check_vae_fits(vae, pipe, name=f"vae: {str(path)!r}")
    # `pipe.components`, not `from_pipe`: that casts every module to one dtype (float32 by default)
    recorded = {name: getattr(pipe.config, name, None) for name in PIPELINE_SETTINGS}
    return SARZero123Pipeline(**{**pipe.components, "vae": vae.eval()}, **recorded)


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether two modules hold identical parameters (same names, shapes and values)."""
    first, second = a.state_dict(), b.state_dict()
    return first.keys() == second.keys() and all(
        first[k].shape == second[k].shape and torch.equal(first[k].cpu(), second[k].cpu()) for k in first
    )


def record_trained_pose_ranges(pose_projection: PoseProjection, pairs: ViewPairDataset) -> tuple[list, list]:
    """Widen the pose projection's recorded training ranges to cover ``pairs`` (saved with its config).

    ``trained_depression_deg`` takes the union with the pairs' depressions; ``trained_d_el_deg`` with every
    change those chips can pair into (pairs are redrawn each epoch): ``[low - high, high - low]``. Both
    widen outward to a multiple of 0.1 deg. A fine-tune of a prior thus keeps the prior's ranges.

    Returns:
        The new ``(trained_d_el_deg, trained_depression_deg)``.
    """
    depressions = [float(record.depression_deg) for record in pairs.records]
    low, high = min(depressions), max(depressions)
    spread = 0.0 if pairs.same_depression else high - low
    ranges = []
    for name, (new_low, new_high) in (
        ("trained_d_el_deg", (-spread, spread)),
        ("trained_depression_deg", (low, high)),
    ):
        old = getattr(pose_projection.config, name, None)
        if old is not None:
            new_low, new_high = min(new_low, float(old[0])), max(new_high, float(old[1]))
        # outward to 0.1 deg (finer than any chip's depression metadata), so that a corpus drawn uniformly
        # in [10, 60] accepts a request for 10; + 0.0: no "-0"
        ranges.append(
            [math.floor(round(new_low * 10, 6)) / 10 + 0.0, math.ceil(round(new_high * 10, 6)) / 10 + 0.0]
        )
    pose_projection.register_to_config(trained_d_el_deg=ranges[0], trained_depression_deg=ranges[1])
    return ranges[0], ranges[1]
