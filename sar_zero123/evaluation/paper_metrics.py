"""Paper-comparable MS-SSIM and Kuan+SSIM: the authors' scoring calls, reproduced without their libraries.

Table III's numbers come from the authors' scripts (`zero123/eval_metrics/` of
AmirooR/noise-tolerant-sar-synthesis), not from the definitions in the text. They:

1. read 8-bit PNG views of 256 x 256 (128 px chips resized bilinearly; zero-1-to-3 decodes 32 x 32
   latents to 256 px), quantised by truncation, `(x * 255).astype(np.uint8)`;
2. crop the centre 64 x 64 (the central 32 x 32 pixels of a 128 px chip, upsampled two-fold);
3. MS-SSIM: torchmetrics `MultiScaleStructuralSimilarityIndexMeasure(data_range=1.0, kernel_size=7,
   sigma=1.0, betas=(0.0448, 0.3001, 0.1333))` on pixel / 255, which ignores `kernel_size` (a 9 x 9
   Gaussian, radius `int(3.5 sigma + 0.5)`), averages the contrast-structure terms over the valid region
   but the last scale's SSIM over the reflect-padded map, and clips negative terms (`normalize="relu"`);
4. Kuan+SSIM: findpeaks' `kuan_filter(win_size=7, cu=0.25)` on the 0-255 image (window rows `i-3 .. i+2`,
   columns `j-3 .. j+2`, truncated at the borders, population std, output rounded half to even), then
   scikit-image's `structural_similarity(data_range=255, win_size=7)` (uniform window, sample covariance,
   mean over the valid region).

This module computes exactly that in float64 (tests/evaluation/test_paper_metrics.py checks it against
torchmetrics, scikit-image and a loop port of findpeaks); the corrected variants are in
:mod:`sar_zero123.evaluation.metrics`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from sar_zero123.evaluation.metrics import (
    CROP_SIZE,
    PAPER_MS_SSIM_BETAS,
    combine_scales,
    gaussian_kernel_1d,
    ssim_maps,
)

PAPER_SCORING_SIZE = 256
"""Side in pixels of the images the authors scored (zero-1-to-3 resolution; 128 px chips resized to it)."""

PAPER_MS_SSIM_SIGMA = 1.0
"""Gaussian sigma of the authors' MS-SSIM; torchmetrics derives a 9 x 9 window from it."""

PAPER_KUAN_WINDOW = 7
"""`win_size` the authors passed to findpeaks' Kuan filter (a 6 x 6 effective window)."""

PAPER_KUAN_CU = 0.25
"""Speckle coefficient of variation the authors passed to the Kuan filter."""

PAPER_SSIM_WINDOW = 7
"""Uniform SSIM window after the Kuan filter (scikit-image's default `win_size`)."""

_K1 = 0.01
_K2 = 0.03


def to_paper_scoring_images(
    images: torch.Tensor, *, scoring_size: int | None = PAPER_SCORING_SIZE, crop_size: int = CROP_SIZE
) -> torch.Tensor:
    """The 8-bit centre crop the authors scored: grey channel (channels averaged), resized to
    `scoring_size` (bilinear, `align_corners=False`, antialiased when shrinking; `None` keeps the size),
    quantised `floor(255 x)`, centre `crop_size` crop.

    Returns:
        Float64 integer values in [0, 255].

    Shape:
        `(B, C, H, W) -> (B, 1, crop_size, crop_size)`.

    Raises:
        ValueError: For images that are not 4-D, outside [0, 1] or not finite, or a crop larger than the
            scored image.
    """
    if images.ndim != 4:
        raise ValueError(f"images must be (B, C, H, W); got {tuple(images.shape)}")
    if not torch.isfinite(images).all():
        raise ValueError("images contain non-finite values")
    low, high = images.min().item(), images.max().item()
    if low < 0.0 or high > 1.0:
        raise ValueError(f"images have values in [{low:.4g}, {high:.4g}], outside [0, 1]")
    grey = images.double().mean(dim=1, keepdim=True)
    if scoring_size is not None and tuple(grey.shape[-2:]) != (scoring_size, scoring_size):
        shrinking = min(grey.shape[-2:]) > scoring_size
        grey = F.interpolate(
            grey, size=(scoring_size, scoring_size), mode="bilinear", align_corners=False, antialias=shrinking
        ).clamp(0.0, 1.0)
    height, width = grey.shape[-2:]
    if height < crop_size or width < crop_size:
        raise ValueError(f"images of size {height}x{width} are smaller than the {crop_size}x{crop_size} crop")
    quantised = torch.floor(grey * 255.0)
    top, left = (height - crop_size) // 2, (width - crop_size) // 2
    return quantised[..., top : top + crop_size, left : left + crop_size]


