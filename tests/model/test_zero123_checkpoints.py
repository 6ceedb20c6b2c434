"""Tests for loading zero-1-to-3 checkpoints: tiny checkpoints fabricated in each real layout.

The LDM layout is written with an inverse of diffusers' single-file key mapping (below), which is
itself checked against diffusers' converters, so the fabricated files carry the original key structure
(``input_blocks.*``, ``encoder.down.*``, LitEma ``model_ema.*``) at tiny sizes.
"""

from __future__ import annotations

import json
import re

import pytest
import torch
from diffusers import AutoencoderKL
from diffusers.loaders.single_file_utils import (
    DIFFUSERS_TO_LDM_MAPPING,
    convert_ldm_unet_checkpoint,
    convert_ldm_vae_checkpoint,
)
from dummies import dummy_images, get_dummy_components
from safetensors.torch import save_file
from transformers import CLIPImageProcessor

from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.pipeline import SARZero123Pipeline

load_zero123 = SARZero123Pipeline.from_zero123

TINY_UNET = {"attention_head_dim": 4, "norm_num_groups": 8, "sample_size": 16}
TINY_VAE = {"norm_num_groups": 8, "sample_size": 32}


# ------------------------------------------------------------------ diffusers -> LDM key names
_RESNET_TO_LDM = [
    ("norm1", "in_layers.0"),
    ("conv1", "in_layers.2"),
    ("norm2", "out_layers.0"),
    ("conv2", "out_layers.3"),
    ("time_emb_proj", "emb_layers.1"),
    ("conv_shortcut", "skip_connection"),
]


def _ldm_block(kind: str, stride: int, level: int, layer: int) -> str:
    if kind == "down":
        return f"input_blocks.{stride * level + layer + 1}"
    return f"output_blocks.{stride * level + layer}"


def unet_to_ldm(state_dict: dict[str, torch.Tensor], config) -> dict[str, torch.Tensor]:
    """diffusers UNet2DConditionModel keys -> LDM ``openaimodel`` keys (inverse of diffusers' converter)."""
    stride = config.layers_per_block + 1
    fixed = DIFFUSERS_TO_LDM_MAPPING["unet"]["layers"]
    up_has_attention = {i: t.startswith("CrossAttn") for i, t in enumerate(config.up_block_types)}
    out = {}
    for key, value in state_dict.items():
        if key in fixed:
            out[fixed[key]] = value
            continue
        if match := re.match(r"(down|up)_blocks\.(\d+)\.resnets\.(\d+)\.(.*)", key):
            kind, i, j, rest = match.group(1), int(match.group(2)), int(match.group(3)), match.group(4)
            for new, old in _RESNET_TO_LDM:
                rest = rest.replace(new, old)
            block = _ldm_block(kind, stride, i, j)
            out[f"{block}.0.{rest}"] = value
        elif match := re.match(r"(down|up)_blocks\.(\d+)\.attentions\.(\d+)\.(.*)", key):
            kind, i, j, rest = match.group(1), int(match.group(2)), int(match.group(3)), match.group(4)
            out[f"{_ldm_block(kind, stride, i, j)}.1.{rest}"] = value
        elif match := re.match(r"down_blocks\.(\d+)\.downsamplers\.0\.conv\.(.*)", key):
            out[f"input_blocks.{stride * (int(match.group(1)) + 1)}.0.op.{match.group(2)}"] = value
        elif match := re.match(r"up_blocks\.(\d+)\.upsamplers\.0\.conv\.(.*)", key):
            i = int(match.group(1))
            position = 2 if up_has_attention[i] else 1
            out[f"output_blocks.{stride * i + stride - 1}.{position}.conv.{match.group(2)}"] = value
        elif match := re.match(r"mid_block\.resnets\.(\d+)\.(.*)", key):
            rest = match.group(2)
            for new, old in _RESNET_TO_LDM:
                rest = rest.replace(new, old)
            out[f"middle_block.{2 * int(match.group(1))}.{rest}"] = value
        elif match := re.match(r"mid_block\.attentions\.0\.(.*)", key):
            out[f"middle_block.1.{match.group(1)}"] = value
        else:
            raise AssertionError(f"unmapped UNet key {key}")
    return out


