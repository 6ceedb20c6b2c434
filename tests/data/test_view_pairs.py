"""MixedPairs and subsample_objects: a fine-tune's pairs with rehearsal pairs of its prior's data."""

from __future__ import annotations

import pytest
from torch.utils.data import Dataset

from sar_zero123.data import ChipRecord, MixedPairs, subsample_objects


def test_mixed_pairs_hold_the_task_and_a_fraction_of_rehearsal_pairs_redrawn_each_epoch() -> None:
    class Items(Dataset):
        def __init__(self, name: str, n: int) -> None:
            self.name, self.n, self.epochs = name, n, []

        def set_epoch(self, epoch: int) -> None:
            self.epochs.append(epoch)

        def __len__(self) -> int:
            return self.n

        def __getitem__(self, index: int) -> dict:
            return {"source": self.name, "index": index}

    task, rehearsal = Items("task", 30), Items("rehearsal", 7)
    mix = MixedPairs(task, rehearsal, fraction=0.25, seed=3)
    assert len(mix) == 30 + 10  # 10 / 40 = 0.25
    assert [mix[i] for i in range(30)] == [{"source": "task", "index": i} for i in range(30)]
    slots = [mix[i]["index"] for i in range(30, 40)]
    assert all(item["source"] == "rehearsal" for item in (mix[i] for i in range(30, 40)))
    assert sorted(slots[:7]) == list(range(7)) and slots[7:] == slots[:3]  # a permutation, cycled
    assert slots == [MixedPairs(task, rehearsal, 0.25, seed=3)[i]["index"] for i in range(30, 40)]  # seeded
    mix.set_epoch(1)
    assert task.epochs == [1] and rehearsal.epochs == [1]
    assert [mix[i]["index"] for i in range(30, 40)] != slots  # another permutation
    assert len(MixedPairs(task, rehearsal, fraction=0.0)) == 30
    with pytest.raises(ValueError, match=r"rehearsal fraction must lie in \[0, 1\), got 1.0"):
        MixedPairs(task, rehearsal, fraction=1.0)


def test_subsample_objects_keeps_whole_objects_within_the_budget_in_record_order() -> None:
    records = [
        ChipRecord(path=f"{v}_{i}.npy", target_class="PROC", target_type="proc", serial=f"v{v}",
                   depression_deg=17.0 + i, azimuth_deg=10.0 * i, height=8, width=8)
        for v in range(10) for i in range(3 + v % 2)
    ]  # fmt: skip  # vehicles of 3 and 4 chips, 35 chips in all
    kept = subsample_objects(records, max_chips=12, seed=5)
    serials = {r.serial for r in kept}
    assert len(kept) <= 12 and len(kept) >= 12 - 3  # full up to less than the smallest object
    assert all(sum(r.serial == s for r in kept) == sum(r.serial == s for r in records) for s in serials)
    assert kept == [r for r in records if r.serial in serials]  # record order
    assert kept == subsample_objects(records, max_chips=12, seed=5)  # seeded
    assert {r.serial for r in subsample_objects(records, max_chips=12, seed=6)} != serials
    assert subsample_objects(records, max_chips=35) == records  # everything fits: all kept
    with pytest.raises(ValueError, match="max_chips must be >= 1, got 0"):
        subsample_objects(records, max_chips=0)
