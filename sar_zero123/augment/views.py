"""SimCLR views: the baseline dB-domain transforms, the Table I presets and the augmented views.

The SimCLR baselines (Table I rows ``simclr-full``, ``simclr-jitter``) act on the normalised dB image:
random resized crop, flip, brightness/contrast jitter and Gaussian blur, in torch because torchvision must
not be installed beside the CPU torch build (REFERENCE.md). :func:`augment_batch` runs a preset end to end
(magnitude -> co-domain transforms -> normalised dB -> dB-domain transforms); :func:`simclr_views` draws
a SimCLR positive pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Protocol

import torch
import torch.nn.functional as F

from ._batch import (
    _check_images,
    _check_nonnegative,
    _check_probability,
    _check_q,
    _check_range,
    _check_rank4,
    _draw,
    _per_sample,
    _uniform,
)
from .codomain import SpeckleMode, additive_gaussian, random_monotonic, rayleigh_speckle

__all__ = [
    "PRESETS",
    "AugmentationPreset",
    "Scaling",
    "augment_batch",
    "color_jitter",
    "random_gaussian_blur",
    "random_resized_crop",
    "simclr_views",
]


class Scaling(Protocol):
    """Anything that maps magnitude in [0, 1] to normalised dB (e.g. ``sar_zero123.data.DecibelScaling``)."""

    def normalize(self, magnitude: torch.Tensor) -> torch.Tensor: ...


# ------------------------------------ SimCLR baseline transforms (applied to normalised dB images in [0, 1])
def random_resized_crop(
    x: torch.Tensor,
    scale: tuple[float, float] = (0.08, 1.0),
    ratio: tuple[float, float] = (3.0 / 4.0, 4.0 / 3.0),
    flip_p: float = 0.5,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Random resized crop with random horizontal flip, resampled to the input size (SimCLR baseline).

    Per sample, an area fraction ``s ~ U(scale)`` and a log-uniform aspect ratio ``r`` give a crop of
    ``sqrt(s * r)`` x ``sqrt(s / r)`` of width x height (clipped to the side instead of torchvision's
    rejection sampling), placed uniformly, mirrored with probability ``flip_p``, resampled bilinearly in one
    ``grid_sample`` pass (never shrinking, so no anti-aliasing).

    Shape:
        ``(B, C, H, W)`` (any value range) -> the same.

    Raises:
        ValueError: If ``x`` is not rank 4 or a parameter is out of range.
    """
    _check_rank4(x)
    _check_range(scale, "scale")
    if scale[0] <= 0 or scale[1] > 1:
        raise ValueError(f"`scale` must lie within (0, 1], got {scale!r}")
    _check_range(ratio, "ratio")
    if ratio[0] <= 0:
        raise ValueError(f"`ratio` must be positive, got {ratio!r}")
    _check_probability(flip_p, "flip_p")
    b, device, dtype = x.shape[0], x.device, x.dtype
    area = _uniform(scale[0], scale[1], (b,), generator, device, dtype)
    log_ratio = _uniform(math.log(ratio[0]), math.log(ratio[1]), (b,), generator, device, dtype)
    width = torch.sqrt(area * torch.exp(log_ratio)).clamp(max=1.0)  # fraction of the image width
    height = torch.sqrt(area / torch.exp(log_ratio)).clamp(max=1.0)
    # Crop centres in grid_sample's [-1, 1] coordinates, keeping the crop inside the image.
    center_x = (1.0 - width) * _uniform(-1.0, 1.0, (b,), generator, device, dtype)
    center_y = (1.0 - height) * _uniform(-1.0, 1.0, (b,), generator, device, dtype)
    flip = _draw("rand", (b,), generator, device, dtype) < flip_p
    sign_x = torch.where(flip, -1.0, 1.0).to(dtype)
    zeros = torch.zeros_like(width)
    theta = torch.stack(
        [
            torch.stack([width * sign_x, zeros, center_x], dim=1),
            torch.stack([zeros, height, center_y], dim=1),
        ],
        dim=1,
    )  # (B, 2, 3)
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)