def vae_to_ldm(state_dict: dict[str, torch.Tensor], config) -> dict[str, torch.Tensor]:
    """diffusers AutoencoderKL keys -> LDM ``first_stage_model`` keys (1x1 conv attention weights)."""
    fixed = DIFFUSERS_TO_LDM_MAPPING["vae"]
    levels = len(config.block_out_channels)
    attention = {"group_norm": "norm", "to_q": "q", "to_k": "k", "to_v": "v", "to_out.0": "proj_out"}
    out = {}
    for key, value in state_dict.items():
        if key in fixed:
            out[fixed[key]] = value
        elif match := re.match(r"encoder\.down_blocks\.(\d+)\.resnets\.(\d+)\.(.*)", key):
            rest = match.group(3).replace("conv_shortcut", "nin_shortcut")
            out[f"encoder.down.{match.group(1)}.block.{match.group(2)}.{rest}"] = value
        elif match := re.match(r"encoder\.down_blocks\.(\d+)\.downsamplers\.0\.(.*)", key):
            out[f"encoder.down.{match.group(1)}.downsample.{match.group(2)}"] = value
        elif match := re.match(r"decoder\.up_blocks\.(\d+)\.resnets\.(\d+)\.(.*)", key):
            rest = match.group(3).replace("conv_shortcut", "nin_shortcut")
            out[f"decoder.up.{levels - 1 - int(match.group(1))}.block.{match.group(2)}.{rest}"] = value
        elif match := re.match(r"decoder\.up_blocks\.(\d+)\.upsamplers\.0\.(.*)", key):
            out[f"decoder.up.{levels - 1 - int(match.group(1))}.upsample.{match.group(2)}"] = value
        elif match := re.match(r"(encoder|decoder)\.mid_block\.resnets\.(\d+)\.(.*)", key):
            rest = match.group(3).replace("conv_shortcut", "nin_shortcut")
            out[f"{match.group(1)}.mid.block_{int(match.group(2)) + 1}.{rest}"] = value
        elif match := re.match(r"(encoder|decoder)\.mid_block\.attentions\.0\.(.*)\.(weight|bias)", key):
            name = attention[match.group(2)]
            is_conv = name != "norm" and match.group(3) == "weight"
            key_ldm = f"{match.group(1)}.mid.attn_1.{name}.{match.group(3)}"
            out[key_ldm] = value[:, :, None, None] if is_conv else value
        else:
            raise AssertionError(f"unmapped VAE key {key}")
    return out


