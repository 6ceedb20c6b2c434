"""Tests for the simulator proxy (analysis by synthesis): correlation, retrieval, re-rendering."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from sar_zero123.domain import to_decibels
from sar_zero123.sim import render_chip
from sar_zero123.sim.procedural import make_procedural_target
from sar_zero123.sim.proxy import PROXY_FIRST_SEED, ProxyBank, blurred_correlation, shifted_correlation


def test_blurred_correlation_is_pearson_of_the_blurred_images_and_ignores_affine_maps():
    rng = np.random.default_rng(0)
    chip, renders = rng.normal(size=(12, 12)), rng.normal(size=(3, 12, 12))
    got = blurred_correlation(chip, renders, 1.5)
    for k in range(3):  # reference: numpy's corrcoef of the blurred pair
        expected = np.corrcoef(gaussian_filter(chip, 1.5).ravel(), gaussian_filter(renders[k], 1.5).ravel())[
            0, 1
        ]
        assert got[k] == pytest.approx(expected, abs=1e-12)
    # decibels or normalised dB (an affine map of them) score the same; an image with itself scores 1
    np.testing.assert_allclose(blurred_correlation(3.0 * chip - 7.0, renders, 1.5), got, atol=1e-12)
    assert blurred_correlation(chip, chip[None], 0.0)[0] == pytest.approx(1.0)
    assert blurred_correlation(chip, np.zeros((1, 12, 12)), 1.0)[0] == 0.0  # a constant image: 0, no NaN
    with pytest.raises(ValueError, match=r"chip \(S, S\) and renders \(N, S, S\) must match"):
        blurred_correlation(chip, renders[:, :10], 1.0)


def test_a_bank_vehicle_under_other_clutter_retrieves_itself_and_leave_one_out_retrieves_another():
    bank = ProxyBank(num_vehicles=6)
    azimuth, depression = 37.0, 17.0
    for k in (1, 4):
        target = make_procedural_target(PROXY_FIRST_SEED + k)
        chip = to_decibels(render_chip(target, azimuth, depression, 64, np.random.default_rng(99)))
        match = bank.retrieve(chip, azimuth, depression)
        assert (match.index, match.seed) == (k, PROXY_FIRST_SEED + k)
        assert 0.8 < match.score <= 1.0
        other = bank.retrieve(chip, azimuth, depression, exclude=[k])
        assert other.index != k and other.score < match.score
        assert bank.scores(chip, azimuth, depression, exclude=[k])[k] == -np.inf


def test_a_shortlist_fit_scores_its_candidates_as_the_exhaustive_fit_and_renders_a_bucket_once(
    monkeypatch,
):
    """shortlist=k: every vehicle rendered once at the pose bucket's centre (kept for the next chip near that
    pose), the k best re-rendered at the exact pose and scored exactly as the exhaustive fit scores them; the
    others score -inf; an excluded vehicle is never shortlisted."""
    exhaustive, short = ProxyBank(num_vehicles=12), ProxyBank(num_vehicles=12, shortlist=4)
    target = make_procedural_target(PROXY_FIRST_SEED + 7)
    chip = to_decibels(render_chip(target, 38.0, 17.0, 32, np.random.default_rng(5)))
    renders = []
    original = ProxyBank.render

    def counted(self, *args, **kwargs):
        renders.append(args[1:3])
        return original(self, *args, **kwargs)

    monkeypatch.setattr(ProxyBank, "render", counted)
    expected = exhaustive.scores(chip, 38.0, 17.0)
    assert len(renders) == 12 and set(renders) == {(38.0, 17.0)}
    renders.clear()
    got = short.scores(chip, 38.0, 17.0)
    assert renders[:12] == [(40.0, 15.0)] * 12 and renders[12:] == [(38.0, 17.0)] * 4  # bucket, then exact
    kept = np.isfinite(got)
    assert kept.sum() == 4 and kept[7] and int(np.argmax(got)) == int(np.argmax(expected)) == 7
    np.testing.assert_allclose(got[kept], expected[kept], rtol=0, atol=1e-12)
    renders.clear()
    match = short.retrieve(chip, 41.0, 16.0, exclude=[7])  # the same bucket: only the shortlist rendered
    assert renders == [(41.0, 16.0)] * 4 and match.index != 7
    words = r"shortlist: expected an integer in \[0, num_vehicles = 12\], got 13"
    with pytest.raises(ValueError, match=words):
        ProxyBank(num_vehicles=12, shortlist=13)


def test_renders_are_the_same_bytes_on_every_call_and_turn_with_the_azimuth():
    bank = ProxyBank(num_vehicles=2, render_seed=3)
    first = bank.render(1, 30.0, 17.0, 64)
    assert first.shape == (64, 64) and first.dtype == np.float32 and float(first.max()) == 1.0
    assert np.array_equal(first, ProxyBank(num_vehicles=2, render_seed=3).render(1, 390.0, 17.0, 64))
    assert not np.array_equal(first, bank.render(1, 210.0, 17.0, 64))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"num_vehicles": 0}, "num_vehicles: expected an integer in"), ({"num_vehicles": 2.5}, "num_vehicles"),
     ({"first_seed": -1}, "first_seed: expected an integer >= 0"), ({"blur_sigma_px": -1.0}, "blur_sigma_px"),
     ({"render_seed": True}, "render_seed")],
)  # fmt: skip
def test_bad_bank_settings_are_refused_naming_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ProxyBank(**kwargs)


def test_bad_chips_and_indices_are_refused():
    bank = ProxyBank(num_vehicles=2)
    with pytest.raises(ValueError, match=r"chip_decibels: expected a finite square"):
        bank.scores(np.zeros((64, 32)), 0.0, 17.0)
    with pytest.raises(ValueError, match=r"chip_decibels"):
        bank.scores(np.full((64, 64), np.nan), 0.0, 17.0)
    with pytest.raises(ValueError, match=r"index: expected an integer in \[0, 2\)"):
        bank.render(2, 0.0, 17.0)


def test_shifted_correlation_is_the_best_rolled_pearson_and_finds_the_shift():
    rng = np.random.default_rng(2)
    chip, renders = rng.normal(size=(16, 16)), rng.normal(size=(3, 16, 16))
    scores, shifts = shifted_correlation(chip, renders, 1.0, 2)
    blurred = gaussian_filter(chip, 1.0)
    for n in range(3):  # reference: every roll of the blurred render within +-2 px, scored by Pearson
        render = gaussian_filter(renders[n], 1.0)
        rolled = {(dy, dx): blurred_correlation(blurred, np.roll(render, (dy, dx), axis=(0, 1))[None], 0.0)[0]
                  for dy in range(-2, 3) for dx in range(-2, 3)}  # fmt: skip
        best = max(rolled, key=rolled.get)
        assert scores[n] == pytest.approx(rolled[best], abs=1e-9) and tuple(shifts[n]) == best
    # a chip that is a render rolled by (2, -1) is found at that shift with correlation 1 (no blur: exact)
    scores, shifts = shifted_correlation(np.roll(renders[1], (2, -1), axis=(0, 1)), renders, 0.0, 3)
    assert int(np.argmax(scores)) == 1 and scores[1] == pytest.approx(1.0) and tuple(shifts[1]) == (2, -1)
    no_shift, zero = shifted_correlation(chip, renders, 1.0, 0)
    np.testing.assert_array_equal(no_shift, blurred_correlation(chip, renders, 1.0))
    assert not zero.any()
    with pytest.raises(ValueError, match=r"max_shift_px: expected an integer in \[0, 4\]"):
        shifted_correlation(chip, renders, 1.0, 5)


def test_a_bank_fit_with_shifts_finds_an_off_centre_vehicle_and_renders_it_there():
    bank = ProxyBank(num_vehicles=4, max_shift_px=4)
    target = make_procedural_target(PROXY_FIRST_SEED + 2)
    magnitude = render_chip(target, 80.0, 17.0, 64, np.random.default_rng(5))
    match = bank.retrieve(to_decibels(np.roll(magnitude, (3, -2), axis=(0, 1))), 80.0, 17.0)
    assert (match.index, match.shift_px) == (2, (3, -2))
    rolled = bank.render(2, 80.0, 17.0, 64, match.shift_px)
    np.testing.assert_array_equal(rolled, np.roll(bank.render(2, 80.0, 17.0, 64), (3, -2), axis=(0, 1)))
