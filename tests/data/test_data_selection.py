"""``sar_zero123.data.selection``: evenly spaced azimuths, a sector, cross-validation folds."""

from __future__ import annotations

import pytest

from sar_zero123.data import ChipRecord
from sar_zero123.data.selection import circular_distance_deg, cv_folds, keep_evenly_spaced, keep_sector


def record(target_class: str, azimuth_deg: float) -> ChipRecord:
    return ChipRecord(
        path=f"/x/{target_class}_{azimuth_deg}.npy", target_class=target_class, target_type="t", serial="s",
        depression_deg=17.0, azimuth_deg=azimuth_deg, height=64, width=64,
    )  # fmt: skip


def test_keep_evenly_spaced_picks_the_chip_nearest_each_grid_azimuth():
    # every 10 deg, two classes; K = 4 wants 0, 90, 180, 270: 359 is nearer to 0 than 10 is (wrap)
    records = [record(c, a) for c in ("A", "B") for a in [359.0, *range(10, 359, 10)]]
    kept = keep_evenly_spaced(records, 4)
    assert sorted(r.azimuth_deg for r in kept if r.target_class == "A") == [90.0, 180.0, 270.0, 359.0]
    assert len(kept) == 8
    with pytest.raises(ValueError, match="fewer than k"):
        keep_evenly_spaced(records[:3], 4)
    assert [r.azimuth_deg for r in keep_sector(records[:12], 90.0)] == [10.0 * i for i in range(1, 9)]


def test_circular_distance_wraps_at_360():
    assert circular_distance_deg(350.0, 10.0) == 20.0
    assert circular_distance_deg(0.0, 180.0) == 180.0 and circular_distance_deg(90.0, 450.0) == 0.0


def test_cv_folds_deal_each_class_evenly_and_need_two_folds():
    records = [record(c, float(a)) for c in ("A", "B") for a in range(7)]
    folds = cv_folds(records, 3, seed=1)
    for name in ("A", "B"):
        labels = [f for r, f in zip(records, folds) if r.target_class == name]
        counts = sorted(labels.count(k) for k in range(3))
        assert counts == [2, 2, 3]
    assert folds == cv_folds(records, 3, seed=1) and folds != cv_folds(records, 3, seed=2)
    with pytest.raises(ValueError, match="folds must be >= 2"):
        cv_folds(records, 1)
    with pytest.raises(ValueError, match="class A has 7 chips, fewer than 8 folds"):
        cv_folds(records, 8)