def clip_to_openai(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """transformers CLIPVisionModelWithProjection keys -> OpenAI CLIP ``visual.*`` keys (fused q/k/v)."""
    out = {
        "conv1.weight": state_dict["vision_model.embeddings.patch_embedding.weight"],
        "class_embedding": state_dict["vision_model.embeddings.class_embedding"],
        "positional_embedding": state_dict["vision_model.embeddings.position_embedding.weight"],
        "ln_pre.weight": state_dict["vision_model.pre_layrnorm.weight"],
        "ln_pre.bias": state_dict["vision_model.pre_layrnorm.bias"],
        "ln_post.weight": state_dict["vision_model.post_layernorm.weight"],
        "ln_post.bias": state_dict["vision_model.post_layernorm.bias"],
        "proj": state_dict["visual_projection.weight"].t(),
    }
    names = {"self_attn.out_proj": "attn.out_proj", "layer_norm1": "ln_1", "layer_norm2": "ln_2",
             "mlp.fc1": "mlp.c_fc", "mlp.fc2": "mlp.c_proj"}
    layers = {int(k.split(".")[3]) for k in state_dict if k.startswith("vision_model.encoder.layers.")}
    for layer in layers:
        hf, openai = f"vision_model.encoder.layers.{layer}.", f"transformer.resblocks.{layer}."
        for kind in ("weight", "bias"):
            for name, new in names.items():
                out[f"{openai}{new}.{kind}"] = state_dict[f"{hf}{name}.{kind}"]
            qkv = [state_dict[f"{hf}self_attn.{n}_proj.{kind}"] for n in ("q", "k", "v")]
            out[f"{openai}attn.in_proj_{kind}"] = torch.cat(qkv)
    return out


# ------------------------------------------------------------------------------------ fixtures
def _components() -> dict:
    components = get_dummy_components()
    spec = dict(SAR_ZERO123_SIZES["tiny"]["vae"], in_channels=3, out_channels=3)
    torch.manual_seed(0)
    components["vae"] = AutoencoderKL(**spec, sample_size=32).eval()  # an RGB VAE, as Stable Diffusion's
    return components


@pytest.fixture(scope="module")
def source() -> SARZero123Pipeline:
    pipe = SARZero123Pipeline(**_components())
    pipe.set_progress_bar_config(disable=True)
    with torch.no_grad():  # a trained-looking projection: nonzero pose weights and bias
        generator = torch.Generator().manual_seed(1)
        pipe.pose_projection.projection.weight[:, -4:].normal_(generator=generator)
        pipe.pose_projection.projection.bias.normal_(generator=generator)
    return pipe


def sample(pipe: SARZero123Pipeline) -> torch.Tensor:
    pipe.set_progress_bar_config(disable=True)
    generator = torch.Generator().manual_seed(0)
    images = dummy_images(batch_size=2)
    return pipe(images, d_az=[30.0, 200.0], d_el=[0.0, 5.0], num_inference_steps=2, generator=generator,
                output_type="pt").images


@pytest.fixture(scope="module")
def reference(source) -> torch.Tensor:
    return sample(source)


def _write_diffusers_folder(pipe: SARZero123Pipeline, root, projection_folder: str) -> None:
    pipe.vae.save_pretrained(root / "vae")
    pipe.unet.save_pretrained(root / "unet")
    pipe.image_encoder.save_pretrained(root / "image_encoder")
    pipe.scheduler.save_pretrained(root / "scheduler")
    CLIPImageProcessor(crop_size=32, size={"shortest_edge": 32}).save_pretrained(root / "feature_extractor")
    folder = root / projection_folder
    folder.mkdir()
    projection = pipe.pose_projection.projection
    weight, bias = projection.weight.detach(), projection.bias.detach()
    if projection_folder == "cc_projection":  # kxic: config without sizes, torch .bin weights
        config = {"_class_name": "CCProjection", "_diffusers_version": "0.15.0"}
        weights = {"projection.weight": weight, "projection.bias": bias}
        torch.save(weights, folder / "diffusion_pytorch_model.bin")
        pipeline_class = "Zero1to3StableDiffusionPipeline"
    else:  # threestudio: sizes in the config, safetensors weights named proj.*
        config = {"_class_name": "CLIPCameraProjection", "embedding_dim": 16, "additional_embeddings": 4}
        save_file({"proj.weight": weight.contiguous(), "proj.bias": bias.contiguous()},
                  folder / "diffusion_pytorch_model.safetensors")
        pipeline_class = "Zero123Pipeline"
    (folder / "config.json").write_text(json.dumps(config))
    model_index = {
        "_class_name": pipeline_class,
        "vae": ["diffusers", "AutoencoderKL"],
        "unet": ["diffusers", "UNet2DConditionModel"],
        "image_encoder": ["transformers", "CLIPVisionModelWithProjection"],
        "scheduler": ["diffusers", "DDIMScheduler"],
        "feature_extractor": ["transformers", "CLIPImageProcessor"],
        projection_folder: ["pipeline", config["_class_name"]],
    }
    (root / "model_index.json").write_text(json.dumps(model_index))


def _ldm_state_dict(pipe: SARZero123Pipeline, ema_pipe: SARZero123Pipeline | None = None) -> dict:
    unet = unet_to_ldm(pipe.unet.state_dict(), pipe.unet.config)
    vae = vae_to_ldm(pipe.vae.state_dict(), pipe.vae.config)
    state = {f"model.diffusion_model.{k}": v for k, v in unet.items()}
    state.update({f"first_stage_model.{k}": v for k, v in vae.items()})
    state["cc_projection.weight"] = pipe.pose_projection.projection.weight.detach().clone()
    state["cc_projection.bias"] = pipe.pose_projection.projection.bias.detach().clone()
    visual = clip_to_openai(pipe.image_encoder.state_dict())
    state.update({f"cond_stage_model.model.visual.{k}": v for k, v in visual.items()})
    state["cond_stage_model.model.token_embedding.weight"] = torch.zeros(8, 4)  # text tower: ignored
    if ema_pipe is not None:
        ema = unet_to_ldm(ema_pipe.unet.state_dict(), ema_pipe.unet.config)
        state.update({"model_ema.diffusion_model" + k.replace(".", ""): v for k, v in ema.items()})
        state["model_ema.decay"] = torch.tensor(0.9999)
        state["model_ema.num_updates"] = torch.tensor(105000, dtype=torch.int32)
    return {k: v.detach().clone().contiguous() for k, v in state.items()}


@pytest.fixture(scope="module")
def perturbed(source) -> SARZero123Pipeline:
    """The 'non-EMA' weights of the LDM checkpoint: the source UNet plus noise."""
    components = _components()
    components["unet"].load_state_dict(source.unet.state_dict())
    components["pose_projection"].load_state_dict(source.pose_projection.state_dict())
    with torch.no_grad():
        generator = torch.Generator().manual_seed(2)
        for parameter in components["unet"].parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))
    return SARZero123Pipeline(**components)


