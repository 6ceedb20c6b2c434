"""Tests for the template-matched readings of views (azimuth, front/back, identity)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from sar_zero123.evaluation.template import (
    TURNED_WITHIN_DEG,
    gap_closed,
    identity_by_proxy,
    read_templates,
    summarise_readings,
    turned_and_kept,
)

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
    assert summary["turned_and_kept"] == 0.0  # the input copy keeps its vehicle and turns none
    assert summarise_readings(ceiling)["turned_and_kept"] == 1.0


def test_turned_and_kept_needs_both_the_vehicle_and_the_turn():
    error = np.array([0.0, 30.0, 30.5, 5.0, 179.0])
    kept = np.array([True, True, True, False, True])
    np.testing.assert_array_equal(turned_and_kept(error, kept), [True, True, False, False, False])
    assert TURNED_WITHIN_DEG == 30.0
    np.testing.assert_array_equal(turned_and_kept(error, kept, within_deg=180.0), kept)
    with pytest.raises(ValueError, match="kept: expected one value per view"):
        turned_and_kept(error, kept[:2])


def test_shapes_that_do_not_match_are_refused(turntables):
    views = turntables[0, :2]
    with pytest.raises(ValueError, match="must share S"):
        read_templates(views[:, :5], turntables, GRID, [0, 0], [0.0, 0.0])
    with pytest.raises(ValueError, match="turntable_azimuths_deg: expected 8"):
        read_templates(views, turntables, GRID[:4], [0, 0], [0.0, 0.0])
    with pytest.raises(ValueError, match=r"vehicle: expected indices in \[0, 3\)"):
        read_templates(views, turntables, GRID, [0, 3], [0.0, 0.0])


def test_chip_templates_read_each_view_against_its_candidate_chips_only(turntables):
    """A data folder's own chips as the turntable: each view reads the azimuth of the candidate chip it
    correlates best with (a double-loop reference), never a chip outside its candidates."""
    from sar_zero123.evaluation.template import read_chip_templates

    chips = turntables.reshape(-1, 10, 10)  # 24 chips: 3 vehicles x 8 azimuths
    azimuths = np.tile(GRID, 3)
    rng = np.random.default_rng(2)
    views = chips[[1, 9, 20]] + 0.05 * rng.random((3, 10, 10))
    candidates = np.zeros((3, 24), dtype=bool)
    candidates[0, :8] = candidates[1, 8:16] = candidates[2, 16:] = True
    candidates[1, 9] = False  # the view's own chip left out: it reads another
    requested = np.array([45.0, 45.0, 180.0])
    got = read_chip_templates(views, chips, azimuths, candidates, requested, blur_sigma_px=1.0)
    for n in range(3):
        view = gaussian_filter(views[n], 1.0).ravel()
        corr = [np.corrcoef(view, gaussian_filter(chips[m], 1.0).ravel())[0, 1] for m in range(24)]
        corr = np.where(candidates[n], corr, -np.inf)
        assert got.matched_azimuth_deg[n] == azimuths[int(np.argmax(corr))]
    assert got.matched_azimuth_deg[0] == 45.0 and got.matched_azimuth_deg[2] == 180.0
    assert got.matched_azimuth_deg[1] != 45.0
    np.testing.assert_allclose(got.azimuth_error_deg[[0, 2]], 0.0)
    assert got.identity_kept.all()
    with pytest.raises(ValueError, match="view 1 has no candidate chip"):
        read_chip_templates(views, chips, azimuths, candidates & (np.arange(3) != 1)[:, None], requested)
    with pytest.raises(ValueError, match=r"candidates \(3, 24\)"):
        read_chip_templates(views, chips, azimuths, candidates[:, :5], requested)


def test_the_evaluation_reads_each_pair_against_its_vehicles_other_chips_at_the_target_depression(tmp_path):
    """`chip_templates`: per pair, the target's vehicle (class and serial) at its depression, the target
    left out; the input copy then reads its own azimuth (the floor) and the true view a neighbour's."""
    from chip_folders import write_chip_folder

    from sar_zero123.data import load_index
    from sar_zero123.data.view_pairs import ViewPairDataset
    from sar_zero123.evaluation.protocol import chip_templates
    from sar_zero123.evaluation.template import read_chip_templates

    folder = write_chip_folder(tmp_path / "chips", azimuths_deg=tuple(range(0, 360, 30)), size=16)
    records = load_index(folder)
    pairs = ViewPairDataset(records, size=16, seed=0)
    chips, azimuths, candidates = chip_templates(pairs)
    assert candidates.shape == (len(pairs), len(chips)) and chips.shape[1:] == (1, 16, 16)
    for row, (_, target) in enumerate(pairs.pairs):
        chosen = records[target]
        expected = sorted(
            r.azimuth_deg for k, r in enumerate(records)
            if k != target and (r.target_class, r.serial, r.depression_deg)
            == (chosen.target_class, chosen.serial, chosen.depression_deg)
        )  # fmt: skip
        assert sorted(azimuths[candidates[row]].tolist()) == expected and len(expected) == 11
    views = np.stack([pairs[i]["input"][0].numpy() for i in range(len(pairs))])
    floor = read_chip_templates(views, chips[:, 0].numpy(), azimuths.numpy(), candidates.numpy(),
                                [records[t].azimuth_deg for _, t in pairs.pairs])  # fmt: skip
    np.testing.assert_allclose(floor.matched_azimuth_deg, [records[s].azimuth_deg for s, _ in pairs.pairs])


def test_identity_by_proxy_splits_a_row_by_its_proxy_and_recombines_to_the_row():
    kept = np.array([1, 1, 1, 0, 1, 0, 0, 0, 1, 0], dtype=bool)
    proxy = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0], dtype=bool)
    split = identity_by_proxy(kept, proxy)
    assert split["proxy_right_share"] == 0.4
    assert split["kept_proxy_right"] == 0.75 and split["kept_proxy_wrong"] == pytest.approx(2 / 6)
    assert split["kept_proxy_right_se"] == pytest.approx(np.std([1, 1, 1, 0], ddof=1) / 2)
    p = split["proxy_right_share"]
    assert p * split["kept_proxy_right"] + (1 - p) * split["kept_proxy_wrong"] == pytest.approx(kept.mean())
    every = identity_by_proxy(kept, np.ones(10, dtype=bool))
    assert np.isnan(every["kept_proxy_wrong"]) and every["kept_proxy_right"] == kept.mean()
    with pytest.raises(ValueError, match=r"proxy_kept: expected one value per view \(10,\), got \(9,\)"):
        identity_by_proxy(kept, proxy[:9])
