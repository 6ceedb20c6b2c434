"""Tests for ChipDataset, ViewPairDataset and the azimuth wrap."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, ViewPairDataset, wrap_azimuth_deg


@pytest.fixture(scope="module")
def records(tmp_path_factory: pytest.TempPathFactory) -> list[ChipRecord]:
    """2 objects of class B (serials s1, s2) and one of class A, 8 azimuths (45 deg step) at 15 and 17 deg.

    Each chip is constant: value = (object number + 1) / 10 so tests can tell which file was read.
    """
    root = tmp_path_factory.mktemp("chips")
    out = []
    for number, (cls, serial) in enumerate([("B", "s1"), ("B", "s2"), ("A", "s1")]):
        for dep in (15.0, 17.0):
            for k in range(8):
                path = root / f"{cls}{serial}_{dep:.0f}_{k}.npy"
                np.save(path, np.full((10, 12), (number + 1) / 10, dtype=np.float32))
                out.append(ChipRecord(path, cls, serial, dep, azimuth_deg=45.0 * k + 2.0))
    return out


@pytest.mark.parametrize(
    ("angle", "expected"),
    [
        (20.0, 20.0),
        (-340.0, 20.0),
        (180.0, 180.0),
        (-180.0, 180.0),
        (190.0, -170.0),
        (0.0, 0.0),
        (180 + 1e-14, 180.0),
    ],
)
def test_wrap_azimuth(angle: float, expected: float) -> None:
    assert wrap_azimuth_deg(angle) == pytest.approx(expected)
    np.testing.assert_allclose(wrap_azimuth_deg(np.array([angle, angle + 720])), [expected, expected])


def test_chip_dataset_items(records: list[ChipRecord]) -> None:
    dataset = ChipDataset(records, size=8, return_magnitude=True)
    assert dataset.class_names == ["A", "B"] and len(dataset) == 48
    item = dataset[17]  # object B/s2 at 15 deg, k = 1
    assert item["image"].shape == item["magnitude"].shape == (1, 8, 8)
    assert item["image"].dtype == torch.float32
    assert (item["label"], item["azimuth_deg"], item["depression_deg"]) == (1, 47.0, 15.0)
    np.testing.assert_allclose(item["magnitude"].numpy(), 0.2, rtol=1e-6)
    expected = DecibelScaling().normalize(torch.tensor(0.2))  # (20 log10(0.201) + 60) / 60.0087 = 0.7676
    np.testing.assert_allclose(item["image"].numpy(), float(expected), rtol=1e-6)
    assert float(expected) == pytest.approx(0.76762, abs=1e-4)


def test_explicit_class_names_keep_labels(records: list[ChipRecord]) -> None:
    only_b = [r for r in records if r.target_class == "B"]
    assert ChipDataset(only_b, size=4)[0]["label"] == 0
    assert ChipDataset(only_b, size=4, class_names=["A", "B", "C"])[0]["label"] == 1
    with pytest.raises(ValueError, match=r"lack the record classes \['B'\]"):
        ChipDataset(only_b, class_names=["A"])


def test_view_pairs_same_object_and_pose(records: list[ChipRecord]) -> None:
    dataset = ViewPairDataset(records, size=4, seed=1, max_d_az_deg=90.0)
    assert len(dataset) == 48  # one pair per chip
    for (i, j), record in zip(dataset.pairs, records):
        source, target = records[i], records[j]
        assert source is record and i != j
        assert source.object_id == target.object_id and source.depression_deg == target.depression_deg
        assert abs(wrap_azimuth_deg(target.azimuth_deg - source.azimuth_deg)) <= 90.0
    item = dataset[0]
    source, target = (records[i] for i in dataset.pairs[0])
    assert item["d_az_deg"] == pytest.approx(wrap_azimuth_deg(target.azimuth_deg - source.azimuth_deg))
    assert item["d_az_deg"] in (-90.0, -45.0, 45.0, 90.0)  # input at 2 deg: targets 47, 92, 317 or 272
    assert (item["input_azimuth_deg"], item["d_el_deg"], item["label"]) == (2.0, 0.0, 1)
    assert torch.equal(item["input"], item["target"])  # same object -> same constant chip


def test_view_pairs_mixed_depression_and_num_pairs(records: list[ChipRecord]) -> None:
    dataset = ViewPairDataset(records, size=4, same_depression=False, num_pairs=200, seed=0)
    assert len(dataset) == 200
    d_el = [records[j].depression_deg - records[i].depression_deg for i, j in dataset.pairs]
    assert set(d_el) == {-2.0, 0.0, 2.0}
    assert dataset[int(np.flatnonzero(np.array(d_el) == 2.0)[0])]["d_el_deg"] == 2.0


def test_view_pairs_deterministic_and_epochs(records: list[ChipRecord]) -> None:
    a = ViewPairDataset(records, size=4, seed=5, pairs_per_chip=3)
    b = ViewPairDataset(records, size=4, seed=5, pairs_per_chip=3)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    assert len(a) == 144
    assert not np.array_equal(a.pairs, ViewPairDataset(records, size=4, seed=6, pairs_per_chip=3).pairs)
    first = a.pairs.copy()
    a.set_epoch(1)
    assert not np.array_equal(first, a.pairs)
    a.set_epoch(0)
    np.testing.assert_array_equal(first, a.pairs)


def test_view_pairs_with_dataloader_workers(records: list[ChipRecord]) -> None:
    dataset = ViewPairDataset(records[:16], size=4, seed=2)
    loader = DataLoader(dataset, batch_size=4, num_workers=2, shuffle=False)
    d_az = torch.cat([batch["d_az_deg"] for batch in loader])
    expected = [dataset[i]["d_az_deg"] for i in range(len(dataset))]
    assert d_az.dtype == torch.float64  # default collate of Python floats
    np.testing.assert_array_equal(d_az.numpy(), expected)


def test_view_pairs_without_partners_raise(records: list[ChipRecord]) -> None:
    with pytest.raises(ValueError, match="no chip has a partner view"):
        ViewPairDataset(records, max_d_az_deg=10.0)
    with pytest.raises(ValueError, match=r"max_d_az_deg must lie in \[0, 180\]"):
        ViewPairDataset(records, max_d_az_deg=270.0)