@pytest.fixture(scope="module")
def encoder_dir(source, tmp_path_factory):
    folder = tmp_path_factory.mktemp("clip")
    source.image_encoder.save_pretrained(folder)
    return folder


# --------------------------------------------------------------------------------------- tests
def test_inverse_key_mapping_round_trips_through_diffusers_converters(source):
    unet = unet_to_ldm(source.unet.state_dict(), source.unet.config)
    unet_ldm = {f"model.diffusion_model.{k}": v for k, v in unet.items()}
    converted = convert_ldm_unet_checkpoint(unet_ldm, dict(source.unet.config))
    expected = source.unet.state_dict()
    assert set(converted) == set(expected)
    assert all(torch.equal(converted[k], expected[k]) for k in expected)
    vae = vae_to_ldm(source.vae.state_dict(), source.vae.config)
    vae_ldm = {f"first_stage_model.{k}": v for k, v in vae.items()}
    converted = convert_ldm_vae_checkpoint(vae_ldm, dict(source.vae.config))
    expected = source.vae.state_dict()
    assert set(converted) == set(expected)
    assert all(torch.equal(converted[k].reshape(expected[k].shape), expected[k]) for k in expected)


@pytest.mark.parametrize("projection_folder", ["cc_projection", "clip_camera_projection"])
def test_diffusers_folder_layouts_load_identically(source, reference, tmp_path, projection_folder):
    _write_diffusers_folder(source, tmp_path, projection_folder)
    loaded = load_zero123(tmp_path)
    assert (loaded.pose_projection.config.in_features, loaded.pose_projection.config.out_features) == (20, 16)
    assert loaded.feature_extractor is not None
    assert torch.equal(sample(loaded), reference)


def test_own_saved_folder_loads_through_from_zero123(source, reference, tmp_path):
    source.save_pretrained(tmp_path)
    assert torch.equal(sample(load_zero123(tmp_path)), reference)


@pytest.mark.parametrize("suffix", [".ckpt", ".safetensors"])
def test_ldm_checkpoint_loads_ema_weights(source, perturbed, reference, encoder_dir, tmp_path, suffix):
    state = _ldm_state_dict(perturbed, ema_pipe=source)
    path = tmp_path / f"105000{suffix}"
    if suffix == ".ckpt":
        torch.save({"state_dict": state, "global_step": 105000, "epoch": 3}, path)
    else:
        save_file(state, str(path))
    # Without overrides the facts the weights cannot tell are zero-1-to-3's: 32 norm groups do not
    # divide the tiny 16 channels.
    with pytest.raises(ValueError, match="num_groups"):
        load_zero123(path, use_ema=True, image_encoder_path=encoder_dir)
    loaded = load_zero123(path, image_encoder_path=encoder_dir, unet_config=TINY_UNET, vae_config=TINY_VAE)
    assert loaded.unet.config.in_channels == 8 and loaded.vae.config.in_channels == 3
    assert loaded.unet.config.down_block_types == ("CrossAttnDownBlock2D", "DownBlock2D")
    assert loaded.unet.config.block_out_channels == (16, 32)
    assert loaded.vae.config.block_out_channels == (16, 32)
    assert torch.equal(sample(loaded), reference)


