"""Throughput of every augmentation preset (images/s), written as JSON.

Times ``augment_batch`` on a batch of SAR-like magnitudes (``U ** 4``: dark clutter with a few bright
pixels; the cost does not depend on the content) after warm-up runs, on the requested device.

    python benchmarks/bench_augment.py --out docs/results/data/bench_augment_cpu.json
"""

from __future__ import annotations

import json
import os
import platform
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from sar_zero123.augment import PRESETS
from sar_zero123.augment.throughput import time_preset
from sar_zero123.config import parse_config
from sar_zero123.config.json_io import config_to_dict, write_json_atomic
from sar_zero123.data import DecibelScaling


@dataclass
class BenchConfig:
    out: str = "bench_augment.json"  # JSON file to write
    device: str = "cpu"  # torch device to run on
    batch_size: int = 256  # images per augment_batch call
    size: int = 128  # image side in pixels
    repeats: int = 5  # timed calls per preset (the median is reported)
    warmup: int = 1  # untimed calls per preset before timing
    presets: str = ""  # comma-separated preset names; empty = all of PRESETS
    seed: int = 0  # generator seed

    def __post_init__(self) -> None:
        for name in ("batch_size", "size", "repeats"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.warmup < 0:
            raise ValueError(f"warmup must be >= 0, got {self.warmup}")
        unknown = sorted(set(self.preset_names) - set(PRESETS))
        if unknown:
            raise ValueError(f"presets: unknown {unknown}; choose from {sorted(PRESETS)}")

    @property
    def preset_names(self) -> list[str]:
        return [p.strip() for p in self.presets.split(",") if p.strip()] or list(PRESETS)


def _cpu_name() -> str:
    """CPU model from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str] | None = None) -> dict:
    config = parse_config(BenchConfig, argv)
    device = torch.device(config.device)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    shape = (config.batch_size, 1, config.size, config.size)
    magnitude = torch.rand(shape, generator=generator, device=device) ** 4
    scaling = DecibelScaling()
    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    results = {}
    for preset in config.preset_names:
        seconds = sorted(time_preset(magnitude, preset, scaling, generator, config.repeats, config.warmup))
        median = seconds[len(seconds) // 2]
        results[preset] = {"images_per_s": config.batch_size / median, "median_s_per_batch": median,
                           "min_s_per_batch": seconds[0]}  # fmt: skip
        print(f"{preset:>20s}: {config.batch_size / median:10.1f} images/s ({median * 1e3:.1f} ms per batch)")
    report = {
        "config": config_to_dict(config),
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else _cpu_name(),
        "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
        # Other processes share the machine: the 1-minute load average says how contended it was.
        "load_average_1min": [load_before, os.getloadavg()[0] if hasattr(os, "getloadavg") else None],
        "torch": torch.__version__, "python": sys.version.split()[0], "results": results,
    }
    write_json_atomic(report, Path(config.out))
    print(json.dumps({k: v["images_per_s"] for k, v in results.items()}, indent=1))
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
