"""The simulate stage: a dataset folder of simulated chips, under the run-folder rule.

``sar-zero123-simulate --out DIR`` (``python train/simulate.py``) parses its flags into
:class:`SimulateConfig` and calls :func:`run_simulate`. The stage refuses a folder that holds another
dataset (``simulate_dataset`` alone would replace its index and leave the old chips unlisted), continues
one only with ``resume`` and moves one aside only with ``restart`` (:mod:`sar_zero123.runs.folder`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from sar_zero123.config import RemovedField
from sar_zero123.runs.folder import StageTimer, finish_run
from sar_zero123.runs.stage import open_stage_folder
from sar_zero123.sim.dataset import check_simulation_options, simulate_dataset
from sar_zero123.sim.targets import TARGET_CLASSES

logger = logging.getLogger(__name__)

__all__ = ["SimulateConfig", "run_simulate"]


@dataclass
class SimulateConfig:
    """Simulate SAR target chips into ``out``: ``index.csv`` and ``chips/<dep>deg/<CLASS>/*.npy``."""

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "azimuth_jitter_deg", "normalization",
    )  # fmt: skip
    #: Removed fields: refused in one line naming what replaced each (a config or run folder holding the old
    #: default of real_root or procedural_sheet reads as before).
    REMOVED_FIELDS = {
        "azimuth_step": RemovedField(None, "it is now --azimuth_step_deg"),
        "azimuth_jitter": RemovedField(None, "it is now azimuth_jitter_deg (--set azimuth_jitter_deg=...)"),
        "depressions": RemovedField(None, "it is now --depressions_deg"),
        "real_root": RemovedField(None, "the contact sheet shows simulated chips only; MSTAR beside them is "
                                  "sar_zero123.sim.contact_sheet.contact_sheet(real_root=...)"),
        "procedural_sheet": RemovedField(0, "that sheet is "
                                         "sar_zero123.sim.contact_sheet.procedural_contact_sheet(...)"),
    }  # fmt: skip

    out: str = "runs/sim"  # output folder
    classes: list[str] = field(default_factory=lambda: list(TARGET_CLASSES))  # classes to simulate
    instances: int = 2  # instances (serials) per class
    azimuth_step_deg: float = 5.0  # azimuth grid step in degrees
    azimuth_jitter_deg: float = 0.0  # seeded per-chip azimuth jitter width (deg)
    depressions_deg: list[float] = field(default_factory=lambda: [15.0, 17.0])  # depression angles (deg)
    size: int = 128  # chip size in pixels
    seed: int = 0  # dataset seed
    normalization: Literal["peak", "calibrated"] = "peak"  # per-chip peak or fixed calibration
    contact_sheet: bool = False  # also write out/contact_sheet.png
    resume: bool = False  # an unfinished dataset with these settings is redone; a finished one is kept
    restart: bool = False  # move an existing folder at out aside (never deleted) and simulate anew

    def __post_init__(self) -> None:
        self.classes = [str(c).upper() for c in self.classes]
        self.depressions_deg = [float(d) for d in self.depressions_deg]
        check_simulation_options(
            self.classes, self.instances, self.azimuth_step_deg, self.depressions_deg, self.size, self.seed,
            self.azimuth_jitter_deg, self.normalization, 3.0,
        )  # fmt: skip


def run_simulate(config: SimulateConfig) -> Path:
    """Simulate the dataset (and the sheets asked for) into ``config.out``; returns the folder.

    Raises:
        ValueError: From :func:`~sar_zero123.runs.folder.open_run_folder`, for a folder holding
            other work.
    """
    timer = StageTimer()
    folder = open_stage_folder(
        config.out, "simulate", config, data=None, resume=config.resume, restart=config.restart,
        may_differ=("resume", "restart"), flag_hint="out", resume_hint="--resume",
    )  # fmt: skip
    if folder.finished:
        logger.info("%s already holds this dataset", folder.path)
        return folder.path
    out = simulate_dataset(
        folder.path,
        classes=config.classes,
        instances=config.instances,
        azimuth_step_deg=config.azimuth_step_deg,
        depressions_deg=tuple(config.depressions_deg),
        size=config.size,
        seed=config.seed,
        azimuth_jitter_deg=config.azimuth_jitter_deg,
        normalization=config.normalization,
    )
    outputs = ["index.csv"]
    if config.contact_sheet:
        from sar_zero123.sim.contact_sheet import contact_sheet

        contact_sheet(
            out / "contact_sheet.png",
            classes=config.classes,
            depression_deg=config.depressions_deg[-1],
            size=config.size,
            seed=config.seed,
        )
        outputs.append("contact_sheet.png")
    with open(out / "index.csv") as handle:
        chips = sum(1 for _ in handle) - 1
    finish_run(folder, outputs, seconds=timer.seconds, results={"chips": chips})
    return out
