"""Tests for the extended / SOC / OOD protocols and prepare_splits."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import pytest

from sar_zero123.data import (
    ChipDataset,
    ChipRecord,
    check_protocol,
    ood_validation_intervals,
    prepare_splits,
    split_records,
    write_index,
)


def make_records(root: Path = Path("/data")) -> list[ChipRecord]:
    """3 classes x 2 depressions x 72 azimuths (5 deg step); BMP2 and T72 with two serials each."""
    objects = [("2S1", "b01"), ("BMP2", "9563"), ("BMP2", "c21"), ("T72", "132"), ("T72", "s7")]
    return [
        ChipRecord(
            path=root / f"{cls}_{serial}_{dep}_{k}.npy",
            target_class=cls,
            serial=serial,
            depression_deg=float(dep),
            azimuth_deg=5.0 * k + 1.0,
        )
        for cls, serial in objects
        for dep in (15, 17)
        for k in range(72)
    ]


def test_extended_and_soc_counts() -> None:
    records = make_records()
    extended = split_records(records, "extended")
    assert (len(extended["train"]), len(extended["test"])) == (5 * 72, 5 * 72)
    assert {r.depression_deg for r in extended["train"]} == {17.0}
    assert {r.depression_deg for r in extended["test"]} == {15.0}
    soc = split_records(records, "soc")
    assert (len(soc["train"]), len(soc["test"])) == (3 * 72, 3 * 72)
    assert {r.object_id for r in soc["train"]} == {("2S1", "b01"), ("BMP2", "9563"), ("T72", "132")}


def test_ood_intervals_definition() -> None:
    intervals = ood_validation_intervals(seed=0)
    assert len(intervals) == 12 == len({start for start, _ in intervals})
    assert all(end - start == 3.0 and start % 3 == 0 and 0 <= start < 360 for start, end in intervals)
    assert intervals == sorted(intervals)
    assert intervals == ood_validation_intervals(seed=0) != ood_validation_intervals(seed=1)


def test_ood_split() -> None:
    records = make_records()
    splits = split_records(records, "ood-T72", seed=3)
    intervals = ood_validation_intervals(seed=3)
    assert set(splits) == {"train", "val", "test"}
    assert len(splits["test"]) == 2 * 2 * 72 and {r.target_class for r in splits["test"]} == {"T72"}
    assert {r.target_class for r in splits["train"] + splits["val"]} == {"2S1", "BMP2"}
    assert len(splits["train"]) + len(splits["val"]) == 3 * 2 * 72
    in_val = [any(a <= r.azimuth_deg < b for a, b in intervals) for r in splits["val"]]
    in_train = [any(a <= r.azimuth_deg < b for a, b in intervals) for r in splits["train"]]
    assert all(in_val) and not any(in_train)
    # azimuths 1, 6, 11, ...: each 3-degree interval [3k, 3k+3) holds at most one grid azimuth
    expected_val = 3 * 2 * sum(any(a <= 5 * k + 1 < b for a, b in intervals) for k in range(72))
    assert len(splits["val"]) == expected_val > 0
    assert split_records(records, "ood-t72", seed=3) == splits  # case-insensitive class name


@pytest.mark.parametrize(
    ("protocol", "message"),
    [
        ("standard", "unknown protocol 'standard'; expected one of"),
        ("ood-", "unknown protocol 'ood-'"),
        ("ood-M1", r"unknown held-out class 'M1'; the records hold \['2S1', 'BMP2', 'T72'\]"),
    ],
)
def test_bad_protocols(protocol: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        split_records(make_records(), protocol)


def test_empty_split_raises() -> None:
    only_17 = [r for r in make_records() if r.depression_deg == 17.0]
    message = r"protocol 'extended' gives an empty 'test' split .*depressions \[17.0\]"
    with pytest.raises(ValueError, match=message):
        split_records(only_17, "extended")
    only_t72 = [r for r in make_records() if r.target_class == "T72"]
    with pytest.raises(ValueError, match="empty 'train' split"):
        split_records(only_t72, "ood-T72")


def _write_fake_dataset(out_dir: Path, seed: int = 0, **kwargs) -> Path:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    records = make_records(out_dir)[::6]
    for record in records:
        np.save(record.path, np.zeros((2, 2), dtype=np.float32))
    return write_index(records, out_dir)


def test_prepare_splits_simulates_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[dict] = []

    def simulate_dataset(out_dir, **kwargs):
        calls.append(kwargs)
        return _write_fake_dataset(out_dir, **kwargs)

    fake_sim = types.SimpleNamespace(simulate_dataset=simulate_dataset)
    monkeypatch.setitem(sys.modules, "sar_zero123.sim", fake_sim)
    first = prepare_splits(None, "extended", tmp_path, seed=4, size=8)
    second = prepare_splits(None, "extended", tmp_path, seed=4, size=8)
    assert calls == [{"seed": 4, "size": 8}]
    assert first == second and len(first["train"]) == len(first["test"]) == 60
    assert first["train"][0].path.parent == (tmp_path / "sim_data").resolve()
    # other simulator options: simulated again, not silently reused
    prepare_splits(None, "extended", tmp_path, seed=4, size=16)
    assert calls[-1] == {"seed": 4, "size": 16}


def test_prepare_splits_from_folder(tmp_path: Path) -> None:
    _write_fake_dataset(tmp_path / "data")
    splits = prepare_splits(tmp_path / "data", "soc", tmp_path / "work")
    assert len(splits["train"]) == 36 and not (tmp_path / "work").exists()
    with pytest.raises(ValueError, match=r"simulator options \['size'\] only apply when data is None"):
        prepare_splits(tmp_path / "data", "soc", tmp_path / "work", size=8)


def test_prepare_splits_with_builtin_simulator(tmp_path: Path) -> None:
    sim = pytest.importorskip("sar_zero123.sim")
    classes = list(sim.TARGET_CLASSES)[:2]
    options = {"classes": classes, "instances": 1, "azimuth_step_deg": 90.0, "size": 16}
    splits = prepare_splits(None, f"ood-{classes[0]}", tmp_path, seed=0, **options)
    assert len(splits["test"]) == 2 * 4  # held-out class, 2 depressions x 4 azimuths
    assert {r.target_class for r in splits["train"] + splits["val"]} == {classes[1]}
    assert len(splits["train"]) + len(splits["val"]) == 8
    image = ChipDataset(splits["test"], size=16)[0]["image"]
    assert image.shape == (1, 16, 16) and 0.0 <= float(image.min()) < float(image.max()) <= 1.0


def test_check_protocol_accepts_the_paper_protocols_and_names_the_field():
    assert [check_protocol(p) for p in ("extended", "soc", "ood-T72")] == ["extended", "soc", "ood-T72"]
    for bad in ("standard", "ood-", "OOD-T72", ""):
        with pytest.raises(ValueError, match=f"data_protocol: unknown protocol {bad!r}"):
            check_protocol(bad, field="data_protocol")


def test_chips_at_a_depression_no_split_takes_are_reported() -> None:
    records = make_records()
    stray = [ChipRecord(Path(f"/data/x{k}.npy"), "2S1", "b01", 15.6, 10.0 * k) for k in range(4)]
    with pytest.warns(UserWarning, match=r"'extended': 4 of 724 chips are at depressions \[15.6\] deg, in no "
                      r"split .* /data/x0.npy, /data/x1.npy, /data/x2.npy, \.\.\."):  # fmt: skip
        splits = split_records(records + stray, "extended")
    assert len(splits["train"]) + len(splits["test"]) == len(records)
