"""What the benchmark scripts share: their parser, the device they ran on, and the clock's barrier.

A script runs as ``python benchmarks/<name>.py``: its folder comes first on ``sys.path``, so it imports
this module as ``_common``. The measuring itself is library code (``sar_zero123``); a script parses its
flags, calls the library, and writes its record with ``sar_zero123.config.json_io.write_json_atomic``.
"""

from __future__ import annotations

import argparse
import os
import platform
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import torch

__all__ = ["cpu_device", "device_record", "gpu_device", "parallel_map", "script_parser", "synchronize"]


def script_parser(doc: str | None) -> argparse.ArgumentParser:
    """An argument parser described by the first line of a script's docstring (its ``--help``)."""
    return argparse.ArgumentParser(description=(doc or "").splitlines()[0])


def cpu_device() -> str:
    """``"CPU, <cores> cores, torch <version>"``: the device a CPU run records."""
    return f"CPU, {os.cpu_count()} cores, torch {torch.__version__}"


def gpu_device() -> str:
    """``"<GPU name>, torch <version>"``, or ``"cpu, torch <version>"`` without one: a GPU script's device."""
    if torch.cuda.is_available():
        return f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}"
    return f"cpu, torch {torch.__version__}"


def device_record() -> dict[str, str]:
    """``{"device": ..., "platform": ...}``: a CPU run's device (:func:`cpu_device`) and the platform."""
    return {"device": cpu_device(), "platform": platform.platform()}


def synchronize(device: str | torch.device) -> None:
    """Waits for the device's queued work (CUDA), so that a clock read after it counts that work."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def parallel_map(function: Callable[[Any], Any], jobs: Sequence[Any], workers: int) -> list[Any]:
    """``function`` of each job, in order, computed in ``workers`` processes (a quarter of each one's share
    per chunk)."""
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(function, jobs, chunksize=max(1, len(jobs) // (4 * workers))))
