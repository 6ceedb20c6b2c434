"""Co-domain augmentations of SAR magnitudes (paper Sec. III): they change pixel values, never geometry.

All act on the magnitude in [0, 1], batched ``(B, C, H, W)``, one draw per sample, explicit ``generator``:
the random monotonic map (Algorithm 1), Rayleigh speckle (Eq. 17-18) and additive Gaussian noise.
:func:`readd_speckle` applies the speckle model to a decoder's smooth views, in normalised dB.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F

from ._batch import (
    _check_images,
    _check_nonnegative,
    _check_positive,
    _check_q,
    _draw,
    _minmax_per_sample,
)

__all__ = [
    "SpeckleMode",
    "additive_gaussian",
    "apply_lookup_table",
    "log_speckle_stats",
    "random_monotonic",
    "rayleigh_speckle",
    "readd_speckle",
    "sample_monotonic_map",
    "sample_rayleigh",
    "speckle_magnitude",
]

SpeckleMode = Literal["pixel", "level"]


# ------------------------------------------------------------------------ Random monotonic map (Algorithm 1)
def sample_monotonic_map(
    batch_size: int,
    q: int = 512,
    gamma: float = 0.0,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Sample random monotonic lookup tables ``(B, Q)``, Algorithm 1 steps 1-3.

    Values on the Q uniform levels ``k / (Q - 1)``: Q-1 i.i.d. draws ``r_i ~ U(0, 1]`` prefixed with 0,
    cumulatively summed and divided by the total, so ``T(0) = 0``, ``T(1) = 1`` and T strictly increases.
    With ``gamma > 0``, ``T -> T ** exp(alpha)`` with ``alpha ~ N(0, gamma)`` keeps both.

    Args:
        q: Lookup levels Q (>= 2); a larger Q is closer to the identity at scales coarser than
            ``1 / (Q - 1)``.
        gamma: Standard deviation of the log-exponent alpha (>= 0); 0 disables the gamma curve.

    Raises:
        ValueError: If ``q < 2``, ``gamma < 0`` or ``batch_size < 1``.
    """
    _check_q(q)
    _check_nonnegative(gamma, "gamma")
    if batch_size < 1:
        raise ValueError(f"`batch_size` must be >= 1, got {batch_size}")
    device = torch.device(device)
    # Half-precision cumulative sums of hundreds of terms would create ties: build in >= float32.
    work_dtype = torch.promote_types(dtype, torch.float32)
    # 1 - U[0, 1) lies in (0, 1]: strictly positive increments give a strictly increasing map.
    increments = 1.0 - _draw("rand", (batch_size, q - 1), generator, device, work_dtype)  # (B, Q-1)
    table = F.pad(torch.cumsum(increments, dim=1), (1, 0))  # (B, Q), starts at 0
    table = table / table[:, -1:]
    if gamma > 0:
        alpha = gamma * _draw("randn", (batch_size, 1), generator, device, work_dtype)  # (B, 1)
        table = table ** torch.exp(alpha)
    return table.to(dtype)


