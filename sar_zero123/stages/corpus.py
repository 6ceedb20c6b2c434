"""The corpus stage: a prior corpus of procedural vehicles
(:func:`~sar_zero123.sim.corpus.write_prior_corpus`) under the run-folder rule.

The quickstart runs it when its preset asks for rehearsal (``rehearsal_vehicles``): a small corpus rendered
with the bundled priors' corpus options, whose pairs (across depressions) are mixed into every fine-tune so
that it keeps the prior's depression requests (measured in docs/usage/training.md's recipe table). Its
vehicles are the procedural seeds ``0 .. num_vehicles - 1``, the first of the prior's own corpus: rehearsal
shows the fine-tune vehicles the prior was trained on, never a named class.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from sar_zero123.runs.folder import StageTimer, finish_run
from sar_zero123.runs.stage import open_stage_folder
from sar_zero123.sim.corpus import DEFAULT_CLUTTER_DB_SPREAD, check_corpus_options, write_prior_corpus

logger = logging.getLogger(__name__)

__all__ = ["CORPUS_FOLDER", "CorpusConfig", "run_corpus"]

#: Where in the stage folder the corpus lands (its record beside it).
CORPUS_FOLDER = "corpus"


@dataclass
class CorpusConfig:
    """Render a prior corpus into ``output_dir`` (defaults: the bundled priors' corpus options)."""

    output_dir: str = "runs/corpus"  # stage folder: its record and corpus/ (index.csv, corpus.json, chips/)
    num_vehicles: int = 2000  # procedural vehicles (validation ones included)
    views_per_vehicle: int = 24  # chips per vehicle
    num_validation_vehicles: int = 32  # vehicles held out as class PROCVAL (never rehearsed)
    depression_range_deg: list[float] = field(default_factory=lambda: [10.0, 60.0])  # uniform depressions
    mstar_fraction: float = 0.25  # share of views at MSTAR's 15/17 deg instead
    size: int = 64  # chip side in pixels
    seed: int = 0  # corpus seed (views, clutter, noise); a vehicle depends on its own seed only
    num_workers: int = 2  # processes rendering vehicles
    resume: bool = True  # finish an interrupted corpus with these settings (its finished chips are kept)
    restart: bool = False  # move an existing folder at output_dir aside (never deleted) and render anew

    def __post_init__(self) -> None:
        self.depression_range_deg = [float(d) for d in self.depression_range_deg]
        if len(self.depression_range_deg) != 2:
            raise ValueError(f"depression_range_deg: expected (low, high), got {self.depression_range_deg}")
        check_corpus_options(**self._options())  # the checks write_prior_corpus makes, before any stage runs

    def _options(self) -> dict:
        """write_prior_corpus's keyword arguments."""
        low, high = self.depression_range_deg
        return {"num_vehicles": self.num_vehicles, "views_per_vehicle": self.views_per_vehicle,
                "num_validation_vehicles": self.num_validation_vehicles, "depression_range_deg": (low, high),
                "mstar_fraction": self.mstar_fraction, "size": self.size, "seed": self.seed,
                "clutter_db_spread": DEFAULT_CLUTTER_DB_SPREAD, "num_workers": self.num_workers}  # fmt: skip


def run_corpus(config: CorpusConfig) -> Path:
    """Render (or finish) the corpus into ``config.output_dir``/corpus; returns the corpus folder.

    Raises:
        ValueError: For a folder holding other work (the run-folder rule) or a corpus written with other
            options (``write_prior_corpus``, naming each difference).
    """
    timer = StageTimer()
    folder = open_stage_folder(
        config.output_dir, "corpus", config, data=None, resume=config.resume, restart=config.restart,
        may_differ=("resume", "restart", "num_workers"), resume_hint="--resume",
    )  # fmt: skip
    corpus = folder.path / CORPUS_FOLDER
    if folder.finished:
        logger.info("%s already holds this corpus", corpus)
        return corpus
    out = write_prior_corpus(corpus, **config._options(), progress=False)
    with open(out / "index.csv") as handle:
        chips = sum(1 for _ in handle) - 1
    finish_run(folder, [f"{CORPUS_FOLDER}/index.csv"], seconds=timer.seconds, results={"chips": chips})
    return out
