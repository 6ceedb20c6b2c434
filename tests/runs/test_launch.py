"""Tests for sar_zero123.runs.launch (the distributed-launch guard, tracker hparams and replica digests are
exercised by the script tests; here the closed-form checks)."""

from __future__ import annotations

import pytest

from sar_zero123.runs.launch import check_global_batch


def test_check_global_batch_needs_one_batch_per_process() -> None:
    check_global_batch(8, 4, 2)  # exactly one global batch
    with pytest.raises(ValueError, match="^data: 7 training pairs, fewer than a global batch of 8$"):
        check_global_batch(7, 4, 2, what="pairs")
