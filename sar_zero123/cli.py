"""The command line: every entry point, the stage it runs and the config its flags come from.

Each command is a console script (``[project.scripts]`` in ``pyproject.toml``; ``sar-zero123-finetune
--help``) and also a script under ``train/`` or a ``python -m`` module, which call the same function here:
``accelerate launch train/finetune_pfm.py`` is ``sar-zero123-finetune`` on many processes. One convention
for all of them:

* the flags are the fields of the command's config dataclass, ``--field_name`` (``--field-name`` too),
  read by :func:`sar_zero123.config.parse_config`; ``--config FILE`` (YAML or JSON) sets fields first;
* every command that writes a run folder continues it with ``--resume`` (training stages: the same as
  ``--resume_from_checkpoint latest``) and moves it aside with ``--restart``; any other use of a folder
  holding a run is refused, naming each difference (:mod:`sar_zero123.runs.folder`).

:data:`COMMANDS` is the table the README's command table and a test are checked against.
"""

from __future__ import annotations

import importlib
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["COMMANDS", "Command", "config_class", "console"]

_LOG_FORMAT = "%(asctime)s %(levelname)s %(message)s"


@dataclass(frozen=True)
class Command:
    """One entry point: its console script, the other way to run it, its stage and its config class."""

    script: str  # the console script (pyproject.toml [project.scripts])
    also: str  # the same command as a train/ script or a module
    stage: str  # the stage recorded in its run folder's run.json ("augment": augment.json)
    config: str  # "module:Class" of the config dataclass whose fields are the flags
    function: str  # the function in this module the console script calls
    summary: str  # what it does, for the command table


COMMANDS: tuple[Command, ...] = (
    Command("sar-zero123-quickstart", "python train/quickstart.py", "quickstart",
            "sar_zero123.stages.presets:QuickstartConfig", "quickstart",
            "every stage end to end on the simulator (or real chips), with a report"),
    Command("sar-zero123-simulate", "python train/simulate.py", "simulate",
            "sar_zero123.stages.simulate:SimulateConfig", "simulate", "simulate a dataset of SAR chips"),
    Command("sar-zero123-simclr", "python train/pretrain_simclr.py", "simclr",
            "sar_zero123.stages.simclr:PretrainSimCLRConfig", "simclr",
            "SimCLR pretraining of the SAR encoder (PFM's feature extractor)"),
    Command("sar-zero123-vae", "python train/train_vae.py", "vae", "sar_zero123.stages.vae:TrainVAEConfig",
            "vae", "train a VAE on SAR chips"),
    Command("sar-zero123-prior", "python train/pretrain_prior.py", "prior",
            "sar_zero123.stages.prior:PriorConfig", "prior",
            "the multi-view prior: procedural corpus, VAE, UNet"),
    Command("sar-zero123-finetune", "python train/finetune_pfm.py", "finetune",
            "sar_zero123.stages.finetune:FinetuneConfig", "finetune",
            "fine-tune a pipeline with L_simple + lambda PFM"),
    Command("sar-zero123-evaluators", "python train/train_evaluators.py", "evaluators",
            "sar_zero123.stages.evaluators:TrainEvaluatorsConfig", "evaluators",
            "the evaluation classifier and azimuth / depression regressors"),
    Command("sar-zero123-evaluate", "python train/evaluate.py", "evaluate",
            "sar_zero123.stages.evaluate:EvaluateConfig", "evaluate",
            "Table III / IV, views, speed against error"),
    Command("sar-zero123-table1", "python train/table1.py", "table1",
            "sar_zero123.stages.table1:Table1Config", "table1",
            "Table I: augmentations for the SimCLR encoder"),
    Command("sar-zero123-synth-to-real", "python train/synth_to_real.py", "synth_to_real",
            "sar_zero123.stages.synth_to_real:SynthToRealConfig", "synth_to_real",
            "Table II: classifiers trained on simulated chips, tested on real ones"),
    Command("sar-zero123-generate", "python -m sar_zero123.generate", "generate",
            "sar_zero123.generate:GenerateConfig", "generate", "novel views of one chip"),
    Command("sar-zero123-augment", "python -m sar_zero123.augment_dataset", "augment",
            "sar_zero123.augment_dataset:AugmentConfig", "augment",
            "a dataset plus generated views of its chips"),
    Command("sar-zero123-proxy-retrieval", "python train/train_proxy_retrieval.py", "proxy_retrieval",
            "sar_zero123.stages.proxy_retrieval:ProxyRetrievalConfig", "proxy_retrieval",
            "the learned shortlist of the simulator proxy's fit"),
    Command("sar-zero123-interpolate", "python -m sar_zero123.interpolate", "interpolate",
            "sar_zero123.interpolate:InterpolateConfig", "interpolate",
            "a fine-tuned pipeline's weights mixed with its prior's (WiSE-FT)"),
)  # fmt: skip


def config_class(command: Command) -> type:
    """The config dataclass of ``command`` (imported on demand)."""
    module, name = command.config.split(":")
    return getattr(importlib.import_module(module), name)


