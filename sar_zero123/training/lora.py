"""Low-rank fine-tunes of the UNet (LoRA, Hu et al. 2021) through ``peft``, merged away at export.

Training only a low-rank update ``B A`` beside each frozen weight moves less of what the prior knew.
``B`` starts at zero, so the first step's model is the prior; :func:`merged_unet` folds
``W + (alpha / r) B A`` back into plain layers. The layers are chosen here because peft's ``"all-linear"``
skips the convolutions, which hold most of a small SAR UNet's weights.
"""

from __future__ import annotations

import copy
from typing import Literal, get_args

import torch
from diffusers import UNet2DConditionModel

__all__ = [
    "LORA_MODULE_SETS", "LoraModules", "add_lora", "check_lora_settings", "has_lora", "lora_target_modules",
    "merged_unet",
]  # fmt: skip

LoraModules = Literal["attention", "all"]
#: ``attention``: the query, key, value and output projections of every attention layer (diffusers'
#: text-to-image LoRA recipe); ``all``: every ``Linear`` and ``Conv2d`` of the UNet.
LORA_MODULE_SETS: tuple[str, ...] = get_args(LoraModules)
_ATTENTION_PROJECTIONS = ("to_q", "to_k", "to_v", "to_out.0")


def check_lora_settings(rank: int | None, alpha: float | None = None, modules: str = "all") -> None:
    """The one check of the LoRA settings: a rank below 1, ``alpha <= 0`` or an unknown layer set is refused
    (``None`` rank: no LoRA).
    """
    if rank is not None and (isinstance(rank, bool) or not rank >= 1):
        raise ValueError(f"lora_rank must be >= 1 or None, got {rank}")
    if alpha is not None and not alpha > 0:
        raise ValueError(f"lora_alpha must be > 0 or None, got {alpha}")
    if modules not in LORA_MODULE_SETS:
        raise ValueError(f"lora_modules must be one of {LORA_MODULE_SETS}, got {modules!r}")


def lora_target_modules(unet: torch.nn.Module, modules: LoraModules = "all") -> list[str]:
    """The full names of the UNet layers that receive LoRA factors, in ``named_modules`` order.

    Raises:
        ValueError: If ``modules`` is not one of :data:`LORA_MODULE_SETS`.
    """
    check_lora_settings(None, modules=modules)
    names = []
    for name, module in unet.named_modules():
        if not isinstance(module, torch.nn.Linear | torch.nn.Conv2d):
            continue
        if modules == "all" or name.endswith(_ATTENTION_PROJECTIONS):
            names.append(name)
    return names


def add_lora(
    unet: UNet2DConditionModel, *, rank: int, alpha: float | None = None, modules: LoraModules = "all"
) -> list[torch.nn.Parameter]:
    """Freeze ``unet`` and add trainable LoRA factors of rank ``rank`` to its ``modules`` (in place).

    ``alpha`` is the update's scale numerator (``W + (alpha / r) B A``; ``None``: ``rank``).

    Returns:
        The trainable factors (``B`` zero, ``A`` Kaiming-uniform), so the output is unchanged until a step.

    Raises:
        ValueError: For a setting :func:`check_lora_settings` refuses, or a UNet that already has LoRA.
    """
    from peft import LoraConfig  # imported here: only LoRA fine-tunes need peft

    check_lora_settings(rank, alpha, modules)
    if has_lora(unet):
        raise ValueError("unet: already has LoRA factors; merge them (merged_unet) before adding new ones")
    targets = lora_target_modules(unet, modules)
    unet.requires_grad_(False)
    config = LoraConfig(r=rank, lora_alpha=float(rank if alpha is None else alpha), target_modules=targets)
    unet.add_adapter(config)
    factors = [parameter for name, parameter in unet.named_parameters() if "lora_" in name]
    for parameter in factors:
        parameter.requires_grad_(True)
    return factors


def has_lora(unet: torch.nn.Module) -> bool:
    """Whether ``unet`` carries peft LoRA layers."""
    return any("lora_" in name for name, _ in unet.named_parameters())


def merged_unet(unet: UNet2DConditionModel) -> UNet2DConditionModel:
    """A plain copy of ``unet`` with every LoRA update folded into its weights (``unet`` is left as it is), so
    an exported pipeline loads without ``peft``. A UNet without LoRA layers is returned itself.
    """
    if not has_lora(unet):
        return unet
    merged = copy.deepcopy(unet)
    merged.fuse_lora(lora_scale=1.0)
    merged.unload_lora()
    plain = UNet2DConditionModel.from_config(unet.config)
    plain.load_state_dict(merged.state_dict())  # strict: no factor or base_layer key may remain
    weight = next(unet.parameters())
    plain.to(weight.device)
    return plain if weight.dtype == torch.float32 else plain.to(weight.dtype)