def apply_lookup_table(x: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Apply one lookup table per sample by linear interpolation between its uniform levels (Alg. 1 step 4).

    Shape:
        x ``(B, C, H, W)`` in [0, 1], table ``(B, Q)`` -> ``(B, C, H, W)``, ``x``'s dtype and device.

    Raises:
        ValueError: If the table is not ``(B, Q)`` with ``Q >= 2`` and the batch size of ``x``.
    """
    if table.ndim != 2 or table.shape[0] != x.shape[0] or table.shape[1] < 2:
        raise ValueError(f"`table` must have shape (B={x.shape[0]}, Q>=2), got {tuple(table.shape)}")
    b, q = table.shape
    table = table.to(device=x.device, dtype=x.dtype).view(b, 1, 1, q)  # a (1 x Q) image per sample
    # With align_corners=True, grid coordinate 2m - 1 lands on level m * (Q - 1): bilinear grid_sampling
    # of the table row is exactly linear interpolation between levels (faster on CPU than two gathers).
    grid = F.pad(x.reshape(b, 1, -1, 1) * 2.0 - 1.0, (0, 1))  # (B, 1, N, 2)
    return F.grid_sample(table, grid, mode="bilinear", padding_mode="border", align_corners=True).view_as(x)


def random_monotonic(
    x: torch.Tensor,
    q: int = 512,
    gamma: float = 0.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Random monotonic map of the co-domain, Algorithm 1: one map per sample (shared by its channels),
    drawn independently of the pixels, so pixel order is preserved, 0 stays 0 and 1 stays 1.

    Shape:
        ``(B, C, H, W)`` magnitudes in [0, 1] -> the same.

    Raises:
        ValueError: If ``x`` is not a finite rank-4 tensor in [0, 1], ``q < 2`` or ``gamma < 0``.
    """
    _check_images(x)
    table = sample_monotonic_map(x.shape[0], q, gamma, generator, x.device, x.dtype)
    return apply_lookup_table(x, table)


# ------------------------------------------------------------------------------ Rayleigh speckle (Eq. 17-18)
def sample_rayleigh(
    shape: tuple[int, ...],
    sigma: float = 10.0,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Draw the multiplicative speckle ``eps ~ Rayleigh(sigma)`` of shape ``shape``, Eq. (17).

    Inverse-CDF sampling ``sigma * sqrt(-2 ln U)``, ``U`` in (0, 1] (torch has no Rayleigh); mean
    ``sigma * sqrt(pi / 2)``, variance ``(4 - pi) / 2 * sigma ** 2``.

    Raises:
        ValueError: If ``sigma <= 0``.
    """
    _check_positive(sigma, "sigma")
    uniform = 1.0 - _draw("rand", tuple(shape), generator, torch.device(device), dtype)  # (0, 1]
    return uniform.log_().mul_(-2.0).sqrt_().mul_(sigma)


def speckle_magnitude(
    m: torch.Tensor, eps: torch.Tensor, lambda1: float = 1.0, lambda2: float = 1.0
) -> torch.Tensor:
    """Speckled magnitude before normalisation, Eq. (18): ``lambda1 * m + lambda2 * m * eps``.

    For constant m and ``eps ~ Rayleigh(sigma)``: mean ``m * (lambda1 + lambda2 * sigma * sqrt(pi / 2))``,
    variance ``(lambda2 * m * sigma) ** 2 * (4 - pi) / 2``. The shape is ``m``'s and ``eps``'s broadcast.

    Raises:
        ValueError: If a lambda is negative or not finite.
    """
    _check_nonnegative(lambda1, "lambda1")
    _check_nonnegative(lambda2, "lambda2")
    return m * (lambda1 + lambda2 * eps)  # Eq. (18) factored: one product per pixel fewer


def rayleigh_speckle(
    x: torch.Tensor,
    sigma: float = 10.0,
    lambda1: float = 1.0,
    lambda2: float = 1.0,
    mode: SpeckleMode = "pixel",
    q: int = 512,
    generator: torch.Generator | None = None,
    normalize: bool = True,
) -> torch.Tensor:
    """Rayleigh speckle augmentation, Eq. (17)-(18), then per-sample min-max back to [0, 1].

    ``mode="pixel"`` draws one ``eps`` per pixel as Eq. (17) states. ``mode="level"`` follows the paper's
    reference implementation: ``eps`` per level of a Q-level table ``k / (Q - 1)``, Eq. (18) on the table,
    min-max normalised and applied by interpolation: a deterministic, for large ``sigma`` non-monotonic,
    function of the pixel value with no spatial noise.

    Args:
        normalize: False returns Eq. (18) before min-max normalisation (pixel mode only).

    Shape:
        ``(B, C, H, W)`` magnitudes in [0, 1] -> the same.

    Raises:
        ValueError: If ``x`` is not a finite rank-4 tensor in [0, 1], ``sigma <= 0``, a lambda is
            negative, ``mode`` is unknown, ``q < 2`` in level mode, or ``normalize=False`` in level mode.
    """
    _check_images(x)
    _check_positive(sigma, "sigma")
    _check_nonnegative(lambda1, "lambda1")
    _check_nonnegative(lambda2, "lambda2")
    if mode == "pixel":
        eps = sample_rayleigh(tuple(x.shape), sigma, generator, x.device, x.dtype)
        speckled = speckle_magnitude(x, eps, lambda1, lambda2)
        return _minmax_per_sample(speckled) if normalize else speckled
    if mode == "level":
        _check_q(q)
        if not normalize:
            raise ValueError("`normalize` must be True when `mode` is 'level' (the table is normalised)")
        levels = torch.linspace(0.0, 1.0, q, device=x.device, dtype=x.dtype).expand(x.shape[0], q)
        eps = sample_rayleigh((x.shape[0], q), sigma, generator, x.device, x.dtype)  # (B, Q)
        table = _minmax_per_sample(speckle_magnitude(levels, eps, lambda1, lambda2))
        return apply_lookup_table(x, table)
    raise ValueError(f"`mode` must be 'pixel' or 'level', got {mode!r}")


# ----------------------------------------------------------------------------------- Additive Gaussian noise
def additive_gaussian(
    x: torch.Tensor, std: float = 0.03, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Additive white Gaussian noise on the magnitude, ``clip(x + std * n, 0, 1)`` (Table I row "Gaussian").

    The default ``std`` is about the median MSTAR clutter magnitude (pixel / 255): it changes the
    background in dB while barely touching the bright scatterers.

    Shape:
        ``(B, C, H, W)`` magnitudes in [0, 1] -> the same.

    Raises:
        ValueError: If ``x`` is not a finite rank-4 tensor in [0, 1] or ``std < 0``.
    """
    _check_images(x)
    _check_nonnegative(std, "std")
    noise = _draw("randn", tuple(x.shape), generator, x.device, x.dtype)
    return (x + std * noise).clamp(0.0, 1.0)


# --------------------------------------------------------------- Speckle re-added to a smooth (decoded) view
def log_speckle_stats(looks: int) -> tuple[float, float]:
    """Mean and standard deviation, in dB, of ``10 log10 g`` for L-look speckle ``g ~ Gamma(L, 1/L)``.

    Closed forms: mean ``(10 / ln 10) (psi(L) - ln L)``, standard deviation ``(10 / ln 10) sqrt(psi_1(L))``
    (digamma and trigamma): -2.51 dB and 5.57 dB for single-look speckle, whose amplitude is Rayleigh.

    Raises:
        ValueError: If ``looks`` is not an integer >= 1.
    """
    _check_looks(looks)
    scale = 10.0 / math.log(10.0)
    value = torch.tensor(float(looks), dtype=torch.float64)
    mean = scale * (float(torch.special.digamma(value)) - math.log(looks))
    std = scale * math.sqrt(float(torch.special.polygamma(1, value)))
    return mean, std


def readd_speckle(
    x: torch.Tensor, db_range: float, looks: int = 1, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Speckle re-added to smooth views in normalised dB: Eq. (17)'s model on a decoder's output.

    A decoder trained with a pixel loss regresses to the local mean of the log image, so its views lack
    the speckle a classifier trained on real chips reads. Each pixel gets an L-look intensity factor
    ``g ~ Gamma(L, 1/L)`` (single look: a Rayleigh amplitude), added in dB without its mean:

        x' = clip(x + (10 log10 g - E[10 log10 g]) / db_range, 0, 1)

    Args:
        db_range: ``max_db - min_db`` of the views' ``DecibelScaling``.
        looks: Independent looks L (>= 1; MSTAR chips are single look).

    Shape:
        ``(B, C, H, W)`` in [0, 1] -> the same.

    Raises:
        ValueError: If ``x`` is not a finite rank-4 tensor in [0, 1], ``db_range <= 0`` or ``looks`` is not
            an integer >= 1.
    """
    _check_images(x)
    _check_positive(db_range, "db_range")
    mean_db, _ = log_speckle_stats(looks)
    shape = (looks, *x.shape)
    # L-look intensity: the mean of L unit exponentials, each -ln U with U in (0, 1]
    uniform = 1.0 - _draw("rand", shape, generator, x.device, torch.float32)
    intensity = (-uniform.log()).mean(dim=0)
    speckle_db = 10.0 * torch.log10(intensity.clamp_min(torch.finfo(torch.float32).tiny)) - mean_db
    return (x + (speckle_db / db_range).to(x.dtype)).clamp(0.0, 1.0)


def _check_looks(looks: int) -> None:
    if isinstance(looks, bool) or not isinstance(looks, int) or looks < 1:
        raise ValueError(f"`looks` must be an integer >= 1, got {looks!r}")
