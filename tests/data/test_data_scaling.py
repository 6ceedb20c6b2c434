"""Tests for decibel conversion and dataset-global min-max scaling."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from sar_zero123.data import (
    MSTAR_RAW_MAX_DB,
    UNIT_MAGNITUDE_MAX_DB,
    DecibelScaling,
    from_decibels,
    to_decibels,
)


def test_to_decibels_closed_forms() -> None:
    db = to_decibels(np.array([0.0, 1.0, 0.999], dtype=np.float32))
    assert db.dtype == np.float32
    np.testing.assert_allclose(db, [-60.0, 20 * math.log10(1.001), 0.0], atol=1e-5)
    assert UNIT_MAGNITUDE_MAX_DB == pytest.approx(0.0086815, abs=1e-7)


def test_numpy_and_torch_agree_and_invert() -> None:
    magnitude = np.random.default_rng(0).uniform(0, 3, size=(2, 5)).astype(np.float32)
    db_np = to_decibels(magnitude)
    db_t = to_decibels(torch.from_numpy(magnitude))
    assert isinstance(db_t, torch.Tensor)
    np.testing.assert_allclose(db_t.numpy(), db_np, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(from_decibels(db_np), magnitude, atol=1e-5)
    np.testing.assert_allclose(from_decibels(db_t).numpy(), magnitude, atol=1e-5)


def test_unit_magnitude_scaling_maps_0_and_1_to_ends() -> None:
    scaling = DecibelScaling()
    assert scaling == DecibelScaling.for_unit_magnitude()
    x = scaling.normalize(torch.tensor([0.0, 1.0, 0.1]))
    # 0.1 -> 20*log10(0.101) = -19.913 dB -> (60 - 19.913) / 60.00868
    assert isinstance(x, torch.Tensor) and x.dtype == torch.float32
    np.testing.assert_allclose(x.numpy(), [0.0, 1.0, 40.0869 / 60.00868], atol=1e-5, rtol=0)
    np.testing.assert_allclose(scaling.denormalize(x).numpy(), [0.0, 1.0, 0.1], atol=1e-6, rtol=0)


def test_normalize_clips_unless_asked() -> None:
    scaling = DecibelScaling.for_unit_magnitude()
    assert scaling.normalize(np.array([4.0]))[0] == 1.0
    assert scaling.normalize(np.array([4.0]), clip=False)[0] == pytest.approx(
        (12.0423 + 60) / 60.00868, abs=1e-4
    )


def test_fit_uses_global_bounds() -> None:
    images = [np.array([[0.5, 2.0]]), torch.tensor([[0.25, 1.0]])]
    scaling = DecibelScaling.fit(images)
    assert scaling.min_db == pytest.approx(20 * math.log10(0.251))
    assert scaling.max_db == pytest.approx(20 * math.log10(2.001))
    expected = [[(-6.0033 + 12.0074) / 18.0323, 1.0]]  # 20*log10(0.501) = -6.0033 dB
    np.testing.assert_allclose(scaling.normalize(images[0]), expected, atol=1e-4)


def test_dict_round_trip_through_json() -> None:
    scaling = DecibelScaling.for_mstar_raw()
    assert scaling.max_db == MSTAR_RAW_MAX_DB == 24.4912
    assert DecibelScaling.from_dict(json.loads(json.dumps(scaling.to_dict()))) == scaling


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: DecibelScaling(min_db=0.0, max_db=0.0), "max_db must exceed min_db"),
        (lambda: DecibelScaling(min_db=-math.inf, max_db=0.0), "must be finite"),
        (lambda: DecibelScaling.from_dict({"min_db": -60}), r"lacks \['max_db'\]"),
        (lambda: DecibelScaling.fit([]), "at least one magnitude"),
        (lambda: DecibelScaling.fit([np.array([np.nan])]), "must be finite and >= 0"),
    ],
)
def test_errors(call, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize(
    ("magnitude", "match"),
    [
        (np.array([0.5, -0.2, 0.1]), r"1 negative \(smallest finite value -0.2\)"),
        (torch.tensor([0.5, float("nan")]), r"1 non-finite of 2 values"),
        (torch.tensor([float("inf"), -1.0]), r"1 negative .* 1 non-finite"),
    ],
)
def test_normalize_refuses_negative_and_non_finite_magnitudes(magnitude, match):
    with pytest.raises(ValueError, match=rf"magnitude must be finite and >= 0.*{match}"):
        DecibelScaling().normalize(magnitude)


def test_from_choice_names_the_three_bounds() -> None:
    from sar_zero123.data import SCALING_CHOICES

    assert DecibelScaling.from_choice("unit") == DecibelScaling.for_unit_magnitude()
    assert DecibelScaling.from_choice("mstar_raw") == DecibelScaling.for_mstar_raw()
    magnitudes = [np.array([[0.5, 2.0]], dtype=np.float32)]
    assert DecibelScaling.from_choice("fit", magnitudes) == DecibelScaling.fit(magnitudes)
    assert SCALING_CHOICES == ("unit", "mstar_raw", "fit")
    with pytest.raises(ValueError, match="scaling must be one of"):
        DecibelScaling.from_choice("minmax")


def test_isclose_compares_both_bounds_to_the_tolerance():
    unit = DecibelScaling.for_unit_magnitude()
    assert unit.isclose(DecibelScaling(min_db=-60.0 + 5e-7, max_db=unit.max_db))
    assert not unit.isclose(DecibelScaling(min_db=-60.0 + 2e-6, max_db=unit.max_db))
    assert not unit.isclose(DecibelScaling.for_mstar_raw())  # same min_db, max_db 24.4912
    assert unit.isclose(DecibelScaling(min_db=-59.9, max_db=unit.max_db), abs_tol=0.2)