def quickstart(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-quickstart``: runs the whole chain; returns the path of ``report.md``."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.presets import QuickstartConfig
    from sar_zero123.stages.quickstart import run_quickstart

    logging.basicConfig(level=logging.INFO, format=_LOG_FORMAT)
    report = run_quickstart(parse_config(QuickstartConfig, argv))
    print(f"report: {report}")
    return report


def simulate(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-simulate``: simulates a dataset folder; returns it."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.simulate import SimulateConfig, run_simulate

    start = time.perf_counter()
    out = run_simulate(parse_config(SimulateConfig, argv))
    with open(out / "index.csv") as handle:
        n_chips = sum(1 for _ in handle) - 1
    print(f"{out / 'index.csv'}: {n_chips} chips ({time.perf_counter() - start:.1f} s)")
    return out  # printed last by the console script, as every command's folder


def simclr(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``sar-zero123-simclr``: SimCLR pretraining; returns the metrics written to ``metrics.json``."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.simclr import PretrainSimCLRConfig, run_simclr

    output_dir = run_simclr(parse_config(PretrainSimCLRConfig, argv))
    print(output_dir)  # the run folder, the last line on stdout as for every command
    return json.loads((output_dir / "metrics.json").read_text())


def vae(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-vae``: trains (or resumes) a VAE; returns its run folder."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.vae import TrainVAEConfig, run_vae

    return run_vae(parse_config(TrainVAEConfig, argv))


def proxy_retrieval(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-proxy-retrieval``: trains the learned shortlist of the proxy fit; returns its folder."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.proxy_retrieval import ProxyRetrievalConfig, run_proxy_retrieval

    return run_proxy_retrieval(parse_config(ProxyRetrievalConfig, argv))


def prior(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-prior``: corpus, VAE and UNet of the prior (each resumable); returns its pipeline."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.prior import PriorConfig, run_prior

    return run_prior(parse_config(PriorConfig, argv))


def finetune(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-finetune``: fine-tunes (or resumes) a pipeline; returns its run folder."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.finetune import FinetuneConfig, run_finetune

    return run_finetune(parse_config(FinetuneConfig, argv))


def evaluators(argv: Sequence[str] | None = None) -> dict[str, dict[str, float]]:
    """``sar-zero123-evaluators``: trains the evaluator models; returns ``{name: test metrics}`` as written
    to ``metrics.json`` (and prints them)."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.evaluators import TrainEvaluatorsConfig, run_evaluators

    config = parse_config(TrainEvaluatorsConfig, argv)
    logging.basicConfig(level=logging.INFO, format=_LOG_FORMAT)
    folder = run_evaluators(config)
    results = json.loads((folder / "metrics.json").read_text())["models"]
    for name, metrics in results.items():
        summary = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in metrics.items()
        )
        print(f"{name}: {summary}")
    print(folder)
    return results


def evaluate(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``sar-zero123-evaluate``: the evaluation; returns ``{"table3": ..., "speed_error": [...]}`` as written
    to disk (and prints Table III)."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.evaluate import EvaluateConfig, load_evaluation, run_evaluate

    config = parse_config(EvaluateConfig, argv)
    logging.basicConfig(level=logging.INFO, format=_LOG_FORMAT)
    folder = run_evaluate(config)
    print((folder / "table3.md").read_text())
    print(folder)
    return load_evaluation(folder)


def table1(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``sar-zero123-table1``: builds Table I; returns the dict written to ``table1.json``."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.table1 import Table1Config, run_table1

    config = parse_config(Table1Config, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    folder = run_table1(config)
    print(folder)
    return json.loads((folder / "table1.json").read_text())


def synth_to_real(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``sar-zero123-synth-to-real``: builds Table II; returns the dict written to ``table2.json``."""
    from sar_zero123.config import parse_config
    from sar_zero123.stages.synth_to_real import SynthToRealConfig, run_synth_to_real

    config = parse_config(SynthToRealConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    folder = run_synth_to_real(config)
    print(folder)
    return json.loads((folder / "table2.json").read_text())


def generate(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-generate``: novel views of one chip; returns the output folder."""
    from sar_zero123.generate import main

    return main(argv)


def augment(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-augment``: a dataset plus generated views; returns the output folder."""
    from sar_zero123.augment_dataset import main

    return main(argv)


def interpolate(argv: Sequence[str] | None = None) -> Path:
    """``sar-zero123-interpolate``: a fine-tune's weights mixed with its prior's; returns the pipeline."""
    from sar_zero123.interpolate import main

    return main(argv)


class _ConsoleScripts:
    """The console scripts (``[project.scripts]``: ``sar_zero123.cli:console.<function>``).

    Each command function returns its result to Python callers (a folder, a metrics dict); a console
    script's launcher passes what it calls to ``sys.exit``, which would print that value and exit 1. Here
    each script runs its function (looked up when called) under :func:`sar_zero123.runs.refusals.run_command`:
    exit 0 once it returns, a refusal in one line, ``sar-zero123-<command>: error: <message>``, exit 2
    (``--traceback``: raised in full). The ``train/`` scripts and ``python -m`` commands run the same way.
    """

    def __getattr__(self, name: str) -> Any:
        if name not in {command.function for command in COMMANDS}:
            raise AttributeError(name)

        def script() -> int:
            from sar_zero123.runs.refusals import run_command

            prog = next(command.script for command in COMMANDS if command.function == name)
            return run_command(globals()[name], prog)

        script.__name__ = script.__qualname__ = name
        script.__doc__ = f"``{name}`` as a console script: exit status 0 when it returns."
        return script


#: What the console scripts call: ``console.finetune()`` runs :func:`finetune` on ``sys.argv`` and returns 0.
console = _ConsoleScripts()
