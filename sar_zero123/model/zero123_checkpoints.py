"""Loading Objaverse zero-1-to-3 checkpoints, and the zero-1-to-3 constants every model here shares.

Layouts (REFERENCE.md, "Checkpoint layouts in the wild"):

(a) a diffusers folder in the ``kxic/zero123-*`` layout with ``cc_projection/`` (keys
    ``projection.weight`` / ``projection.bias``, no sizes in its config);
(b) threestudio's, the same with ``clip_camera_projection/`` (keys ``proj.weight`` / ``proj.bias``);
(c) the Lightning/LDM state dict (``.ckpt`` / ``.safetensors``): ``model.diffusion_model.*``,
    ``first_stage_model.*``, ``cc_projection.*``, optionally ``model_ema.*`` and the OpenAI CLIP model
    ``cond_stage_model.model.*``;

and this package's own ``save_pretrained`` folders. Projection sizes come from the weight shapes. Layout
(c) is renamed by diffusers' single-file converters; the EMA substitution and the architecture inference
(which they take from an LDM yaml) are done here. Components are returned, not a pipeline, so this module
does not import the pipeline.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
from diffusers.loaders.single_file_utils import convert_ldm_unet_checkpoint, convert_ldm_vae_checkpoint
from safetensors.torch import load_file
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

try:  # transformers >= 5: the PIL backend (no torchvision); only its mean/std and config are used
    from transformers import CLIPImageProcessorPil as CLIPImageProcessor
except ImportError:  # transformers 4.x
    from transformers import CLIPImageProcessor

from sar_zero123.config.json_io import read_json
from sar_zero123.model.conditioning import POSE_DIM, PoseProjection
from sar_zero123.model.loading import load_component

__all__ = [
    "PROJECTION_FOLDERS",
    "SD_VAE_SCALING_FACTOR",
    "ZERO123_SCHEDULER_CONFIG",
    "CLIPImageProcessor",
    "convert_openai_clip_vision",
    "load_ldm_state_dict",
    "load_zero123_components",
]

#: zero-1-to-3 / Stable Diffusion noise schedule (REFERENCE.md): 1000 steps, scaled_linear, epsilon.
ZERO123_SCHEDULER_CONFIG: dict[str, Any] = {
    "num_train_timesteps": 1000,
    "beta_start": 0.00085,
    "beta_end": 0.012,
    "beta_schedule": "scaled_linear",
    "prediction_type": "epsilon",
    "clip_sample": False,
    "set_alpha_to_one": False,
    "steps_offset": 1,
}
SD_VAE_SCALING_FACTOR = 0.18215

#: Folder name of the pose projection -> names of its weight and bias in that folder's state dict.
PROJECTION_FOLDERS: dict[str, tuple[str, str]] = {
    "pose_projection": ("projection.weight", "projection.bias"),  # this package's own layout
    "cc_projection": ("projection.weight", "projection.bias"),  # kxic/zero123-* diffusers layout
    "clip_camera_projection": ("proj.weight", "proj.bias"),  # threestudio layout
}
LDM_UNET_PREFIX = "model.diffusion_model."
LDM_VAE_PREFIX = "first_stage_model."
LDM_EMA_PREFIX = "model_ema."
LDM_PROJECTION_KEYS = ("cc_projection.weight", "cc_projection.bias")
LDM_CLIP_VISUAL_PREFIX = "cond_stage_model.model.visual."  # zero-1-to-3's FrozenCLIPImageEmbedder
_FOLDER_COMPONENTS = ("vae", "unet", "image_encoder")
_WEIGHT_FILES = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin", "model.safetensors")

#: Architecture facts an LDM state dict cannot tell (head count, norm groups), zero-1-to-3's values.
ZERO123_UNET_DEFAULTS: dict[str, Any] = {"attention_head_dim": 8, "norm_num_groups": 32, "sample_size": 32}
ZERO123_VAE_DEFAULTS: dict[str, Any] = {
    "norm_num_groups": 32,
    "sample_size": 256,
    "scaling_factor": SD_VAE_SCALING_FACTOR,
}


def load_zero123_components(
    path: str | Path,
    use_ema: bool = True,
    image_encoder_path: str | Path | None = None,
    unet_config: dict[str, Any] | None = None,
    vae_config: dict[str, Any] | None = None,
    image_encoder_config: dict[str, Any] | None = None,
    weights_only: bool = True,
) -> dict[str, Any]:
    """The keyword arguments of ``SARZero123Pipeline`` (``pose_projection`` in eval mode) from a
    zero-1-to-3 checkpoint in any supported layout.

    Args:
        path: A diffusers folder (layouts a, b, or this package's) or an LDM file (layout c).
        use_ema: For LDM files holding ``model_ema.*``, load the EMA UNet (as zero-1-to-3 samples).
        image_encoder_path: A ``CLIPVisionModelWithProjection`` folder (optionally with its processor)
            overriding a folder's ``image_encoder``; for an LDM file needed only when it holds no OpenAI
            CLIP tower.
        unet_config: LDM only: ``UNet2DConditionModel`` overrides of the inferred config (head count and
            norm groups are not in the weights).
        vae_config: LDM only: ``AutoencoderKL`` config overrides.
        image_encoder_config: LDM only: ``CLIPVisionConfig`` overrides (default heads: ``width // 64``).
        weights_only: Passed to ``torch.load`` for ``.ckpt`` files; keep True unless the file is trusted.

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        ValueError: For an unknown layout, missing components or keys, or weights whose shapes do not
            fit; the message lists what was expected.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"zero-1-to-3 checkpoint not found: {path}")
    if path.is_dir():
        return _load_folder(path, image_encoder_path)
    if path.suffix in (".ckpt", ".pt", ".pth", ".safetensors"):
        state_dict = load_ldm_state_dict(path, weights_only=weights_only)
        return _components_from_ldm(
            state_dict, use_ema, image_encoder_path, unet_config, vae_config, image_encoder_config
        )
    raise ValueError(
        f"unknown zero-1-to-3 checkpoint layout: {path}. Expected a diffusers folder with "
        f"model_index.json and one of {sorted(PROJECTION_FOLDERS)}, or an LDM .ckpt/.safetensors file"
    )


def load_ldm_state_dict(path: str | Path, weights_only: bool = True) -> dict[str, torch.Tensor]:
    """The flat state dict of an LDM checkpoint (a Lightning ``.ckpt``'s ``state_dict`` entry).

    Raises:
        ValueError: If the file holds no tensor state dict.
    """
    path = Path(path)
    if path.suffix == ".safetensors":
        return load_file(str(path))
    checkpoint = torch.load(path, map_location="cpu", weights_only=weights_only)
    if isinstance(checkpoint, dict) and isinstance(checkpoint.get("state_dict"), dict):
        checkpoint = checkpoint["state_dict"]
    if not isinstance(checkpoint, dict) or not all(isinstance(v, torch.Tensor) for v in checkpoint.values()):
        raise ValueError(f"{path} holds no state dict of tensors (nor a Lightning checkpoint with one)")
    return checkpoint


# ------------------------------------------------------------------------------ layouts (a), (b)
def _read_weights(folder: Path) -> dict[str, torch.Tensor]:
    for name in _WEIGHT_FILES:
        file = folder / name
        if file.exists():
            if file.suffix == ".safetensors":
                return load_file(str(file))
            return torch.load(file, map_location="cpu", weights_only=True)
    raise ValueError(f"no weights in {folder}; expected one of {list(_WEIGHT_FILES)}")


def _projection_from_tensors(
    weight: torch.Tensor | None, bias: torch.Tensor | None, where: str
) -> PoseProjection:
    """A :class:`PoseProjection` sized from its weight, e.g. (768, 772) for zero-1-to-3."""
    if weight is None or bias is None:
        raise ValueError(f"{where}: missing projection weight or bias")
    if weight.ndim != 2 or weight.shape[1] <= POSE_DIM or bias.shape != (weight.shape[0],):
        raise ValueError(
            f"{where}: expected weight (out, image_embed_dim + {POSE_DIM}) and bias (out,), got "
            f"{tuple(weight.shape)} and {tuple(bias.shape)}"
        )
    out_features, in_features = weight.shape
    projection = PoseProjection(in_features=in_features, out_features=out_features)
    projection.load_state_dict({"projection.weight": weight.float(), "projection.bias": bias.float()})
    return projection


def _load_projection(folder: Path) -> PoseProjection:
    weight_key, bias_key = PROJECTION_FOLDERS[folder.name]
    state_dict = _read_weights(folder)
    unexpected = sorted(set(state_dict) - {weight_key, bias_key})
    if unexpected:
        raise ValueError(f"{folder}: unexpected keys {unexpected}; expected {[weight_key, bias_key]}")
    projection = _projection_from_tensors(state_dict.get(weight_key), state_dict.get(bias_key), str(folder))
    config_file = folder / "config.json"
    if folder.name == "clip_camera_projection" and config_file.exists():
        config = read_json(config_file, what="the projection's config {embedding_dim, additional_embeddings}")
        if not isinstance(config, dict):
            raise ValueError(f"{config_file}: expected a JSON object (the projection's config)")
        stated = config.get("embedding_dim"), config.get("additional_embeddings", POSE_DIM)
        if stated[0] is not None and (stated[0] + stated[1], stated[0]) != (
            projection.config.in_features,
            projection.config.out_features,
        ):
            raise ValueError(
                f"{config_file}: embedding_dim={stated[0]}, additional_embeddings={stated[1]} do not match "
                f"the weight shape {(projection.config.out_features, projection.config.in_features)}"
            )
    return projection


def _load_scheduler(folder: Path) -> Any:
    import diffusers

    config_file = folder / "scheduler_config.json"
    if not config_file.exists():
        return DDIMScheduler(**ZERO123_SCHEDULER_CONFIG)
    config = read_json(config_file, what="a diffusers scheduler config")
    if not isinstance(config, dict):
        raise ValueError(f"{config_file}: expected a JSON object (a diffusers scheduler config)")
    class_name = config.get("_class_name", "DDIMScheduler")
    scheduler_class = getattr(diffusers, class_name, None)
    if scheduler_class is None:
        raise ValueError(f"{config_file}: unknown scheduler class {class_name!r} (not in diffusers)")
    return scheduler_class.from_pretrained(folder)


def _load_folder(path: Path, image_encoder_path: str | Path | None) -> dict[str, Any]:
    projection_folders = [name for name in PROJECTION_FOLDERS if (path / name).is_dir()]
    if not (path / "model_index.json").exists() or not projection_folders:
        raise ValueError(
            f"unknown zero-1-to-3 folder layout: {path}. Expected model_index.json and a projection folder "
            f"named one of {sorted(PROJECTION_FOLDERS)} next to {list(_FOLDER_COMPONENTS)}"
        )
    required = [name for name in _FOLDER_COMPONENTS if name != "image_encoder" or image_encoder_path is None]
    missing = [name for name in required if not (path / name).is_dir()]
    if missing:
        raise ValueError(f"{path}: missing component folders {missing}; expected {required}")

    encoder_dir = Path(image_encoder_path) if image_encoder_path is not None else path / "image_encoder"
    feature_dir = encoder_dir if image_encoder_path is not None else path / "feature_extractor"
    return dict(
        vae=load_component(AutoencoderKL, path / "vae", "vae").eval(),
        image_encoder=load_component(CLIPVisionModelWithProjection, encoder_dir, "image_encoder").eval(),
        unet=load_component(UNet2DConditionModel, path / "unet", "unet").eval(),
        scheduler=_load_scheduler(path / "scheduler"),
        pose_projection=_load_projection(path / projection_folders[0]).eval(),
        feature_extractor=_load_feature_extractor(feature_dir),
    )


def _load_feature_extractor(folder: Path) -> CLIPImageProcessor | None:
    if (folder / "preprocessor_config.json").exists():
        return CLIPImageProcessor.from_pretrained(folder)
    return None


# ------------------------------------------------------------------------------------ layout (c)
def _substitute_ema(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Replace ``model.diffusion_model.*`` by their ``model_ema.*`` copies.

    LitEma stores ``model.diffusion_model.a.b`` as ``model_ema.diffusion_modelab``; diffusers' converter
    only switches to EMA above 100 EMA keys, so the substitution is done here for any size.
    """
    substituted = dict(state_dict)
    missing = []
    for key in state_dict:
        if key.startswith(LDM_UNET_PREFIX):
            ema_key = LDM_EMA_PREFIX + "".join(key.split(".")[1:])
            if ema_key in state_dict:
                substituted[key] = state_dict[ema_key]
            else:
                missing.append(ema_key)
    if missing:
        raise ValueError(
            f"use_ema=True but {len(missing)} EMA weights are missing, e.g. {missing[:3]}; "
            "pass use_ema=False to load the non-EMA UNet"
        )
    return substituted


def _infer_unet_config(unet_sd: dict[str, torch.Tensor], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """``UNet2DConditionModel`` config from the shapes of an LDM ``model.diffusion_model.*`` dict."""
    input_ids = sorted({int(key.split(".")[1]) for key in unet_sd if key.startswith("input_blocks.")})
    output_ids = sorted({int(key.split(".")[1]) for key in unet_sd if key.startswith("output_blocks.")})
    downsample_ids = [i for i in input_ids if f"input_blocks.{i}.0.op.weight" in unet_sd]
    num_levels = len(downsample_ids) + 1
    layers_per_block = downsample_ids[0] - 1 if downsample_ids else len(input_ids) - 1
    if layers_per_block < 1 or len(input_ids) != 1 + num_levels * layers_per_block + num_levels - 1:
        raise ValueError(f"cannot read the UNet block structure from input_blocks {input_ids}")
    block_out_channels, down_types, up_types = [], [], []
    for level in range(num_levels):
        first = 1 + level * (layers_per_block + 1)
        block_out_channels.append(unet_sd[f"input_blocks.{first}.0.out_layers.3.weight"].shape[0])
        has_attention = any(k.startswith(f"input_blocks.{first}.1.") for k in unet_sd)
        down_types.append("CrossAttnDownBlock2D" if has_attention else "DownBlock2D")
    for level in range(num_levels):
        first = level * (layers_per_block + 1)
        has_attention = any(k.startswith(f"output_blocks.{first}.1.transformer_blocks") for k in unet_sd)
        up_types.append("CrossAttnUpBlock2D" if has_attention else "UpBlock2D")
    if len(output_ids) != num_levels * (layers_per_block + 1):
        raise ValueError(
            f"UNet output_blocks {output_ids} do not mirror {num_levels} levels of {layers_per_block} layers"
        )
    attn2 = [key for key in unet_sd if key.endswith("attn2.to_k.weight")]
    if not attn2:
        raise ValueError("the UNet has no cross-attention (`attn2.to_k.weight`) keys")
    conv_in = unet_sd["input_blocks.0.0.weight"]
    config = {
        **ZERO123_UNET_DEFAULTS,
        "in_channels": conv_in.shape[1],
        "out_channels": unet_sd["out.2.weight"].shape[0],
        "block_out_channels": tuple(block_out_channels),
        "layers_per_block": layers_per_block,
        "down_block_types": tuple(down_types),
        "up_block_types": tuple(up_types),
        "cross_attention_dim": unet_sd[attn2[0]].shape[1],
    }
    return {**config, **(overrides or {})}


def _infer_vae_config(vae_sd: dict[str, torch.Tensor], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """``AutoencoderKL`` config from the shapes of an LDM ``first_stage_model.*`` dict."""
    levels = sorted({int(key.split(".")[2]) for key in vae_sd if key.startswith("encoder.down.")})
    if not levels:
        raise ValueError("the VAE has no `encoder.down.*` keys")
    block_out_channels = tuple(vae_sd[f"encoder.down.{i}.block.0.conv2.weight"].shape[0] for i in levels)
    layers_per_block = len({key.split(".")[4] for key in vae_sd if key.startswith("encoder.down.0.block.")})
    config = {
        **ZERO123_VAE_DEFAULTS,
        "in_channels": vae_sd["encoder.conv_in.weight"].shape[1],
        "out_channels": vae_sd["decoder.conv_out.weight"].shape[0],
        "latent_channels": vae_sd["post_quant_conv.weight"].shape[0],
        "block_out_channels": block_out_channels,
        "layers_per_block": layers_per_block,
        "down_block_types": ("DownEncoderBlock2D",) * len(levels),
        "up_block_types": ("UpDecoderBlock2D",) * len(levels),
    }
    return {**config, **(overrides or {})}


def _load_strict(module: torch.nn.Module, state_dict: dict[str, torch.Tensor], name: str) -> None:
    """``load_state_dict(strict=True)`` with a ValueError listing missing/unexpected/mis-shaped keys."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    wrong_shape = [
        f"{key}: expected {tuple(expected[key].shape)}, got {tuple(state_dict[key].shape)}"
        for key in sorted(set(expected) & set(state_dict))
        if expected[key].shape != state_dict[key].shape
    ]
    if missing or unexpected or wrong_shape:
        raise ValueError(
            f"{name} weights do not fit the architecture: missing {missing[:10]} ({len(missing)}), "
            f"unexpected {unexpected[:10]} ({len(unexpected)}), wrong shapes {wrong_shape[:10]}"
        )
    module.load_state_dict(state_dict, strict=True)


def convert_openai_clip_vision(
    state_dict: dict[str, torch.Tensor],
    prefix: str = LDM_CLIP_VISUAL_PREFIX,
    config_overrides: dict[str, Any] | None = None,
) -> CLIPVisionModelWithProjection:
    """The OpenAI CLIP image tower of an LDM checkpoint as a transformers ``CLIPVisionModelWithProjection``.

    Neither library ships this conversion (diffusers converts CLIP text towers only). ``conv1`` -> patch
    embedding, ``ln_pre``/``ln_post``, each ``resblocks.i`` (fused ``attn.in_proj`` split into q/k/v), and
    ``proj`` -> the transposed ``visual_projection``; QuickGELU, LayerNorm eps 1e-5, 64-d heads.

    Returns:
        The image tower in eval mode.

    Raises:
        ValueError: If keys are missing or shapes do not fit.
    """
    visual = {k[len(prefix) :]: v for k, v in state_dict.items() if k.startswith(prefix)}
    try:
        width, channels, patch_size, _ = visual["conv1.weight"].shape
        num_positions = visual["positional_embedding"].shape[0]
        num_layers = len({k.split(".")[2] for k in visual if k.startswith("transformer.resblocks.")})
        config = CLIPVisionConfig(
            **{
                "hidden_size": width,
                "num_channels": channels,
                "patch_size": patch_size,
                "image_size": patch_size * round((num_positions - 1) ** 0.5),
                "num_hidden_layers": num_layers,
                "num_attention_heads": max(width // 64, 1),
                "intermediate_size": visual["transformer.resblocks.0.mlp.c_fc.weight"].shape[0],
                "projection_dim": visual["proj"].shape[1],
                "hidden_act": "quick_gelu",
                "layer_norm_eps": 1e-5,
                **(config_overrides or {}),
            }
        )
        converted = {
            "vision_model.embeddings.patch_embedding.weight": visual["conv1.weight"],
            "vision_model.embeddings.class_embedding": visual["class_embedding"],
            "vision_model.embeddings.position_embedding.weight": visual["positional_embedding"],
            "vision_model.pre_layrnorm.weight": visual["ln_pre.weight"],
            "vision_model.pre_layrnorm.bias": visual["ln_pre.bias"],
            "vision_model.post_layernorm.weight": visual["ln_post.weight"],
            "vision_model.post_layernorm.bias": visual["ln_post.bias"],
            "visual_projection.weight": visual["proj"].t().contiguous(),
        }
        renames = {
            "attn.out_proj": "self_attn.out_proj",
            "ln_1": "layer_norm1",
            "ln_2": "layer_norm2",
            "mlp.c_fc": "mlp.fc1",
            "mlp.c_proj": "mlp.fc2",
        }
        for layer in range(num_layers):
            source, target = f"transformer.resblocks.{layer}.", f"vision_model.encoder.layers.{layer}."
            for kind in ("weight", "bias"):
                for name, new_name in renames.items():
                    converted[f"{target}{new_name}.{kind}"] = visual[f"{source}{name}.{kind}"]
                q, k, v = visual[f"{source}attn.in_proj_{kind}"].chunk(3, dim=0)
                for name, tensor in (("q_proj", q), ("k_proj", k), ("v_proj", v)):
                    converted[f"{target}self_attn.{name}.{kind}"] = tensor.contiguous()
    except KeyError as error:
        raise ValueError(f"OpenAI CLIP tower under {prefix!r} lacks {error}") from None
    model = CLIPVisionModelWithProjection(config)
    _load_strict(model, converted, "CLIP image encoder")
    return model.eval()


def _components_from_ldm(
    state_dict: dict[str, torch.Tensor],
    use_ema: bool,
    image_encoder_path: str | Path | None,
    unet_config: dict[str, Any] | None,
    vae_config: dict[str, Any] | None,
    image_encoder_config: dict[str, Any] | None,
) -> dict[str, Any]:
    # 1. check the layout
    prefixes = (LDM_UNET_PREFIX, LDM_VAE_PREFIX)
    absent = [f"{prefix}*" for prefix in prefixes if not any(k.startswith(prefix) for k in state_dict)]
    absent += [key for key in LDM_PROJECTION_KEYS if key not in state_dict]
    if absent:
        raise ValueError(
            f"not a zero-1-to-3 LDM state dict: missing {absent}; expected keys "
            f"{LDM_UNET_PREFIX}*, {LDM_VAE_PREFIX}*, {LDM_PROJECTION_KEYS[0]}, {LDM_PROJECTION_KEYS[1]} "
            f"(and optionally {LDM_EMA_PREFIX}*)"
        )
    has_clip = f"{LDM_CLIP_VISUAL_PREFIX}proj" in state_dict
    if image_encoder_path is None and not has_clip:
        raise ValueError(
            f"this LDM checkpoint holds no CLIP image tower ({LDM_CLIP_VISUAL_PREFIX}*): pass "
            "`image_encoder_path`, a folder holding a CLIPVisionModelWithProjection (CLIP ViT-L/14 "
            "image tower for the Objaverse checkpoints)"
        )
    if use_ema and any(key.startswith(LDM_EMA_PREFIX + "diffusion_model") for key in state_dict):
        state_dict = _substitute_ema(state_dict)

    # 2. UNet and VAE through diffusers' converters, on architectures inferred from the shapes
    unet_sd = {k[len(LDM_UNET_PREFIX) :]: v for k, v in state_dict.items() if k.startswith(LDM_UNET_PREFIX)}
    vae_sd = {k[len(LDM_VAE_PREFIX) :]: v for k, v in state_dict.items() if k.startswith(LDM_VAE_PREFIX)}
    # Only the prefixed keys go in, so the converters see neither EMA copies nor other modules.
    try:
        inferred_unet = _infer_unet_config(unet_sd, unet_config)
        inferred_vae = _infer_vae_config(vae_sd, vae_config)
    except KeyError as error:
        raise ValueError(f"LDM state dict lacks {error}, needed to read the UNet/VAE architecture") from None
    unet = UNet2DConditionModel(**inferred_unet)
    unet_ldm = {LDM_UNET_PREFIX + k: v for k, v in unet_sd.items()}
    _load_strict(unet, convert_ldm_unet_checkpoint(unet_ldm, dict(unet.config)), "UNet")
    vae = AutoencoderKL(**inferred_vae)
    vae_ldm = {LDM_VAE_PREFIX + k: v for k, v in vae_sd.items()}
    _load_strict(vae, convert_ldm_vae_checkpoint(vae_ldm, dict(vae.config)), "VAE")

    # 3. projection, CLIP image tower, scheduler
    projection = _projection_from_tensors(
        state_dict[LDM_PROJECTION_KEYS[0]], state_dict[LDM_PROJECTION_KEYS[1]], "cc_projection"
    )
    if image_encoder_path is not None:
        image_encoder = CLIPVisionModelWithProjection.from_pretrained(Path(image_encoder_path)).eval()
        feature_extractor = _load_feature_extractor(Path(image_encoder_path))
    else:
        image_encoder = convert_openai_clip_vision(state_dict, config_overrides=image_encoder_config)
        feature_extractor = None  # the pipeline then uses OpenAI CLIP's mean/std, as zero-1-to-3 does
    return dict(
        vae=vae.eval(),
        image_encoder=image_encoder,
        unet=unet.eval(),
        scheduler=DDIMScheduler(**ZERO123_SCHEDULER_CONFIG),
        pose_projection=projection.eval(),
        feature_extractor=feature_extractor,
    )
