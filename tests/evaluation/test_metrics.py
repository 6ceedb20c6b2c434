"""Tests for sar_zero123.evaluation.metrics: closed forms, naive reference loops and library cross-checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import linalg
from skimage.metrics import structural_similarity

from sar_zero123.data import center_crop
from sar_zero123.evaluation.metrics import (
    PAPER_MS_SSIM_BETAS,
    axis_error_deg,
    azimuth_error_deg,
    classification_accuracy,
    frechet_distance,
    frechet_distance_from_moments,
    gaussian_kernel_1d,
    kuan_filter,
    kuan_ssim,
    ms_ssim,
    ssim,
)


def _pair(
    batch: int = 2, size: int = 64, noise: float = 0.3, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, 1, size, size, generator=generator)
    y = (1.0 - noise) * x + noise * torch.rand(batch, 1, size, size, generator=generator)
    return x, y


# --- accuracy and azimuth ----------------------------------------------------------------------------


def test_classification_accuracy_from_logits_and_indices() -> None:
    logits = torch.tensor([[2.0, 0.1, 0.0], [0.0, 1.0, 3.0], [0.5, 0.4, 0.0], [0.0, 2.0, 1.0]])
    labels = torch.tensor([0, 1, 0, 1])
    assert classification_accuracy(logits, labels) == pytest.approx(0.75)
    assert classification_accuracy(torch.tensor([1, 1, 2]), torch.tensor([1, 1, 2])) == 1.0
    with pytest.raises(ValueError, match="batch sizes"):
        classification_accuracy(torch.tensor([1, 2]), torch.tensor([1]))


def test_azimuth_error_is_circular_and_symmetric() -> None:
    predicted = torch.tensor([350.0, 10.0, 0.0, 180.0, 720.0 + 5.0, -30.0, 90.0])
    target = torch.tensor([10.0, 350.0, 0.0, 0.0, 0.0, 30.0, 269.0])
    expected = torch.tensor([20.0, 20.0, 0.0, 180.0, 5.0, 60.0, 179.0])
    torch.testing.assert_close(azimuth_error_deg(predicted, target), expected)
    torch.testing.assert_close(azimuth_error_deg(target, predicted), expected)


def test_axis_error_forgives_a_front_back_flip_only() -> None:
    predicted = torch.tensor([350.0, 190.0, 180.0, 90.0, 270.0, 135.0])
    target = torch.tensor([10.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    expected = torch.tensor([20.0, 10.0, 0.0, 90.0, 90.0, 45.0])  # min(e, 180 - e)
    torch.testing.assert_close(axis_error_deg(predicted, target), expected)
    assert axis_error_deg(190.0, 0.0) == 10.0 and axis_error_deg(-100.0, 100.0) == 20.0
    # a uniformly random orientation: 45 deg on average
    uniform = torch.arange(0.0, 360.0, 0.5, dtype=torch.float64)
    assert abs(axis_error_deg(uniform, torch.tensor(0.0, dtype=torch.float64)).mean().item() - 45.0) < 0.01


# --- Frechet distance --------------------------------------------------------------------------------


def test_frechet_from_moments_matches_diagonal_closed_form() -> None:
    # Diagonal (commuting) covariances: d^2 = |mu_a - mu_b|^2 + sum (sqrt(s_a) - sqrt(s_b))^2.
    mean_a, mean_b = np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 0.0])
    var_a, var_b = np.array([1.0, 4.0, 9.0]), np.array([4.0, 1.0, 9.0])
    expected = 1.0 + 0.0 + 4.0 + (1 - 2) ** 2 + (2 - 1) ** 2 + 0.0
    value = frechet_distance_from_moments(mean_a, np.diag(var_a), mean_b, np.diag(var_b))
    assert value == pytest.approx(expected, abs=1e-12)
    assert frechet_distance_from_moments(mean_a, np.diag(var_a), mean_a, np.diag(var_a)) == pytest.approx(
        0.0, abs=1e-12
    )


def test_frechet_from_moments_matches_scipy_sqrtm_for_full_rank() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 5)), rng.normal(size=(5, 5))
    cov_a, cov_b = a @ a.T + 0.1 * np.eye(5), b @ b.T + 0.1 * np.eye(5)
    mean_a, mean_b = rng.normal(size=5), rng.normal(size=5)
    reference = (
        np.sum((mean_a - mean_b) ** 2)
        + np.trace(cov_a)
        + np.trace(cov_b)
        - 2 * np.trace(linalg.sqrtm(cov_a @ cov_b).real)
    )
    value = frechet_distance_from_moments(mean_a, cov_a, mean_b, cov_b)
    assert value == pytest.approx(reference, rel=1e-9)
    assert value == pytest.approx(frechet_distance_from_moments(mean_b, cov_b, mean_a, cov_a), rel=1e-9)


def test_frechet_distance_of_samples_approaches_closed_form() -> None:
    # N(0, I) against N(1, 4 I) in 2-D: d^2 = 2 * 1 + 2 * (2 - 1)^2 = 4.
    rng = np.random.default_rng(1)
    a = rng.normal(size=(20000, 2))
    b = 1.0 + 2.0 * rng.normal(size=(20000, 2))
    assert frechet_distance(a, b) == pytest.approx(4.0, abs=0.1)
    assert frechet_distance(torch.from_numpy(a), torch.from_numpy(a)) == pytest.approx(0.0, abs=1e-9)


def test_frechet_distance_is_finite_and_warns_when_n_below_dimension() -> None:
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(10, 64)), rng.normal(size=(10, 64)) + 0.5
    with pytest.warns(UserWarning, match="n=10 samples for D=64"):
        value = frechet_distance(a, b)
    assert math.isfinite(value) and value > 0
    assert isinstance(value, float)
    with pytest.raises(ValueError, match="n=1"):
        frechet_distance(a[:1], b)
    with pytest.raises(ValueError, match="dimensions"):
        frechet_distance(a, b[:, :3])


# --- SSIM and MS-SSIM ---------------------------------------------------------------------------------


def test_gaussian_kernel_is_normalised_and_symmetric() -> None:
    kernel = gaussian_kernel_1d(7, 1.0)
    assert kernel.sum().item() == pytest.approx(1.0)
    torch.testing.assert_close(kernel, kernel.flip(0))
    assert kernel[3].item() == pytest.approx(1.0 / sum(math.exp(-(k**2) / 2) for k in range(-3, 4)))


def test_identical_images_score_one() -> None:
    x, _ = _pair(batch=3, size=128)
    for metric in (ssim, ms_ssim, kuan_ssim):
        torch.testing.assert_close(metric(x, x), torch.ones(3, dtype=torch.float64))


def test_ssim_matches_skimage_with_same_window() -> None:
    # skimage fixes a 9x9 window for sigma 1.0 (truncate 3.5); at 9x9 the two must agree to round-off.
    x, y = _pair(batch=2, size=64)
    ours = ssim(x, y, kernel_size=9, crop_size=None)
    reference = [
        structural_similarity(
            x[i, 0].double().numpy(),
            y[i, 0].double().numpy(),
            gaussian_weights=True,
            sigma=1.0,
            use_sample_covariance=False,
            data_range=1.0,
        )
        for i in range(2)
    ]
    torch.testing.assert_close(ours, torch.tensor(reference, dtype=torch.float64), atol=1e-12, rtol=0)


def test_ssim_is_symmetric_and_hand_computed_for_constant_images() -> None:
    x, y = _pair()
    torch.testing.assert_close(ssim(x, y), ssim(y, x))
    # Constant images a and b: sigma terms vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    a, b, c1 = 0.2, 0.6, 0.01**2
    constant_a, constant_b = torch.full((1, 1, 64, 64), a), torch.full((1, 1, 64, 64), b)
    expected = (2 * a * b + c1) / (a**2 + b**2 + c1)
    assert ssim(constant_a, constant_b).item() == pytest.approx(expected, rel=1e-6)
    # MS-SSIM on constants: cs = 1 at every scale, so only l^{beta_3} remains.
    expected_ms = expected ** PAPER_MS_SSIM_BETAS[-1]
    assert ms_ssim(constant_a, constant_b).item() == pytest.approx(expected_ms, rel=1e-6)


def test_ms_ssim_pinned_values_and_torchmetrics_cross_check() -> None:
    from torchmetrics.functional.image import multiscale_structural_similarity_index_measure

    x, y = _pair(batch=2, size=64, noise=0.3)
    paper = ms_ssim(x, y, crop_size=None)
    nine = ms_ssim(x, y, kernel_size=9, crop_size=None)

    def torchmetrics_ms_ssim(betas: tuple[float, ...]) -> torch.Tensor:
        return multiscale_structural_similarity_index_measure(
            x, y, betas=betas, kernel_size=9, sigma=1.0, data_range=1.0, reduction="none", normalize="relu"
        ).double()

    # Contrast-structure terms (valid region in both) agree to float32 precision: zero last-scale weight.
    contrast_only = (0.0448, 0.3001, 0.0)
    torch.testing.assert_close(
        ms_ssim(x, y, betas=contrast_only, kernel_size=9, crop_size=None),
        torchmetrics_ms_ssim(contrast_only),
        atol=1e-5,
        rtol=0,
    )
    # Full setting: torchmetrics averages the last-scale luminance over reflect-padded borders too,
    # which moves the value by a few 1e-3.
    torch.testing.assert_close(nine, torchmetrics_ms_ssim(PAPER_MS_SSIM_BETAS), atol=5e-3, rtol=0)
    # The paper's 7x7 window differs from 9x9 by a measurable, small amount on this pair.
    assert 1e-4 < (paper - nine).abs().max().item() < 5e-3
    torch.testing.assert_close(paper, torch.tensor([0.9461, 0.9457], dtype=torch.float64), atol=1e-4, rtol=0)
    torch.testing.assert_close(ms_ssim(x, y), ms_ssim(y, x))


def test_ms_ssim_uses_centre_crop() -> None:
    x, y = _pair(batch=1, size=128)
    y_outside = x.clone()
    y_outside[..., :20, :] = y[..., :20, :]  # change only pixels outside the 64x64 centre
    assert ms_ssim(x, y_outside).item() == pytest.approx(1.0)
    assert ms_ssim(x, y_outside, crop_size=None).item() < 0.999
    assert center_crop(x, 64).shape == (1, 1, 64, 64)


def test_image_metrics_reject_bad_input() -> None:
    x, y = _pair(size=64)
    with pytest.raises(ValueError, match="differ in size"):
        ms_ssim(x, y[..., :60, :60])
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        ms_ssim(x * 2.0, y)
    with pytest.raises(ValueError, match="smaller than crop_size=64"):
        kuan_ssim(x[..., :32, :32], y[..., :32, :32])


# --- Kuan filter ---------------------------------------------------------------------------------------


def _kuan_loop(image: np.ndarray, window: int, cu: float) -> np.ndarray:
    radius = window // 2
    padded = np.pad(image, radius, mode="reflect")
    out = np.empty_like(image)
    for i in range(image.shape[0]):
        for j in range(image.shape[1]):
            patch = padded[i : i + window, j : j + window]
            mean, var = patch.mean(), patch.var()
            if var == 0:
                weight = 0.0
            else:
                ci2 = var / mean**2 if mean != 0 else np.inf
                weight = float(np.clip((1 - cu**2 / ci2) / (1 + cu**2), 0.0, 1.0))
            out[i, j] = mean + weight * (image[i, j] - mean)
    return out


def test_kuan_filter_matches_per_pixel_loop() -> None:
    rng = np.random.default_rng(3)
    # Speckled scene: a bright scatterer on a dim clutter background, multiplicative Rayleigh noise.
    scene = np.full((20, 17), 0.2)
    scene[8:12, 6:10] = 0.9
    image = scene * rng.rayleigh(scale=1 / math.sqrt(math.pi / 2), size=scene.shape)
    image[0, 0:7] = 0.0  # a flat zero run reaches the border
    expected = _kuan_loop(image, window=7, cu=0.25)
    ours = kuan_filter(torch.from_numpy(image), window=7, cu=0.25).numpy()
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-12)
    batch = kuan_filter(torch.from_numpy(np.stack([image, image]))[:, None].float())
    assert batch.shape == (2, 1, 20, 17) and batch.dtype == torch.float32
    np.testing.assert_allclose(batch[1, 0].numpy(), expected, atol=1e-6)


def test_kuan_filter_limits() -> None:
    constant = torch.full((1, 1, 16, 16), 0.4)
    torch.testing.assert_close(kuan_filter(constant), constant)
    # cu = 0: W = 1 everywhere the variance is positive -> identity.
    x, _ = _pair(batch=1, size=16)
    torch.testing.assert_close(kuan_filter(x, cu=0.0), x)
    with pytest.raises(ValueError, match="odd"):
        kuan_filter(x, window=6)


def test_kuan_ssim_smooths_speckle_differences() -> None:
    # Two independent speckle realisations of one scene: the filter removes much of the disagreement.
    rng = np.random.default_rng(4)
    scene = np.full((128, 128), 0.15)
    scene[40:90, 50:80] = 0.5
    looks = [scene * rng.gamma(shape=16.0, scale=1 / 16.0, size=scene.shape) for _ in range(2)]
    x, y = (torch.from_numpy(np.clip(look, 0.0, 1.0))[None, None].float() for look in looks)
    torch.testing.assert_close(kuan_ssim(x, y), kuan_ssim(y, x))
    assert kuan_ssim(x, y).item() > ssim(x, y).item() + 0.1


# --- input validation (issue 11): one case per kind of bad input -----------------------------------------
def _pair64():
    return _pair(size=64)


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (lambda: ms_ssim(*_pair64(), betas=(0.0448, -0.3, 0.1333)), ValueError, r"betas must be finite"),
        (lambda: ms_ssim(*(t.numpy() for t in _pair64())), TypeError, r"first image must be a torch.Tensor"),
        (lambda: ms_ssim(*(t[:0] for t in _pair64())), ValueError, r"empty batch"),
        (lambda: kuan_filter(torch.rand(16, 16), cu=float("nan")), ValueError, r"cu must be finite"),
        (lambda: kuan_filter(-torch.rand(16, 16)), ValueError, r"image must be finite and non-negative"),
        (lambda: classification_accuracy(torch.zeros(2, 3), torch.tensor([0.7, 1.2])), ValueError,
         r"labels must hold integer class indices, got dtype torch.float32"),
        (lambda: classification_accuracy(torch.tensor([0.4, 1.0]), torch.tensor([0, 1])), ValueError,
         r"\(B,\) predictions must hold integer class indices"),
        (lambda: azimuth_error_deg(torch.zeros(4, 1), torch.zeros(4)), ValueError,
         r"predicted_deg \(4, 1\) and target_deg \(4,\) must have the same shape"),
        (lambda: azimuth_error_deg(torch.tensor([float("nan")]), torch.zeros(1)), ValueError,
         r"predicted_deg contains non-finite"),
        (lambda: frechet_distance(np.full((4, 2), 1e200) * np.arange(4)[:, None], np.ones((4, 2))),
         ValueError, r"overflow their covariance"),
    ],
    ids=["negative-beta", "numpy-input", "batch-0", "nan-cu", "negative-image", "float-labels",
         "float-index-predictions", "azimuth-shapes", "nan-azimuth", "frechet-huge"],
)  # fmt: skip
def test_metrics_refuse_bad_input_naming_it(call, error, match) -> None:
    with pytest.raises(error, match=match):
        call()


def test_azimuth_error_takes_a_scalar_target() -> None:
    torch.testing.assert_close(azimuth_error_deg(torch.tensor([350.0, 20.0]), torch.tensor(10.0)),
                               torch.tensor([20.0, 10.0]))  # fmt: skip
