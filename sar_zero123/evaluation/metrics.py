"""Metrics that score generated SAR views against their targets (paper Table III).

* classification accuracy of a ResNet-18 classifier trained on real chips,
* circular azimuth error of a ResNet-18 + MLP azimuth regressor,
* SFD, the Frechet distance between that regressor's pre-head features of generated and real views,
* MS-SSIM (3 scales, weights (0.0448, 0.3001, 0.1333), data range 1, Gaussian sigma 1) on the 64x64 crop,
* Kuan+SSIM: a Kuan speckle filter on both images, then SSIM on the 64x64 centre crop.

The **paper-comparable** MS-SSIM and Kuan+SSIM (:mod:`sar_zero123.evaluation.paper_metrics`) reproduce the
authors' scripts (8-bit 256 px views, torchmetrics' 9x9-window MS-SSIM, findpeaks' 6x6 rounded Kuan,
scikit-image's uniform-window SSIM). The **corrected** ones here implement the stated definitions: one
true 7x7 Gaussian window averaged over the valid region (Wang et al. 2003), a centred 7x7 reflect-padded
Kuan filter without rounding, at the generated resolution. Table III reports both.

Image metrics take `(B, C, H, W)` in [0, 1] (normalised dB) and return per-sample `(B,)` scores. With a
9x9 window `ssim` equals scikit-image's Gaussian SSIM and the contrast-structure terms torchmetrics'
(tests/evaluation/test_metrics.py); the full `ms_ssim` differs from torchmetrics', which averages the last
scale over the reflect-padded map.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from sar_zero123.domain import center_crop

PAPER_MS_SSIM_BETAS: tuple[float, float, float] = (0.0448, 0.3001, 0.1333)
"""MS-SSIM scale weights of the paper (the first, middle and last of Wang et al.'s five weights)."""

CROP_SIZE = 64
"""The paper scores MS-SSIM and Kuan+SSIM on the 64x64 centre crop, where the target sits."""

_K1 = 0.01
_K2 = 0.03


# ---------------------------------------------------------------------- Classifier / regressor based metrics
def classification_accuracy(predictions: torch.Tensor, labels: torch.Tensor) -> float:
    """Fraction of samples whose predicted class (logits `(B, K)` arg-max, or indices `(B,)`) equals the
    label `(B,)`.

    Raises:
        ValueError: if the batch sizes differ or the batch is empty, or class indices are not integers.
    """
    if labels.is_floating_point() or labels.is_complex() or labels.dtype == torch.bool:
        raise ValueError(f"labels must hold integer class indices, got dtype {labels.dtype} (truncated)")
    if predictions.ndim == 1 and (predictions.is_floating_point() or predictions.is_complex()):
        raise ValueError(
            f"(B,) predictions must hold integer class indices, got dtype {predictions.dtype}; pass (B, K) "
            "logits to take the arg-max"
        )
    if predictions.ndim == 2:
        predictions = predictions.argmax(dim=1)
    if predictions.ndim != 1 or labels.ndim != 1:
        raise ValueError(
            f"predictions must be (B, K) logits or (B,) indices and labels (B,); got predictions "
            f"{tuple(predictions.shape)} and labels {tuple(labels.shape)}"
        )
    if predictions.shape[0] != labels.shape[0]:
        raise ValueError(
            f"predictions and labels have different batch sizes: {predictions.shape[0]} != {labels.shape[0]}"
        )
    if labels.shape[0] == 0:
        raise ValueError("labels is empty: accuracy of zero samples is undefined")
    return (predictions.long() == labels.long()).double().mean().item()


def axis_error_deg(
    predicted_deg: torch.Tensor | float | Sequence[float], target_deg: torch.Tensor | float | Sequence[float]
) -> torch.Tensor | float:
    """Azimuth error up to a front/back flip, ``min(e, 180 - e)`` with ``e = azimuth_error_deg``, in [0, 90].

    A view turned to the requested heading with front and back swapped has an azimuth error near 180 and
    an axis error near 0: it says whether a generator turns the body at all (45 deg for random
    orientations). Arguments, shapes and errors as :func:`azimuth_error_deg`;
    ``axis_error_deg(190.0, 0.0) == 10.0``.
    """
    error = azimuth_error_deg(predicted_deg, target_deg)
    if isinstance(error, float):
        return min(error, 180.0 - error)
    return torch.minimum(error, 180.0 - error)


def azimuth_error_deg(
    predicted_deg: torch.Tensor | float | Sequence[float], target_deg: torch.Tensor | float | Sequence[float]
) -> torch.Tensor | float:
    """Circular absolute azimuth error `min(|a - b|, 360 - |a - b|)` in [0, 180] degrees.

    Any real angles (modulo 360); a plain `float` when both inputs are plain numbers
    (`azimuth_error_deg(350.0, 10.0) == 20.0`).

    Shape:
        `(B,)` -> `(B,)`; a scalar target broadcasts, other shapes must be equal.

    Raises:
        ValueError: if the shapes differ (`(B, 1)` against `(B,)` would compare every pair) or a value is
            not finite.
    """
    scalars = isinstance(predicted_deg, numbers.Real) and isinstance(target_deg, numbers.Real)
    # Numbers and lists become float64 tensors; a tensor keeps its dtype and device.
    if not isinstance(predicted_deg, torch.Tensor):
        predicted_deg = torch.as_tensor(predicted_deg, dtype=torch.float64)
    if not isinstance(target_deg, torch.Tensor):
        target_deg = torch.as_tensor(target_deg, dtype=torch.float64, device=predicted_deg.device)
    if predicted_deg.shape != target_deg.shape and target_deg.numel() != 1:
        raise ValueError(
            f"predicted_deg {tuple(predicted_deg.shape)} and target_deg {tuple(target_deg.shape)} must have "
            "the same shape (one target per prediction)"
        )
    for name, value in (("predicted_deg", predicted_deg), ("target_deg", target_deg)):
        if not torch.isfinite(value).all():
            raise ValueError(f"{name} contains non-finite azimuths")
    difference = torch.remainder(predicted_deg - target_deg, 360.0)
    error = torch.minimum(difference, 360.0 - difference)
    return float(error) if scalars else error


def frechet_distance_from_moments(
    mean_a: np.ndarray, covariance_a: np.ndarray, mean_b: np.ndarray, covariance_b: np.ndarray
) -> float:
    """Frechet (2-Wasserstein squared) distance between two Gaussians, in float64.

    `d^2 = ||mu_a - mu_b||^2 + tr(S_a) + tr(S_b) - 2 tr((S_a^{1/2} S_b S_a^{1/2})^{1/2})`.

    The cross term comes from the eigenvalues of the symmetric PSD `S_a^{1/2} S_b S_a^{1/2}`, round-off
    negatives clipped: unlike `scipy.linalg.sqrtm(S_a @ S_b)` never complex or NaN for rank-deficient
    covariances, and no diagonal epsilon.

    Shape:
        means `(D,)`, covariances `(D, D)`.

    Raises:
        ValueError: if the shapes do not agree.
    """
    mean_a, mean_b = np.asarray(mean_a, np.float64), np.asarray(mean_b, np.float64)
    covariance_a, covariance_b = np.asarray(covariance_a, np.float64), np.asarray(covariance_b, np.float64)
    dim = mean_a.shape[0]
    if mean_a.shape != (dim,) or mean_b.shape != (dim,):
        raise ValueError(f"means must both be (D,); got {mean_a.shape} and {mean_b.shape}")
    if covariance_a.shape != (dim, dim) or covariance_b.shape != (dim, dim):
        raise ValueError(
            f"covariances must be ({dim}, {dim}); got {covariance_a.shape} and {covariance_b.shape}"
        )
    # 1. S_a^{1/2} via the symmetric eigendecomposition.
    eigenvalues_a, eigenvectors_a = np.linalg.eigh((covariance_a + covariance_a.T) / 2.0)
    sqrt_a = (eigenvectors_a * np.sqrt(np.clip(eigenvalues_a, 0.0, None))) @ eigenvectors_a.T
    # 2. tr((S_a^{1/2} S_b S_a^{1/2})^{1/2}) = sum of square roots of its (non-negative) eigenvalues.
    middle = sqrt_a @ covariance_b @ sqrt_a
    eigenvalues_middle = np.linalg.eigvalsh((middle + middle.T) / 2.0)
    trace_sqrt = np.sqrt(np.clip(eigenvalues_middle, 0.0, None)).sum()
    # 3. Assemble.
    distance = (
        np.sum((mean_a - mean_b) ** 2) + np.trace(covariance_a) + np.trace(covariance_b) - 2.0 * trace_sqrt
    )
    return float(max(distance, 0.0))


def frechet_distance(features_a: torch.Tensor | np.ndarray, features_b: torch.Tensor | np.ndarray) -> float:
    """Frechet distance between the Gaussian fits of two feature sets `(N_a, D)`, `(N_b, D)` (SFD).

    The value depends strongly on the sample count: compare numbers only at equal n.

    Raises:
        ValueError: if either set has fewer than 2 samples, the feature sizes differ, or a value is not
            finite.

    Warns:
        UserWarning: when a set has no more samples than dimensions (n <= D): the covariance is then
            rank-deficient and the value biased.
    """
    a = _as_float64_matrix(features_a, "features_a")
    b = _as_float64_matrix(features_b, "features_b")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"features_a has {a.shape[1]} dimensions but features_b has {b.shape[1]}")
    for name, features in (("features_a", a), ("features_b", b)):
        if features.shape[0] <= features.shape[1]:
            warnings.warn(
                f"{name} has n={features.shape[0]} samples for D={features.shape[1]} feature dimensions "
                f"(n <= D): its covariance is rank-deficient and the Frechet distance is biased; compare "
                f"values only at equal n",
                UserWarning,
                stacklevel=2,
            )
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is reported below, by name
        covariance_a, covariance_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    largest = max(np.abs(a).max(), np.abs(b).max())
    if not (np.isfinite(covariance_a).all() and np.isfinite(covariance_b).all()):
        raise ValueError(
            f"features up to {largest:.3g} overflow their covariance in float64; rescale the features"
        )
    try:
        return frechet_distance_from_moments(a.mean(axis=0), covariance_a, b.mean(axis=0), covariance_b)
    except np.linalg.LinAlgError as error:
        raise ValueError(
            f"the Frechet distance's eigendecomposition failed ({error}) for features up to {largest:.3g}; "
            "rescale the features"
        ) from error


