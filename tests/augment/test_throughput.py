"""``sar_zero123.augment.throughput``: a preset's timed calls."""

from __future__ import annotations

import pytest
import torch

from sar_zero123.augment.throughput import time_preset
from sar_zero123.data import DecibelScaling


def test_time_preset_times_each_repeat_and_refuses_an_unknown_preset() -> None:
    generator = torch.Generator().manual_seed(0)
    magnitude = torch.rand(2, 1, 16, 16, generator=generator) ** 4
    for preset in ("monotonic", "simclr-full"):
        seconds = time_preset(magnitude, preset, DecibelScaling(), generator, repeats=2, warmup=0)
        assert len(seconds) == 2 and all(s > 0 for s in seconds)
    with pytest.raises(ValueError, match="rotate"):
        time_preset(magnitude, "rotate", DecibelScaling(), generator, repeats=1, warmup=0)