def _box_sums(image: torch.Tensor, offset: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sums over the truncated windows `[i - offset, i + offset)` x `[j - offset, j + offset)`, and counts."""
    height, width = image.shape[-2:]
    integral = F.pad(image.cumsum(-2).cumsum(-1), (1, 0, 1, 0))  # (..., H + 1, W + 1)
    rows = torch.arange(height)
    cols = torch.arange(width)
    top, bottom = (rows - offset).clamp_min(0), (rows + offset).clamp_max(height)
    left, right = (cols - offset).clamp_min(0), (cols + offset).clamp_max(width)

    def corner(r: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return integral[..., r, :][..., c]

    sums = corner(bottom, right) - corner(top, right) - corner(bottom, left) + corner(top, left)
    counts = ((bottom - top)[:, None] * (right - left)[None, :]).to(image.dtype)  # (H, W)
    return sums, counts


def kuan_filter_findpeaks(
    image: torch.Tensor, *, win_size: int = PAPER_KUAN_WINDOW, cu: float = PAPER_KUAN_CU
) -> torch.Tensor:
    """Kuan filter as findpeaks' `kuan_filter` computes it (the filter behind the paper's Kuan+SSIM).

    With `o = win_size // 2`, pixel `(i, j)`'s window is rows `max(0, i - o) .. min(i + o, H) - 1`, the same
    for columns: `2 o` wide, not centred, truncated at the borders. With window mean `m` and population
    `Ci = std / m`: `W = 0` where `Ci < Cu`, else `(1 - Cu^2 / Ci^2) / (1 + Cu^2)`;
    `out = round(W pix + (1 - W) m)` (half to even); an all-zero window gives 0.

    Shape:
        `(H, W)` or `(B, C, H, W)` on the 0-255 scale -> the same, float64 integer-valued.

    Raises:
        ValueError: For `win_size < 3`, negative `cu` or values, or an image that is not 2-D or 4-D.
    """
    if win_size < 3:
        raise ValueError(f"win_size must be >= 3; got {win_size}")
    if cu < 0:
        raise ValueError(f"cu must be non-negative; got {cu}")
    if image.ndim not in (2, 4):
        raise ValueError(f"image must be (H, W) or (B, C, H, W); got {tuple(image.shape)}")
    work = image.double()
    if (work < 0).any():
        raise ValueError("image has negative values; the Kuan filter needs magnitudes")
    # Integer-valued inputs keep the window sums exact, so the mean matches findpeaks' bit for bit.
    sums, counts = _box_sums(work, win_size // 2)
    squares, _ = _box_sums(work * work, win_size // 2)
    mean = sums / counts
    variance = (squares / counts - mean * mean).clamp_min(0.0)
    ci_squared = torch.where(mean > 0, variance / (mean * mean).clamp_min(1e-300), 0.0)
    weight = torch.where(
        ci_squared < cu**2, 0.0, (1.0 - cu**2 / ci_squared.clamp_min(1e-300)) / (1.0 + cu**2)
    )
    return torch.round(work * weight + mean * (1.0 - weight))


def ssim_uniform_window(
    x: torch.Tensor, y: torch.Tensor, *, win_size: int = PAPER_SSIM_WINDOW, data_range: float = 255.0
) -> torch.Tensor:
    """SSIM as scikit-image's `structural_similarity` computes it with its defaults.

    Uniform `win_size x win_size` window, sample (co)variances (`N / (N - 1)`), `C1 = (0.01 L)^2`,
    `C2 = (0.03 L)^2`, the map's mean over the windows inside the image, no clipping of the variances.

    Shape:
        `(B, C, H, W) -> (B,)` float64.

    Raises:
        ValueError: For mismatched shapes, an even window, or images smaller than the window.
    """
    if x.shape != y.shape or x.ndim != 4:
        raise ValueError(f"x and y must be equal (B, C, H, W); got {tuple(x.shape)} and {tuple(y.shape)}")
    if win_size % 2 == 0 or min(x.shape[-2:]) < win_size:
        raise ValueError(f"win_size must be odd and <= the image side; got {win_size} for {tuple(x.shape)}")
    x, y = x.double(), y.double()

    def box(image: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(image, win_size, stride=1)

    covariance_norm = win_size**2 / (win_size**2 - 1.0)
    c1, c2 = (_K1 * data_range) ** 2, (_K2 * data_range) ** 2
    mu_x, mu_y = box(x), box(y)
    var_x = covariance_norm * (box(x * x) - mu_x * mu_x)
    var_y = covariance_norm * (box(y * y) - mu_y * mu_y)
    cov_xy = covariance_norm * (box(x * y) - mu_x * mu_y)
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / (
        (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    )
    return ssim_map.flatten(1).mean(1)


def _torchmetrics_ssim_terms(
    x: torch.Tensor, y: torch.Tensor, kernel_1d: torch.Tensor, data_range: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample (SSIM over the whole reflect-padded map, contrast-structure over the valid region)."""
    pad = (kernel_1d.shape[0] - 1) // 2
    x = F.pad(x, (pad, pad, pad, pad), mode="reflect")
    y = F.pad(y, (pad, pad, pad, pad), mode="reflect")
    ssim_map, contrast_structure = ssim_maps(x, y, kernel_1d, data_range)
    valid = contrast_structure[..., pad:-pad, pad:-pad]
    return ssim_map.flatten(1).mean(1), valid.flatten(1).mean(1)