def color_jitter(
    x: torch.Tensor,
    brightness: float = 0.4,
    contrast: float = 0.4,
    p: float = 0.8,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Random brightness then contrast jitter on [0, 1] images, applied with probability ``p`` (SimCLR).

    Brightness multiplies by ``b ~ U(max(0, 1 - brightness), 1 + brightness)``; contrast blends with the
    sample's mean, ``c * x + (1 - c) * mean``, ``c ~ U(max(0, 1 - contrast), 1 + contrast)``; each step
    clipped to [0, 1] as torchvision's ``ColorJitter``, in a fixed order (no saturation or hue for SAR).

    Shape:
        ``(B, C, H, W)`` -> the same.

    Raises:
        ValueError: If ``x`` is not rank 4 or a parameter is out of range.
    """
    _check_rank4(x)
    _check_nonnegative(brightness, "brightness")
    _check_nonnegative(contrast, "contrast")
    _check_probability(p, "p")
    b, device, dtype = x.shape[0], x.device, x.dtype
    apply = _per_sample(_draw("rand", (b,), generator, device, dtype) < p)
    bright = _per_sample(_uniform(max(0.0, 1 - brightness), 1 + brightness, (b,), generator, device, dtype))
    contr = _per_sample(_uniform(max(0.0, 1 - contrast), 1 + contrast, (b,), generator, device, dtype))
    jittered = (x * bright).clamp(0.0, 1.0)
    mean = jittered.mean(dim=(1, 2, 3), keepdim=True)
    jittered = torch.lerp(mean, jittered, contr).clamp(0.0, 1.0)
    return torch.where(apply, jittered, x)


def random_gaussian_blur(
    x: torch.Tensor,
    sigma: tuple[float, float] = (0.1, 2.0),
    p: float = 0.5,
    kernel_size: int | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Gaussian blur with a random per-sample sigma ``~ U(sigma)`` pixels, applied with probability ``p``.

    Separable, reflect-padded, one kernel per sample (:func:`_blur_matrix`). ``kernel_size`` defaults to
    SimCLR's 10% of the shorter side, made odd.

    Shape:
        ``(B, C, H, W)`` -> the same.

    Raises:
        ValueError: If ``x`` is not rank 4, a parameter is out of range or the kernel does not fit.
    """
    _check_rank4(x)
    _check_range(sigma, "sigma")
    if sigma[0] <= 0:
        raise ValueError(f"`sigma` must be positive, got {sigma!r}")
    _check_probability(p, "p")
    b, c, h, w = x.shape
    if kernel_size is None:
        kernel_size = max(3, int(0.1 * min(h, w)) // 2 * 2 + 1)
    if kernel_size < 1 or kernel_size % 2 == 0 or kernel_size // 2 >= min(h, w):
        raise ValueError(
            f"`kernel_size` must be odd and smaller than twice the image side, got {kernel_size}"
        )
    device, dtype = x.device, x.dtype
    apply = _per_sample(_draw("rand", (b,), generator, device, dtype) < p)
    sigmas = _uniform(sigma[0], sigma[1], (b,), generator, device, dtype)
    offsets = torch.arange(kernel_size, device=device, dtype=dtype) - kernel_size // 2
    kernel = torch.exp(-0.5 * (offsets[None] / sigmas[:, None]) ** 2)
    kernel = kernel / kernel.sum(dim=1, keepdim=True)  # (B, K)
    rows = _blur_matrix(kernel, h)[:, None]  # (B, 1, H, H)
    cols = _blur_matrix(kernel, w)[:, None].transpose(-1, -2)  # (B, 1, W, W)
    return torch.where(apply, rows @ x @ cols, x)


def _blur_matrix(kernel: torch.Tensor, n: int) -> torch.Tensor:
    """Banded matrices M with ``(M @ v)[i] = sum_k kernel[k] * v[reflect(i + k - K // 2)]``.

    Blurring as ``M_rows @ X @ M_cols^T`` handles a kernel per sample, faster on CPU than a grouped
    ``conv2d``; reflect padding (edge pixel not repeated) is folded into the matrix.

    Shape:
        kernel: ``(B, K)``; output: ``(B, n, n)``.
    """
    b, k = kernel.shape
    source = torch.arange(n, device=kernel.device)[:, None] + torch.arange(k, device=kernel.device) - k // 2
    source = source.abs()
    source = torch.where(source > n - 1, 2 * (n - 1) - source, source)  # (n, K) reflected columns
    matrix = kernel.new_zeros(b, n, n)
    return matrix.scatter_add_(2, source.expand(b, n, k), kernel[:, None, :].expand(b, n, k).contiguous())


# ---------------------------------------------- Presets (Table I rows) and the end-to-end batch augmentation
@dataclass(frozen=True)
class AugmentationPreset:
    """Parameters of one augmentation pipeline; a stage is off when its switch value is 0 / None.

    Stages run in this order: additive Gaussian, Rayleigh speckle and random monotonic map on the
    magnitude; then normalised dB; then random resized crop + flip, brightness/contrast jitter and
    Gaussian blur on the normalised dB image.
    """

    gaussian_std: float = 0.0  # additive Gaussian std on magnitude; 0 = off
    speckle_sigma: float = 0.0  # Rayleigh sigma of Eq. (17); 0 = off
    speckle_lambda1: float = 1.0  # lambda1 of Eq. (18)
    speckle_lambda2: float = 1.0  # lambda2 of Eq. (18)
    speckle_mode: SpeckleMode = "pixel"  # "pixel" (Eq. 17) or "level" (reference code)
    speckle_q: int = 512  # lookup levels of the level-mode speckle table (unused in pixel mode)
    monotonic_q: int = 0  # lookup levels Q of Algorithm 1; 0 = off
    monotonic_gamma: float = 0.0  # std of the random gamma's log-exponent
    codomain_p: float = 1.0  # probability that a chip gets the co-domain stages (reference run: 0.95)
    crop_scale: tuple[float, float] | None = None  # random resized crop area range; None = no crop
    crop_ratio: tuple[float, float] = (3.0 / 4.0, 4.0 / 3.0)  # random resized crop aspect range
    flip_p: float = 0.0  # horizontal flip probability (applied with the crop stage)
    jitter_p: float = 0.0  # probability of brightness/contrast jitter; 0 = off
    brightness: float = 0.0  # brightness jitter strength
    contrast: float = 0.0  # contrast jitter strength
    blur_p: float = 0.0  # probability of Gaussian blur; 0 = off
    blur_sigma: tuple[float, float] = (0.1, 2.0)  # blur sigma range in pixels

    def __post_init__(self) -> None:
        for name in ("gaussian_std", "speckle_sigma", "monotonic_gamma", "brightness", "contrast"):
            _check_nonnegative(getattr(self, name), name)
        _check_nonnegative(self.speckle_lambda1, "speckle_lambda1")
        _check_nonnegative(self.speckle_lambda2, "speckle_lambda2")
        if self.speckle_mode not in ("pixel", "level"):
            raise ValueError(f"`speckle_mode` must be 'pixel' or 'level', got {self.speckle_mode!r}")
        _check_q(self.speckle_q, "speckle_q")
        if self.monotonic_q != 0:
            _check_q(self.monotonic_q, "monotonic_q")
        for name in ("flip_p", "jitter_p", "blur_p", "codomain_p"):
            _check_probability(getattr(self, name), name)
        if self.crop_scale is not None:
            _check_range(self.crop_scale, "crop_scale")
        _check_range(self.crop_ratio, "crop_ratio")
        _check_range(self.blur_sigma, "blur_sigma")

    def to_dict(self) -> dict[str, object]:
        """Plain dict of the fields (for configs and result tables)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


_SPECKLE = {"speckle_sigma": 10.0, "speckle_lambda1": 1.0, "speckle_lambda2": 1.0}
_JITTER = {"jitter_p": 0.8, "brightness": 0.4, "contrast": 0.4, "blur_p": 0.5, "blur_sigma": (0.1, 2.0)}

#: Table I rows. Co-domain settings follow the paper (sigma 10, lambda1 = lambda2 = 1, Q 512, Eq. (17) per
#: pixel, always applied); ``speckle+monotonic-as-run`` is the authors' encoder checkpoint's (level-mode
#: speckle, Q 4096, probability 0.95). The Gaussian std and the SimCLR strengths are this library's choices.
PRESETS: dict[str, AugmentationPreset] = {
    "simclr-full": AugmentationPreset(crop_scale=(0.08, 1.0), flip_p=0.5, **_JITTER),
    "simclr-jitter": AugmentationPreset(**_JITTER),
    "gaussian": AugmentationPreset(gaussian_std=0.03),
    "speckle": AugmentationPreset(monotonic_q=0, **_SPECKLE),
    "monotonic": AugmentationPreset(monotonic_q=512),
    "gaussian+monotonic": AugmentationPreset(gaussian_std=0.03, monotonic_q=512),
    "speckle+monotonic": AugmentationPreset(monotonic_q=512, **_SPECKLE),
    # The authors' encoder run: speckle on the lookup-table levels, each chip unaugmented with probability
    # 0.05.
    "speckle+monotonic-as-run": AugmentationPreset(
        monotonic_q=4096, speckle_mode="level", speckle_q=4096, codomain_p=0.95, **_SPECKLE
    ),
}


def _resolve_preset(preset: str | AugmentationPreset) -> AugmentationPreset:
    if isinstance(preset, AugmentationPreset):
        return preset
    if preset not in PRESETS:
        raise ValueError(
            f"`preset` must be one of {sorted(PRESETS)} or an AugmentationPreset, got {preset!r}"
        )
    return PRESETS[preset]


def augment_batch(
    magnitude: torch.Tensor,
    preset: str | AugmentationPreset,
    scaling: Scaling,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Augment magnitude chips ``(B, 1, H, W)`` in [0, 1] with a preset into normalised-dB views in [0, 1].

    Co-domain stages act on the magnitude, ``scaling.normalize`` maps it to normalised dB (dataset-global
    bounds), the SimCLR stages act on that.

    Raises:
        ValueError: If ``magnitude`` is not a finite ``(B, 1, H, W)`` tensor in [0, 1], the preset is
            unknown, or ``scaling`` has no ``normalize`` method.
    """
    # 1. check inputs
    _check_images(magnitude, "magnitude")
    if magnitude.shape[1] != 1:
        raise ValueError(
            f"`magnitude` must have one channel (B, 1, H, W), got shape {tuple(magnitude.shape)}"
        )
    params = _resolve_preset(preset)
    if not callable(getattr(scaling, "normalize", None)):
        raise ValueError(f"`scaling` must have a `normalize` method, got {type(scaling).__name__}")

    # 2. co-domain transforms on the magnitude
    x = magnitude
    if params.gaussian_std > 0:
        x = additive_gaussian(x, params.gaussian_std, generator)
    if params.speckle_sigma > 0:
        x = rayleigh_speckle(
            x,
            params.speckle_sigma,
            params.speckle_lambda1,
            params.speckle_lambda2,
            params.speckle_mode,
            params.speckle_q,
            generator,
        )
    if params.monotonic_q > 0:
        x = random_monotonic(x, params.monotonic_q, params.monotonic_gamma, generator)
    if params.codomain_p < 1.0:  # the reference code skips the whole co-domain map with probability 1 - p
        applied = _draw("rand", (x.shape[0],), generator, x.device, torch.float32) < params.codomain_p
        x = torch.where(applied[:, None, None, None], x, magnitude)

    # 3. magnitude -> normalised dB (dataset-global bounds)
    x = scaling.normalize(x).to(device=magnitude.device, dtype=magnitude.dtype).clamp(0.0, 1.0)

    # 4. SimCLR baseline transforms in the dB domain
    if params.crop_scale is not None or params.flip_p > 0:
        if params.crop_scale is None:  # flip only: the whole image at its own aspect ratio
            x = random_resized_crop(x, (1.0, 1.0), (1.0, 1.0), params.flip_p, generator)
        else:
            x = random_resized_crop(x, params.crop_scale, params.crop_ratio, params.flip_p, generator)
    if params.jitter_p > 0:
        x = color_jitter(x, params.brightness, params.contrast, params.jitter_p, generator)
    if params.blur_p > 0:
        x = random_gaussian_blur(x, params.blur_sigma, params.blur_p, generator=generator)
    return x.clamp(0.0, 1.0)


def simclr_views(
    magnitude: torch.Tensor,
    preset: str | AugmentationPreset,
    scaling: Scaling,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Two independently augmented views of every chip (the second continues the first's random stream):
    SimCLR's positive pairs. As :func:`augment_batch`, twice.
    """
    view1 = augment_batch(magnitude, preset, scaling, generator)
    view2 = augment_batch(magnitude, preset, scaling, generator)
    return view1, view2
