"""Tests for sar_zero123.evaluation.paper_metrics against the authors' calls: scikit-image defaults,
torchmetrics MS-SSIM and a per-pixel loop port of findpeaks' Kuan filter."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from sar_zero123.evaluation.metrics import PAPER_MS_SSIM_BETAS, kuan_ssim, ms_ssim
from sar_zero123.evaluation.paper_metrics import (
    kuan_filter_findpeaks,
    ms_ssim_torchmetrics,
    paper_kuan_ssim,
    paper_ms_ssim,
    ssim_uniform_window,
    to_paper_scoring_images,
)


def _speckled_pair(batch: int = 2, size: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Two related SAR-like images in [0, 1]: a bright blob with multiplicative speckle, shifted."""
    generator = torch.Generator().manual_seed(seed)
    coords = torch.linspace(-1, 1, size)
    blob = torch.exp(-(coords[:, None] ** 2 + coords[None, :] ** 2) / 0.1)
    speckle = torch.empty(batch, 1, size, size).exponential_(generator=generator)
    x = (0.2 + 0.6 * blob) * speckle
    y = (0.2 + 0.6 * blob.roll(3, dims=1)) * torch.empty_like(x).exponential_(generator=generator)
    return x.clamp(0, 1), y.clamp(0, 1)


def _findpeaks_kuan_loop(image: np.ndarray, win_size: int = 7, cu: float = 0.25) -> np.ndarray:
    """Per-pixel loop with findpeaks' window bounds, weighting and rounding (written from its behaviour)."""
    rows, cols = image.shape
    offset = win_size // 2
    out = np.zeros_like(image, dtype=np.float64)
    for i in range(rows):
        for j in range(cols):
            top, bottom = max(0, i - offset), min(i + offset, rows)
            left, right = max(0, j - offset), min(j + offset, cols)
            window = image[top:bottom, left:right]
            mean = window.mean()
            if mean == 0:
                out[i, j] = 0.0
                continue
            ci = window.std() / mean
            weight = 0.0 if cu > ci else (1.0 - cu**2 / ci**2) / (1.0 + cu**2)
            out[i, j] = round(image[i, j] * weight + mean * (1.0 - weight))
    return out


def test_findpeaks_window_is_six_wide_and_truncated() -> None:
    # One slightly brighter pixel on a flat background (Ci < Cu, so W = 0 and out = round(window mean)):
    # out(i, j) moves off the background only where rows i-3 .. i+2 and columns j-3 .. j+2 contain the
    # pixel (r, c), i.e. i in [r-2, r+3]: the window is 6 wide and sits one pixel up-left of centre.
    image = torch.full((16, 16), 100.0, dtype=torch.float64)
    image[8, 8] = 130.0
    filtered = kuan_filter_findpeaks(image)
    rows, cols = torch.nonzero(filtered != 100.0, as_tuple=True)
    assert filtered[8, 8].item() == 101.0  # round(100 + 30 / 36)
    assert (rows.min().item(), rows.max().item()) == (6, 11)
    assert (cols.min().item(), cols.max().item()) == (6, 11)
    # Truncated corner window of (0, 0) is 3 x 3; a constant window returns its value unchanged.
    assert kuan_filter_findpeaks(torch.full((8, 8), 37.0)).unique().tolist() == [37.0]


def test_findpeaks_kuan_matches_loop_port() -> None:
    x, y = _speckled_pair(batch=2, size=40)
    images = torch.floor(torch.cat([x, y]) * 255.0).double()  # (4, 1, 40, 40), 8-bit values
    ours = kuan_filter_findpeaks(images)
    for k in range(images.shape[0]):
        reference = _findpeaks_kuan_loop(images[k, 0].numpy())
        np.testing.assert_array_equal(ours[k, 0].numpy(), reference)
    assert torch.equal(ours, torch.round(ours))


def test_uniform_ssim_matches_skimage_defaults() -> None:
    x, y = _speckled_pair(batch=2, size=48)
    x, y = torch.floor(x * 255).double(), torch.floor(y * 255).double()
    ours = ssim_uniform_window(x, y, data_range=255.0)
    reference = [
        structural_similarity(x[k, 0].numpy(), y[k, 0].numpy(), data_range=255.0, win_size=7)
        for k in range(2)
    ]
    torch.testing.assert_close(ours, torch.tensor(reference, dtype=torch.float64), atol=1e-10, rtol=0)


