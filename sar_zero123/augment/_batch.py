"""What every augmentation shares: argument checks and per-sample random draws.

Random numbers are drawn on the generator's device and then moved to the data's device, so one CPU
generator gives the same random draws whatever device the images live on.
"""

from __future__ import annotations

import math
from typing import Literal

import torch


def _check_rank4(x: torch.Tensor, name: str = "x") -> None:
    """Raise ``ValueError`` unless ``x`` is a (B, C, H, W) batch."""
    if x.ndim != 4:
        raise ValueError(f"`{name}` must have rank 4 (B, C, H, W), got shape {tuple(x.shape)}")


def _check_images(x: torch.Tensor, name: str = "x") -> None:
    """Raise ``ValueError`` unless ``x`` is a finite floating (B, C, H, W) tensor with values in [0, 1]."""
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"`{name}` must be a torch.Tensor, got {type(x).__name__}")
    _check_rank4(x, name)
    if not x.is_floating_point():
        raise ValueError(f"`{name}` must be a floating tensor, got dtype {x.dtype}")
    if x.numel() == 0:
        raise ValueError(f"`{name}` must not be empty, got shape {tuple(x.shape)}")
    # One fused pass and one device sync: NaN propagates into both extremes and fails the comparisons.
    low, high = (value.item() for value in torch.aminmax(x))
    if not (low >= 0.0 and high <= 1.0):
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"`{name}` contains non-finite values")
        raise ValueError(f"`{name}` must lie in [0, 1], got min {low:.4g} and max {high:.4g}")


def _check_q(q: int, name: str = "q") -> None:
    if isinstance(q, bool) or not isinstance(q, int) or q < 2:
        raise ValueError(f"`{name}` (number of lookup levels) must be an integer >= 2, got {q!r}")


def _check_nonnegative(value: float, name: str) -> None:
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"`{name}` must be a finite number >= 0, got {value!r}")


def _check_positive(value: float, name: str) -> None:
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"`{name}` must be a finite number > 0, got {value!r}")


def _check_probability(value: float, name: str) -> None:
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"`{name}` must be a probability in [0, 1], got {value!r}")


def _check_range(value: tuple[float, float], name: str, low: float = 0.0) -> None:
    if len(value) != 2 or not low <= value[0] <= value[1] or not math.isfinite(value[1]):
        raise ValueError(f"`{name}` must be a pair (lo, hi) with {low} <= lo <= hi, got {value!r}")


def _draw(
    kind: Literal["rand", "randn"],
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    device: torch.device,
    dtype: torch.dtype,
) -> torch.Tensor:
    """Draw on the generator's device, then move (a seed gives the same random numbers on every device).

    Hand-written rather than diffusers' ``randn_tensor`` because uniform draws are needed too and
    importing diffusers here would make the data-loading path pay for the whole library.
    """
    draw_device = generator.device if generator is not None else device
    sampler = torch.rand if kind == "rand" else torch.randn
    return sampler(shape, generator=generator, device=draw_device, dtype=dtype).to(device)


def _uniform(
    low: float | torch.Tensor,
    high: float | torch.Tensor,
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    device: torch.device,
    dtype: torch.dtype,
) -> torch.Tensor:
    return low + (high - low) * _draw("rand", shape, generator, device, dtype)


def _minmax_per_sample(y: torch.Tensor) -> torch.Tensor:
    """Min-max normalise each sample (over all non-batch dims) to [0, 1]; a constant sample maps to 0."""
    low, high = torch.aminmax(y.flatten(1), dim=1)
    low = low.view(-1, *([1] * (y.ndim - 1)))
    span = high.view_as(low) - low
    return torch.where(span > 0, (y - low) / span.clamp_min(torch.finfo(y.dtype).tiny), torch.zeros_like(y))


def _per_sample(values: torch.Tensor) -> torch.Tensor:
    """(B,) -> (B, 1, 1, 1) for broadcasting against images."""
    return values.view(-1, 1, 1, 1)
