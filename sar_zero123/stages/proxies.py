"""The proxies stage: each vehicle of a data folder gets its simulator proxies
(:func:`~sar_zero123.data.corpus_proxies.write_corpus_proxies`) under the run-folder rule.

A pipeline whose UNet takes the simulator proxy (``spatial_pose="proxy"``, the bundled
``sar-zero123/sim-prior-identity``) fine-tunes on pairs that carry each chip's proxies at both poses. The
quickstart runs this stage when its preset's prior takes the proxy: the bank is fitted to one view of each
vehicle (its first chip in ``index.csv``; a vehicle is a class and serial), and the best bank vehicles are
rendered at every chip's pose. The data folder is only read; the proxies land in this stage's own folder.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from sar_zero123.data.corpus_proxies import write_corpus_proxies
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run
from sar_zero123.runs.stage import open_stage_folder
from sar_zero123.sim.proxy import PROXY_FIRST_SEED

logger = logging.getLogger(__name__)

__all__ = ["PROXIES_FOLDER", "ProxiesConfig", "run_proxies"]

#: Where in the stage folder the proxies land (``proxies.safetensors`` and ``proxies.json``).
PROXIES_FOLDER = "proxies"


@dataclass
class ProxiesConfig:
    """Fit and render the simulator proxies of every vehicle of a data folder into ``output_dir``."""

    data: str = "data"  # data folder with index.csv (azimuth and depression of every chip), only read
    output_dir: str = "runs/proxies"  # stage folder: its record and proxies/
    num_vehicles: int = 250  # bank vehicles fitted to each data vehicle (sar_zero123.sim.proxy.ProxyBank)
    candidates: int = 2  # best-fitting bank vehicles kept per data vehicle (the best, then runners-up)
    image_size: int | None = None  # side the chips are read at as a fine-tune reads them (None: as stored)
    first_seed: int = PROXY_FIRST_SEED  # procedural seed of the bank's first vehicle
    num_workers: int = 2  # processes fitting vehicles in parallel
    resume: bool = True  # a finished stage with these settings is returned; an unfinished one is redone
    restart: bool = False  # move an existing folder at output_dir aside (never deleted) and start over

    def __post_init__(self) -> None:
        size = self.image_size
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise ValueError(f"image_size: expected an integer >= 1 or None, got {size!r}")
        for name in ("num_vehicles", "candidates", "num_workers"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
        if self.candidates > self.num_vehicles:
            raise ValueError(
                f"candidates: at most num_vehicles ({self.num_vehicles}), got {self.candidates}"
            )


def run_proxies(config: ProxiesConfig) -> Path:
    """Write (or return, when finished with these settings) the proxies; returns their folder.

    Raises:
        ValueError: For a folder holding other work (the run-folder rule), or a data folder whose index
            lacks a chip's pose.
    """
    if not (Path(config.data) / "index.csv").is_file():
        raise FileNotFoundError(f"data: expected a folder with index.csv, got {config.data}")
    timer = StageTimer()
    folder = open_stage_folder(
        config.output_dir, "proxies", config, data={"data": data_identity(config.data)}, resume=config.resume,
        restart=config.restart, may_differ=("resume", "restart", "num_workers"), resume_hint="--resume",
    )  # fmt: skip
    out = folder.path / PROXIES_FOLDER
    if folder.finished:
        logger.info("%s already holds these proxies", out)
        return out
    record = write_corpus_proxies(
        config.data, out, num_vehicles=config.num_vehicles, candidates=config.candidates,
        first_seed=config.first_seed, size=config.image_size, num_workers=config.num_workers,
    )  # fmt: skip
    finish_run(folder, [f"{PROXIES_FOLDER}/{Path(record).name}"], seconds=timer.seconds)
    return out