def test_ldm_checkpoint_non_ema_weights(source, perturbed, reference, encoder_dir, tmp_path):
    path = tmp_path / "model.ckpt"
    torch.save({"state_dict": _ldm_state_dict(perturbed, ema_pipe=source)}, path)
    loaded = load_zero123(path, use_ema=False, image_encoder_path=encoder_dir, unet_config=TINY_UNET,
                          vae_config=TINY_VAE)
    assert torch.equal(sample(loaded), sample(perturbed))
    torch.save(_ldm_state_dict(source), path)  # a bare state dict without model_ema.*
    loaded = load_zero123(path, image_encoder_path=encoder_dir, unet_config=TINY_UNET, vae_config=TINY_VAE)
    assert torch.equal(sample(loaded), reference)


def test_ldm_checkpoint_with_its_own_openai_clip_tower(source, reference, tmp_path):
    path = tmp_path / "105000.ckpt"
    torch.save({"state_dict": _ldm_state_dict(source)}, path)
    loaded = load_zero123(path, unet_config=TINY_UNET, vae_config=TINY_VAE,
                          image_encoder_config={"num_attention_heads": 4})
    assert loaded.image_encoder.config.image_size == 32 and loaded.image_encoder.config.projection_dim == 16
    assert torch.equal(sample(loaded), reference)


# ---------------------------------------------------------------------------------- errors
def test_unknown_layouts(tmp_path):
    with pytest.raises(ValueError, match="unknown zero-1-to-3 folder layout.*cc_projection"):
        load_zero123(tmp_path)
    (tmp_path / "weights.txt").write_text("")
    with pytest.raises(ValueError, match="unknown zero-1-to-3 checkpoint layout"):
        load_zero123(tmp_path / "weights.txt")
    with pytest.raises(FileNotFoundError):
        load_zero123(tmp_path / "absent.ckpt")


def test_missing_component_folder(source, tmp_path):
    _write_diffusers_folder(source, tmp_path, "cc_projection")
    (tmp_path / "unet" / "config.json").rename(tmp_path / "config.json.bak")
    for file in (tmp_path / "unet").iterdir():
        file.unlink()
    (tmp_path / "unet").rmdir()
    with pytest.raises(ValueError, match=r"missing component folders \['unet'\]"):
        load_zero123(tmp_path)


def test_projection_with_wrong_shape_is_rejected(source, tmp_path):
    _write_diffusers_folder(source, tmp_path, "clip_camera_projection")
    save_file({"proj.weight": torch.zeros(16, 24), "proj.bias": torch.zeros(16)},
              str(tmp_path / "clip_camera_projection" / "diffusion_pytorch_model.safetensors"))
    with pytest.raises(ValueError, match="embedding_dim=16"):
        load_zero123(tmp_path)


def test_ldm_errors_list_what_was_expected(source, encoder_dir, tmp_path):
    path = tmp_path / "model.ckpt"
    state = {k: v for k, v in _ldm_state_dict(source).items() if not k.startswith("cond_stage_model.")}
    torch.save(state, path)
    with pytest.raises(ValueError, match="holds no CLIP image tower.*image_encoder_path"):
        load_zero123(path)

    del state["model.diffusion_model.middle_block.0.in_layers.0.weight"]
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"missing \['mid_block.resnets.0.norm1.weight'\]"):
        load_zero123(path, image_encoder_path=encoder_dir, unet_config=TINY_UNET, vae_config=TINY_VAE)

    state = _ldm_state_dict(source)
    state["cc_projection.weight"] = torch.zeros(16, 30)
    torch.save(state, path)
    with pytest.raises(ValueError, match="pose_projection.config.in_features"):
        load_zero123(path, image_encoder_path=encoder_dir, unet_config=TINY_UNET, vae_config=TINY_VAE)

    state = {k: v for k, v in _ldm_state_dict(source).items() if not k.startswith("first_stage_model.")}
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"missing \['first_stage_model.\*'\]"):
        load_zero123(path, image_encoder_path=encoder_dir)

    state = _ldm_state_dict(source, ema_pipe=source)
    del state["model_ema.diffusion_modelout2weight"]
    torch.save(state, path)
    with pytest.raises(ValueError, match="EMA weights are missing"):
        load_zero123(path, image_encoder_path=encoder_dir)