def test_paper_kuan_ssim_reproduces_authors_pipeline_at_native_size() -> None:
    # The authors' chain on a 64 px crop: x255 -> findpeaks Kuan -> skimage SSIM(data_range=255, win 7).
    x, y = _speckled_pair(batch=3, size=96)
    ours = paper_kuan_ssim(x, y, scoring_size=None)
    reference = []
    for k in range(3):
        crops = [torch.floor(image[k, 0, 16:80, 16:80] * 255.0).double().numpy() for image in (x, y)]
        filtered = [_findpeaks_kuan_loop(crop) for crop in crops]
        reference.append(structural_similarity(*filtered, data_range=255.0, win_size=7))
    torch.testing.assert_close(ours, torch.tensor(reference, dtype=torch.float64), atol=1e-10, rtol=0)
    # Hard-coded values (float64, this seed), tolerance 1e-8.
    expected = torch.tensor([0.0138214796, 0.0446240635, 0.0242897065], dtype=torch.float64)
    torch.testing.assert_close(ours, expected, atol=1e-8, rtol=0)


def test_ms_ssim_torchmetrics_matches_torchmetrics() -> None:
    tm = pytest.importorskip("torchmetrics.functional.image")
    x, y = _speckled_pair(batch=3, size=64)
    x, y = torch.floor(x * 255) / 255, torch.floor(y * 255) / 255
    ours = ms_ssim_torchmetrics(x, y)
    # The authors' call: kernel_size=7 is ignored by torchmetrics (9x9 window from sigma 1.0).
    reference = tm.multiscale_structural_similarity_index_measure(
        x, y, data_range=1.0, kernel_size=7, sigma=1.0, betas=PAPER_MS_SSIM_BETAS, reduction="none"
    )
    torch.testing.assert_close(ours, reference.double(), atol=1e-5, rtol=0)
    # The corrected 7x7 variant is a different number on the same pair.
    assert (ms_ssim(x, y, crop_size=None) - ours).abs().max() > 1e-3


def test_paper_ms_ssim_reproduces_authors_pipeline() -> None:
    tm = pytest.importorskip("torchmetrics.functional.image")
    x, y = _speckled_pair(batch=2, size=128)
    ours = paper_ms_ssim(x, y)
    # Reference: bilinear resize to 256, 8-bit truncation, centre 64 crop, torchmetrics on pixel / 255.
    def authors(images: torch.Tensor) -> torch.Tensor:
        up = torch.nn.functional.interpolate(
            images.double(), size=(256, 256), mode="bilinear", align_corners=False
        )
        return (torch.floor(up.clamp(0, 1) * 255) / 255)[..., 96:160, 96:160].float()

    reference = tm.multiscale_structural_similarity_index_measure(
        authors(x), authors(y), data_range=1.0, kernel_size=7, sigma=1.0, betas=PAPER_MS_SSIM_BETAS,
        reduction="none",
    )
    torch.testing.assert_close(ours, reference.double(), atol=1e-5, rtol=0)


def test_scoring_images_resize_quantise_and_crop() -> None:
    images = torch.linspace(0, 1, 128).repeat(1, 1, 128, 1)  # (1, 1, 128, 128), ramp along columns
    scored = to_paper_scoring_images(images)
    assert scored.shape == (1, 1, 64, 64) and scored.dtype == torch.float64
    assert torch.equal(scored, torch.floor(scored))
    # Centre 64 of 256 = central 32 columns of the 128 px ramp: values 48/127 .. 79/127 (x255, floored).
    assert 95.0 <= scored.min().item() <= 97.0 and 157.0 <= scored.max().item() <= 159.0
    same = to_paper_scoring_images(torch.full((1, 1, 256, 256), 0.5))
    assert same.unique().tolist() == [127.0]
    with pytest.raises(ValueError, match="outside"):
        to_paper_scoring_images(images * 2)
    with pytest.raises(ValueError, match="smaller"):
        to_paper_scoring_images(images, scoring_size=None, crop_size=200)


def test_identical_images_score_one_and_paper_differs_from_corrected() -> None:
    x, y = _speckled_pair(batch=2, size=128)
    for metric in (paper_ms_ssim, paper_kuan_ssim):
        torch.testing.assert_close(metric(x, x), torch.ones(2, dtype=torch.float64))
    assert (paper_kuan_ssim(x, y) - kuan_ssim(x, y)).abs().min() > 1e-3
