"""Throughput of an augmentation preset: the wall-clock seconds of :func:`~sar_zero123.augment.augment_batch`
calls on one batch (``benchmarks/bench_augment.py`` times every preset with it)."""

from __future__ import annotations

import time

import torch

from .views import AugmentationPreset, Scaling, augment_batch

__all__ = ["time_preset"]


def time_preset(
    magnitude: torch.Tensor,
    preset: str | AugmentationPreset,
    scaling: Scaling,
    generator: torch.Generator,
    repeats: int,
    warmup: int,
) -> list[float]:
    """Wall-clock seconds of ``repeats`` :func:`augment_batch` calls after ``warmup`` untimed ones (on a GPU
    each waits for the device before and after).

    Raises:
        ValueError: As ``augment_batch`` does, for a bad batch or an unknown preset.
    """

    def synchronize() -> None:
        if magnitude.device.type == "cuda":
            torch.cuda.synchronize(magnitude.device)

    for _ in range(warmup):
        augment_batch(magnitude, preset, scaling, generator)
    seconds = []
    for _ in range(repeats):
        synchronize()
        start = time.perf_counter()
        augment_batch(magnitude, preset, scaling, generator)
        synchronize()
        seconds.append(time.perf_counter() - start)
    return seconds