def ms_ssim_torchmetrics(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    betas: Sequence[float] = PAPER_MS_SSIM_BETAS,
    sigma: float = PAPER_MS_SSIM_SIGMA,
    data_range: float = 1.0,
) -> torch.Tensor:
    """MS-SSIM as torchmetrics computes it with `gaussian_kernel=True` (whatever `kernel_size` says).

    A Gaussian window of side `2 int(3.5 sigma + 0.5) + 1`; scales `1 .. M - 1` give their
    contrast-structure mean over the valid region, the last its SSIM mean over the reflect-padded map; each
    clipped at 0 and raised to its beta; 2 x 2 average pooling between scales.

    Shape:
        `(B, C, H, W)` in [0, `data_range`] -> `(B,)` float64.

    Raises:
        ValueError: For mismatched shapes or images too small for the window at the coarsest scale.
    """
    if x.shape != y.shape or x.ndim != 4:
        raise ValueError(f"x and y must be equal (B, C, H, W); got {tuple(x.shape)} and {tuple(y.shape)}")
    kernel = gaussian_kernel_1d(2 * int(3.5 * sigma + 0.5) + 1, sigma)
    coarsest = min(x.shape[-2:]) // 2 ** (len(betas) - 1)
    if coarsest <= kernel.shape[0] // 2:
        raise ValueError(f"images of size {tuple(x.shape[-2:])} are too small for {len(betas)} scales")
    terms = lambda a, b: _torchmetrics_ssim_terms(a, b, kernel, data_range)  # noqa: E731
    return combine_scales(x.double(), y.double(), betas, terms)


def paper_ms_ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    scoring_size: int | None = PAPER_SCORING_SIZE,
    crop_size: int = CROP_SIZE,
) -> torch.Tensor:
    """Paper-comparable MS-SSIM (Table III): the authors' torchmetrics call on their 8-bit crop
    (:func:`to_paper_scoring_images`).

    Shape:
        x (generated), y (target) `(B, C, H, W)` in [0, 1] -> `(B,)` float64.

    Raises:
        ValueError: For mismatched shapes or values outside [0, 1].
    """
    x8, y8 = _paper_crops(x, y, scoring_size, crop_size)
    return ms_ssim_torchmetrics(x8 / 255.0, y8 / 255.0)


def paper_kuan_ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    scoring_size: int | None = PAPER_SCORING_SIZE,
    crop_size: int = CROP_SIZE,
) -> torch.Tensor:
    """Paper-comparable Kuan+SSIM (Table III): findpeaks' Kuan filter on the 8-bit crop (not the whole
    image, as the authors did), then scikit-image's default SSIM with `data_range=255`.

    Shape:
        x (generated), y (target) `(B, C, H, W)` in [0, 1] -> `(B,)` float64.

    Raises:
        ValueError: For mismatched shapes or values outside [0, 1].
    """
    x8, y8 = _paper_crops(x, y, scoring_size, crop_size)
    return ssim_uniform_window(kuan_filter_findpeaks(x8), kuan_filter_findpeaks(y8), data_range=255.0)


def _paper_crops(
    x: torch.Tensor, y: torch.Tensor, scoring_size: int | None, crop_size: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generated and target views as the authors scored them (:func:`to_paper_scoring_images`)."""
    if x.shape != y.shape:
        raise ValueError(f"generated and target images differ in size: {tuple(x.shape)} != {tuple(y.shape)}")
    x8 = to_paper_scoring_images(x, scoring_size=scoring_size, crop_size=crop_size)
    return x8, to_paper_scoring_images(y, scoring_size=scoring_size, crop_size=crop_size)


__all__ = [
    "PAPER_KUAN_CU",
    "PAPER_KUAN_WINDOW",
    "PAPER_MS_SSIM_SIGMA",
    "PAPER_SCORING_SIZE",
    "PAPER_SSIM_WINDOW",
    "kuan_filter_findpeaks",
    "ms_ssim_torchmetrics",
    "paper_kuan_ssim",
    "paper_ms_ssim",
    "ssim_uniform_window",
    "to_paper_scoring_images",
]

