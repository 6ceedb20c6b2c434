"""Speckle re-added to smooth views (readd_speckle): closed forms of log speckle, seeding, bounds."""

from __future__ import annotations

import math

import pytest
import torch

from sar_zero123.augment import log_speckle_stats, readd_speckle


# ------------------------------------------------------------------------- speckle re-added to views
def test_log_speckle_stats_closed_forms():
    # single look: E[ln Exp(1)] = -Euler's gamma, Var = pi^2 / 6; four looks: psi(4) = 1 + 1/2 + 1/3 - gamma
    gamma = 0.5772156649015329
    scale = 10.0 / math.log(10.0)
    assert log_speckle_stats(1) == pytest.approx((-scale * gamma, scale * math.pi / math.sqrt(6.0)), rel=1e-9)
    mean4, std4 = log_speckle_stats(4)
    assert mean4 == pytest.approx(scale * (1 + 1 / 2 + 1 / 3 - gamma - math.log(4.0)), rel=1e-9)
    assert std4 == pytest.approx(scale * math.sqrt(math.pi**2 / 6 - 1 - 1 / 4 - 1 / 9), rel=1e-9)


@pytest.mark.parametrize("looks", [1, 4])
def test_readd_speckle_keeps_the_mean_log_brightness_and_adds_the_speckle_spread(looks):
    x = torch.full((4, 1, 128, 128), 0.5)
    db_range = 60.0
    y = readd_speckle(x, db_range, looks, torch.Generator().manual_seed(0))
    added_db = (y - x) * db_range
    _, std = log_speckle_stats(looks)
    assert abs(float(added_db.mean())) < 0.05  # 65,536 draws: standard error 0.02 dB
    assert float(added_db.std()) == pytest.approx(std, rel=0.02)


def test_readd_speckle_is_seeded_bounded_and_checks_its_arguments():
    x = torch.rand(2, 1, 16, 16)
    first = readd_speckle(x, 60.0, 1, torch.Generator().manual_seed(3))
    assert torch.equal(first, readd_speckle(x, 60.0, 1, torch.Generator().manual_seed(3)))
    assert first.shape == x.shape and float(first.min()) >= 0.0 and float(first.max()) <= 1.0
    with pytest.raises(ValueError, match="looks"):
        readd_speckle(x, 60.0, 0)
    with pytest.raises(ValueError, match="looks"):
        readd_speckle(x, 60.0, 1.5)
    with pytest.raises(ValueError, match="db_range"):
        readd_speckle(x, 0.0)
