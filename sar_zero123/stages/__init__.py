"""The stages of the method as library calls: each takes its typed config and returns its output folder.

``train/*.py`` parse flags into these configs and call the stage; stages that drive others (the prior,
the quickstart) build the configs directly. Every stage applies the run-folder rule
(:mod:`sar_zero123.runs.folder`) before any work. Names are imported on first use, so that a light
stage (the simulator) does not load the training stack.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> the module of this package that defines it.
_EXPORTS = {
    "FinetuneConfig": "finetune",
    "run_finetune": "finetune",
    "TrainVAEConfig": "vae",
    "run_vae": "vae",
    "PretrainSimCLRConfig": "simclr",
    "run_simclr": "simclr",
    "PriorConfig": "prior",
    "run_prior": "prior",
    "TrainEvaluatorsConfig": "evaluators",
    "run_evaluators": "evaluators",
    "EvaluateConfig": "evaluate",
    "run_evaluate": "evaluate",
    "CorpusConfig": "corpus",
    "run_corpus": "corpus",
    "SimulateConfig": "simulate",
    "run_simulate": "simulate",
    "Table1Config": "table1",
    "run_table1": "table1",
    "SynthToRealConfig": "synth_to_real",
    "run_synth_to_real": "synth_to_real",
    "Recipe": "presets",
    "RECIPES": "presets",
    "QuickstartConfig": "presets",
    "plan_stages": "quickstart",
    "run_quickstart": "quickstart",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
