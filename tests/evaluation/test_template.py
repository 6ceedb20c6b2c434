"""Tests for the template-matched readings of views (azimuth, front/back, identity)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from sar_zero123.evaluation.template import gap_closed, read_templates, summarise_readings

GRID = np.arange(0.0, 360.0, 45.0)  # 8 grid azimuths


@pytest.fixture(scope="module")
def turntables() -> np.ndarray:
    return np.random.default_rng(0).random((3, len(GRID), 10, 10))  # 3 vehicles


def test_a_template_reads_as_its_own_azimuth_and_vehicle_and_its_flip_reads_180_off(turntables):
    vehicle = np.array([0, 1, 2, 2])
    k = np.array([0, 3, 5, 7])
    views = turntables[vehicle, k]
    right = read_templates(views, turntables, GRID, vehicle, GRID[k])
    np.testing.assert_array_equal(right.matched_azimuth_deg, GRID[k])
    np.testing.assert_array_equal(right.azimuth_error_deg, 0.0)
    assert right.front_back_right.all() and right.identity_kept.all()
    flipped = read_templates(views, turntables, GRID, vehicle, (GRID[k] + 180.0) % 360.0)
    np.testing.assert_allclose(flipped.azimuth_error_deg, 180.0)
    assert not flipped.front_back_right.any()
    wrong = read_templates(views, turntables, GRID, np.array([1, 0, 0, 1]), GRID[k])
    assert not wrong.identity_kept.any()


def test_readings_match_a_double_loop_reference(turntables):
    rng = np.random.default_rng(1)
    views = rng.random((5, 10, 10))
    vehicle, requested = rng.integers(0, 3, 5), rng.uniform(0, 360, 5)
    got = read_templates(views, turntables, GRID, vehicle, requested, blur_sigma_px=1.0)
    for n in range(5):
        corr = np.array([[np.corrcoef(gaussian_filter(views[n], 1.0).ravel(),
                                      gaussian_filter(turntables[v, j], 1.0).ravel())[0, 1]
                          for j in range(len(GRID))] for v in range(3)])  # fmt: skip
        matched = GRID[np.argmax(corr[vehicle[n]])]
        assert got.matched_azimuth_deg[n] == matched
        error = abs((matched - requested[n] + 180.0) % 360.0 - 180.0)
        assert got.azimuth_error_deg[n] == pytest.approx(error)
        assert got.front_back_right[n] == (error < 90.0)
        assert got.identity_kept[n] == (np.unravel_index(np.argmax(corr), corr.shape)[0] == vehicle[n])


def test_gap_closed_and_the_summary(turntables):
    assert gap_closed(60.0, 100.0, 20.0) == pytest.approx(0.5)
    assert gap_closed(100.0, 100.0, 20.0) == 0.0 and gap_closed(20.0, 100.0, 20.0) == 1.0
    with pytest.raises(ValueError, match="must exceed ceiling_error"):
        gap_closed(1.0, 5.0, 5.0)
    vehicle, k = np.array([0, 1]), np.array([2, 4])
    ceiling = read_templates(turntables[vehicle, k], turntables, GRID, vehicle, GRID[k])
    floor = read_templates(turntables[vehicle, k], turntables, GRID, vehicle, (GRID[k] + 180.0) % 360.0)
    summary = summarise_readings(floor, floor, ceiling)
    assert summary["n"] == 2 and summary["azimuth_error_deg"] == pytest.approx(180.0)
    assert summary["gap_closed"] == 0.0 and summary["front_back_right"] == 0.0
    assert summary["identity_kept"] == 1.0 and summary["identity_kept_se"] == 0.0


def test_shapes_that_do_not_match_are_refused(turntables):
    views = turntables[0, :2]
    with pytest.raises(ValueError, match="must share S"):
        read_templates(views[:, :5], turntables, GRID, [0, 0], [0.0, 0.0])
    with pytest.raises(ValueError, match="turntable_azimuths_deg: expected 8"):
        read_templates(views, turntables, GRID[:4], [0, 0], [0.0, 0.0])
    with pytest.raises(ValueError, match=r"vehicle: expected indices in \[0, 3\)"):
        read_templates(views, turntables, GRID, [0, 3], [0.0, 0.0])
