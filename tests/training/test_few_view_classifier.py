"""``sar_zero123.training.few_view_classifier``: the shift augmentation of the few-view classifier."""

from __future__ import annotations

import torch

from sar_zero123.training.few_view_classifier import random_shift


def test_random_shift_moves_each_image_within_the_bound():
    images = torch.arange(2 * 16 * 16, dtype=torch.float32).reshape(2, 1, 16, 16)
    shifted = random_shift(images, 2, torch.Generator().manual_seed(0))
    assert shifted.shape == images.shape
    # the centre 12 x 12 of a shifted image is a window of the original, offset by at most 2 px
    for original, moved in zip(images, shifted):
        centre = moved[0, 2:14, 2:14]
        windows = [original[0, dy : dy + 12, dx : dx + 12] for dy in range(5) for dx in range(5)]
        found = [window for window in windows if torch.equal(window, centre)]
        assert len(found) == 1