def _as_float64_matrix(features: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    if isinstance(features, torch.Tensor):
        features = features.detach().cpu().double().numpy()
    features = np.asarray(features, dtype=np.float64)
    if features.ndim != 2:
        raise ValueError(f"{name} must be (N, D); got shape {features.shape}")
    if features.shape[0] < 2:
        raise ValueError(f"{name} has n={features.shape[0]} samples; the Frechet distance needs at least 2")
    if not np.isfinite(features).all():
        raise ValueError(f"{name} contains non-finite values")
    return features


# ------------------------------------------------------------------------------------- Structural similarity
def _check_image_pair(x: torch.Tensor, y: torch.Tensor) -> None:
    for name, image in (("first image", x), ("second image", y)):
        if not isinstance(image, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor (B, C, H, W), got {type(image).__name__}")
    if x.ndim != 4 or y.ndim != 4:
        raise ValueError(f"images must be (B, C, H, W); got {tuple(x.shape)} and {tuple(y.shape)}")
    if x.shape != y.shape:
        raise ValueError(f"generated and target images differ in size: {tuple(x.shape)} != {tuple(y.shape)}")
    if x.shape[0] == 0:
        raise ValueError(f"images are an empty batch: {tuple(x.shape)}")
    for name, image in (("first image", x), ("second image", y)):
        if not torch.isfinite(image).all():
            raise ValueError(f"{name} contains non-finite values")
        low, high = image.min().item(), image.max().item()
        if low < 0.0 or high > 1.0:
            raise ValueError(
                f"{name} has values in [{low:.4g}, {high:.4g}], outside [0, 1]: metrics expect normalised dB"
            )


def gaussian_kernel_1d(kernel_size: int, sigma: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Normalised 1-D Gaussian window `exp(-k^2 / (2 sigma^2))`, `k = -(n-1)/2 ... (n-1)/2`.

    Raises:
        ValueError: if `kernel_size` is not a positive odd integer or `sigma <= 0`.
    """
    if kernel_size <= 0 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer; got {kernel_size}")
    if sigma <= 0:
        raise ValueError(f"sigma must be positive; got {sigma}")
    coords = torch.arange(kernel_size, dtype=dtype) - (kernel_size - 1) / 2.0
    kernel = torch.exp(-(coords**2) / (2.0 * sigma**2))
    return kernel / kernel.sum()


def ssim_maps(
    x: torch.Tensor, y: torch.Tensor, kernel_1d: torch.Tensor, data_range: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The SSIM and contrast-structure maps under a separable window, valid convolution only (pad first
    for other borders). Shape: ``(B, C, H, W)`` -> twice ``(B, C, H - K + 1, W - K + 1)``."""
    channels = x.shape[1]
    size = kernel_1d.shape[0]
    window = kernel_1d.to(x)
    window_h = window.view(1, 1, size, 1).expand(channels, 1, size, 1)
    window_w = window.view(1, 1, 1, size).expand(channels, 1, 1, size)

    def blur(image: torch.Tensor) -> torch.Tensor:
        # Separable Gaussian, valid convolution (each output pixel sees a full window).
        return F.conv2d(F.conv2d(image, window_h, groups=channels), window_w, groups=channels)

    c1 = (_K1 * data_range) ** 2
    c2 = (_K2 * data_range) ** 2
    mu_x, mu_y = blur(x), blur(y)
    sigma_xx = (blur(x * x) - mu_x**2).clamp_min(0.0)
    sigma_yy = (blur(y * y) - mu_y**2).clamp_min(0.0)
    sigma_xy = blur(x * y) - mu_x * mu_y
    contrast_structure = (2.0 * sigma_xy + c2) / (sigma_xx + sigma_yy + c2)
    luminance = (2.0 * mu_x * mu_y + c1) / (mu_x**2 + mu_y**2 + c1)
    return luminance * contrast_structure, contrast_structure


def _ssim_terms(
    x: torch.Tensor, y: torch.Tensor, kernel_1d: torch.Tensor, data_range: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample mean SSIM and mean contrast-structure term over the valid region (no padding)."""
    ssim_map, contrast_structure = ssim_maps(x, y, kernel_1d, data_range)
    return ssim_map.flatten(1).mean(1), contrast_structure.flatten(1).mean(1)


def ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    kernel_size: int = 7,
    sigma: float = 1.0,
    data_range: float = 1.0,
    crop_size: int | None = CROP_SIZE,
) -> torch.Tensor:
    """Gaussian-window SSIM (Wang et al. 2004), averaged over the valid region of each image.

    Args:
        data_range: dynamic range L (`C1 = (0.01 L)^2`, `C2 = (0.03 L)^2`).
        crop_size: score the centre `crop_size x crop_size` crop; `None` the whole image.

    Shape:
        x (generated), y (target) `(B, C, H, W)` in [0, 1] -> `(B,)` float64.

    Raises:
        ValueError: for mismatched sizes, values outside [0, 1], or images smaller than the crop or window.
    """
    _check_image_pair(x, y)
    x, y = _prepare(x, y, crop_size, kernel_size, scales=1)
    value, _ = _ssim_terms(x, y, gaussian_kernel_1d(kernel_size, sigma), data_range)
    return value


def ms_ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    betas: Sequence[float] = PAPER_MS_SSIM_BETAS,
    kernel_size: int = 7,
    sigma: float = 1.0,
    data_range: float = 1.0,
    crop_size: int | None = CROP_SIZE,
) -> torch.Tensor:
    """Multi-scale SSIM with the paper's stated setting, corrected variant (Table III "MS-SSIM"; the
    authors' call is :func:`~sar_zero123.evaluation.paper_metrics.paper_ms_ssim`).

    `MS-SSIM = l_M^{beta_M} * prod_{j=1..M} cs_j^{beta_j}` (Wang, Simoncelli and Bovik 2003), 2x2 average
    pooling between scales, negative terms clipped to 0 before the powers (torchmetrics' `normalize="relu"`).

    Shape:
        x (generated), y (target) `(B, C, H, W)` in [0, 1] -> `(B,)` float64; 1 for identical images.

    Raises:
        ValueError: for mismatched sizes, values outside [0, 1], or images too small for the scales.
    """
    _check_image_pair(x, y)
    if len(betas) < 1:
        raise ValueError("betas must contain at least one scale weight")
    if not all(math.isfinite(beta) and beta >= 0 for beta in betas):
        raise ValueError(f"betas must be finite and >= 0 (exponents of the scale terms), got {tuple(betas)}")
    x, y = _prepare(x, y, crop_size, kernel_size, scales=len(betas))
    kernel = gaussian_kernel_1d(kernel_size, sigma)
    return combine_scales(x, y, betas, lambda a, b: _ssim_terms(a, b, kernel, data_range))


def combine_scales(x: torch.Tensor, y: torch.Tensor, betas: Sequence[float], ssim_terms) -> torch.Tensor:
    """MS-SSIM's product over scales: contrast-structure terms at the finer scales, full SSIM at the
    coarsest, each clamped at 0 and raised to its beta (finest first), 2x average pooling between.

    Args:
        ssim_terms: ``(x, y) -> (ssim, contrast_structure)``, each ``(B,)``, at one scale.

    Shape:
        ``(B, C, H, W) -> (B,)``.
    """
    factors = []
    for scale, beta in enumerate(betas):
        value, contrast_structure = ssim_terms(x, y)
        last = scale == len(betas) - 1
        factors.append((value if last else contrast_structure).clamp_min(0.0) ** beta)
        if not last:
            x, y = F.avg_pool2d(x, 2), F.avg_pool2d(y, 2)
    return torch.stack(factors).prod(dim=0)


def _prepare(
    x: torch.Tensor, y: torch.Tensor, crop_size: int | None, kernel_size: int, scales: int
) -> tuple[torch.Tensor, torch.Tensor]:
    if crop_size is not None:
        x, y = center_crop(x, crop_size), center_crop(y, crop_size)
    smallest = min(x.shape[-2:]) // 2 ** (scales - 1)
    if smallest < kernel_size:
        raise ValueError(
            f"images of size {tuple(x.shape[-2:])} are too small for {scales} scale(s) with a "
            f"{kernel_size}x{kernel_size} window (coarsest scale {smallest} px)"
        )
    return x.double(), y.double()


# ----------------------------------------------------------------------------------------------- Kuan filter
def kuan_filter(image: torch.Tensor, window: int = 7, cu: float = 0.25) -> torch.Tensor:
    """Kuan adaptive speckle filter with a full square window and reflect-padded borders.

    With local mean `m` and population variance `v` over the window: `Ci^2 = v / m^2`,
    `W = (1 - Cu^2 / Ci^2) / (1 + Cu^2)` clipped to [0, 1], `out = m + W (pix - m)` (the mean where
    `v = 0`). Borders reflect without repeating the edge pixel; no rounding. Hand-written because findpeaks
    uses a 6x6 effective window, truncates borders and rounds.

    Args:
        image: `(B, C, H, W)` or `(H, W)` non-negative image.
        window: odd window size; 7 in the paper.
        cu: speckle coefficient of variation `Cu = 1/sqrt(ENL)`.

    Raises:
        ValueError: for an even or non-positive window, a window larger than the image, or negative `cu`.
    """
    if window <= 0 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd integer; got {window}")
    if not (math.isfinite(cu) and cu >= 0):
        raise ValueError(f"cu must be finite and non-negative; got {cu}")
    if not torch.isfinite(image).all() or (image < 0).any():
        raise ValueError("image must be finite and non-negative (a SAR magnitude or normalised dB image)")
    squeeze = image.ndim == 2
    batch = image[None, None] if squeeze else image
    if batch.ndim != 4:
        raise ValueError(f"image must be (H, W) or (B, C, H, W); got {tuple(image.shape)}")
    radius = window // 2
    if min(batch.shape[-2:]) <= radius:
        raise ValueError(
            f"image of size {tuple(batch.shape[-2:])} is too small for a {window}x{window} window"
        )
    work = batch.double()
    padded = F.pad(work, (radius, radius, radius, radius), mode="reflect")
    local_mean = F.avg_pool2d(padded, window, stride=1)
    local_var = (F.avg_pool2d(padded * padded, window, stride=1) - local_mean**2).clamp_min(0.0)
    # Cu^2 / Ci^2 = Cu^2 m^2 / v; zero variance means a perfectly homogeneous window -> weight 0.
    ratio = torch.where(local_var > 0, cu**2 * local_mean**2 / local_var.clamp_min(1e-300), math.inf)
    weight = ((1.0 - ratio) / (1.0 + cu**2)).clamp(0.0, 1.0)
    filtered = (local_mean + weight * (work - local_mean)).to(image.dtype)
    return filtered[0, 0] if squeeze else filtered


def kuan_ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    window: int = 7,
    cu: float = 0.25,
    kernel_size: int = 7,
    sigma: float = 1.0,
    data_range: float = 1.0,
    crop_size: int | None = CROP_SIZE,
) -> torch.Tensor:
    """Kuan+SSIM of Table III, corrected variant: Kuan-filter both full images (the crop sees no padded
    border), then :func:`ssim` on the centre crop (the authors' is
    :func:`~sar_zero123.evaluation.paper_metrics.paper_kuan_ssim`).

    Shape:
        x (generated), y (target) `(B, C, H, W)` in [0, 1] -> `(B,)` float64.

    Raises:
        ValueError: for mismatched sizes or values outside [0, 1].
    """
    _check_image_pair(x, y)
    # The Kuan output is a convex combination of in-range values, so it stays in [0, 1]; clamp round-off.
    filtered_x = kuan_filter(x, window=window, cu=cu).clamp(0.0, 1.0)
    filtered_y = kuan_filter(y, window=window, cu=cu).clamp(0.0, 1.0)
    return ssim(
        filtered_x,
        filtered_y,
        kernel_size=kernel_size,
        sigma=sigma,
        data_range=data_range,
        crop_size=crop_size,
    )
