"""Speed against error for every (pipeline, scheduler, step count): images per second, UNet evaluations per
image, peak memory, the errors and their Pareto front (``speed_error.{json,md,png}``).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.evaluation.evaluators import Evaluators
from sar_zero123.evaluation.protocol import PairSet, generate_pair_targets, score, set_scheduler
from sar_zero123.evaluation.tables import MIN_SPEED_PAIRS, plot_speed_error, speed_markdown
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import SamplerSettings

logger = logging.getLogger(__name__)

__all__ = [
    "SPEED_ERROR_SCORES",
    "PeakMemory",
    "UNetImageCount",
    "device_name",
    "pareto_front",
    "speed_error_rows",
    "write_speed_error",
]


#: The scores a speed/error row keeps, each beside its standard error.
SPEED_ERROR_SCORES = ("azimuth_error_deg", "azimuth_error_deg_se", "accuracy", "accuracy_se", "ms_ssim",
                      "ms_ssim_se")  # fmt: skip


class UNetImageCount:
    """Counts the samples the pipeline's UNet evaluates while active (a forward hook): a sampler's cost
    per image, measured (guidance branches and strength included).
    """

    def __init__(self, pipe: SARZero123Pipeline) -> None:
        self.unet, self.samples, self._handle = pipe.unet, 0, None

    def _count(self, module, args, kwargs) -> None:
        sample = args[0] if args else kwargs["sample"]
        self.samples += int(sample.shape[0])

    def __enter__(self) -> UNetImageCount:
        self._handle = self.unet.register_forward_pre_hook(self._count, with_kwargs=True)
        return self

    def __exit__(self, *exc) -> None:
        self._handle.remove()


class PeakMemory:
    """Peak memory in MiB of the work done while active: CUDA's ``max_memory_allocated``; on the CPU the
    resident set size sampled every ``interval_s`` (else the process's lifetime peak from ``resource``).
    """

    def __init__(self, device: torch.device, interval_s: float = 0.005) -> None:
        self.device, self.interval_s, self.peak_mib = torch.device(device), interval_s, float("nan")
        self._stop = None
        self._thread = None

    @staticmethod
    def _rss_mib() -> float:
        try:
            with open("/proc/self/statm") as handle:
                pages = int(handle.read().split()[1])
            return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
        except (OSError, ValueError, IndexError):
            import resource

            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB

    def __enter__(self) -> PeakMemory:
        import threading

        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
            return self
        self.peak_mib = self._rss_mib()
        self._stop = threading.Event()

        def sample() -> None:
            while not self._stop.wait(self.interval_s):
                self.peak_mib = max(self.peak_mib, self._rss_mib())

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            self.peak_mib = torch.cuda.max_memory_allocated(self.device) / 2**20
            return
        self._stop.set()
        self._thread.join()
        self.peak_mib = max(self.peak_mib, self._rss_mib())


def pareto_front(
    rows: list[dict[str, Any]], speed: str = "images_per_s", error: str = "azimuth_error_deg"
) -> list[bool]:
    """Whether each row is on the front of speed (higher is better) against error (lower is better): no
    other row is at least as fast and at least as accurate, and strictly better in one."""
    return [
        not any(
            other[speed] >= row[speed] and other[error] <= row[error]
            and (other[speed] > row[speed] or other[error] < row[error])
            for other in rows
        )
        for row in rows
    ]  # fmt: skip


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU with its thread count (speed figures depend on both)."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU ({torch.get_num_threads()} threads)"


def speed_error_rows(
    pipes: dict[str, Any],
    pairs: PairSet,
    evaluators: Evaluators,
    *,
    schedulers: Sequence[str],
    steps: Sequence[int],
    guidance_scale: float | None,
    sampler: SamplerSettings,
    batch_size: int,
    scoring: dict[str, Any],
    device: torch.device,
) -> list[dict[str, Any]]:
    """Azimuth error and accuracy against images/s for every (pipeline, scheduler, step count) on ``pairs``,
    each row marked ``pareto`` where no other row beats it on both speed and error.

    Args:
        pipes: The pipelines by row name (each one's scheduler is restored afterwards).
        schedulers: ``SCHEDULERS`` names each pipeline samples with.
        guidance_scale: The warm-up call's (``None``: the pipeline's recorded value).
        sampler: Every timed call's; each row sets its own step count.
        scoring: :func:`~sar_zero123.evaluation.protocol.score`'s keyword arguments.
    """
    rows: list[dict[str, Any]] = []
    for name, pipe in pipes.items():
        original = pipe.scheduler
        for scheduler in schedulers:
            set_scheduler(pipe, scheduler)
            # a warm-up call, so one-time costs (allocation, kernel selection) do not count
            warm_up = SamplerSettings(num_inference_steps=1, guidance_scale=guidance_scale)
            generate_pair_targets(
                pipe, pairs.subset(1), sampler=warm_up, batch_size=1, device=device,
                desc=f"{name} {scheduler} warm-up",
            )  # fmt: skip
            for num_steps in steps:
                with UNetImageCount(pipe) as unet_count, PeakMemory(device) as memory:
                    images, seconds = generate_pair_targets(
                        pipe, pairs, sampler=replace(sampler, num_inference_steps=num_steps),
                        batch_size=batch_size, device=device, desc=f"{name} {scheduler} {num_steps} steps",
                    )  # fmt: skip
                scores = score(images, pairs, evaluators, **scoring)
                rows.append({
                    "pipeline": name, "scheduler": scheduler, "steps": num_steps, "n": len(pairs),
                    "batch_size": batch_size, "images_per_s": len(pairs) / seconds,
                    "unet_evaluations_per_image": unet_count.samples / len(pairs),
                    "peak_memory_mib": memory.peak_mib,
                    **{key: scores[key] for key in SPEED_ERROR_SCORES},
                })  # fmt: skip
                logger.info("speed %s", json.dumps(rows[-1]))
        pipe.scheduler = original
    for row, on_front in zip(rows, pareto_front(rows), strict=True):
        row["pareto"] = on_front
    return rows


def write_speed_error(
    rows: list[dict[str, Any]], output_dir: Path, device: torch.device, *, num_pairs: int
) -> list[str]:
    """Writes ``speed_error.{json,md,png}`` of :func:`speed_error_rows`' rows into ``output_dir``; returns
    their names. Fewer than ``MIN_SPEED_PAIRS`` pairs per row mark the sweep indicative."""
    memory_kind = "max allocated (CUDA)" if device.type == "cuda" else "resident set size (CPU)"
    write_json_atomic(
        {"device": str(device), "device_name": device_name(device), "peak_memory": memory_kind,
         "indicative": num_pairs < MIN_SPEED_PAIRS, "rows": rows},
        output_dir / "speed_error.json",
    )  # fmt: skip
    (output_dir / "speed_error.md").write_text(speed_markdown(rows, device_name(device), memory_kind))
    plot_speed_error(rows, output_dir / "speed_error.png")
    return ["speed_error.json", "speed_error.md", "speed_error.png"]
