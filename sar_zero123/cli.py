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

:data:`COMMANDS` is the table the README's command table and a test are checked against; each command
function (``cli.finetune(argv=None)``, ...) is generated from its row: ``run(parse_config(config, argv))``,
then what the command prints and returns (:data:`_REPORTS`; by default the folder its stage returned).
"""

from __future__ import annotations

import importlib
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["COMMANDS", "Command", "config_class", "console"]

_LOG_FORMAT = "%(asctime)s %(levelname)s %(message)s"


@dataclass(frozen=True)
class Command:
    """One entry point: its console script, the other way to run it, its stage, its config class and what it
    calls; the command function of this module named ``function`` is generated from it (:func:`_command`)."""

    script: str  # the console script (pyproject.toml [project.scripts])
    also: str  # the same command as a train/ script or a module
    stage: str  # the stage recorded in its run folder's run.json ("augment": augment.json)
    config: str  # "module:Class" of the config dataclass whose fields are the flags
    function: str  # the function in this module the console script calls
    summary: str  # what it does, for the command table
    run: str  # "module:function" it calls: a stage's run_<stage>(config), or a module's own main(argv)
    # logging.basicConfig's format, set before the flags are parsed; None: logging left as it is
    log_format: str | None = None


_NAMED_LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

COMMANDS: tuple[Command, ...] = (
    Command("sar-zero123-quickstart", "python train/quickstart.py", "quickstart",
            "sar_zero123.stages.presets:QuickstartConfig", "quickstart",
            "every stage end to end on the simulator (or real chips), with a report",
            "sar_zero123.stages.quickstart:run_quickstart", _LOG_FORMAT),
    Command("sar-zero123-simulate", "python train/simulate.py", "simulate",
            "sar_zero123.stages.simulate:SimulateConfig", "simulate", "simulate a dataset of SAR chips",
            "sar_zero123.stages.simulate:run_simulate"),
    Command("sar-zero123-simclr", "python train/pretrain_simclr.py", "simclr",
            "sar_zero123.stages.simclr:PretrainSimCLRConfig", "simclr",
            "SimCLR pretraining of the SAR encoder (PFM's feature extractor)",
            "sar_zero123.stages.simclr:run_simclr"),
    Command("sar-zero123-vae", "python train/train_vae.py", "vae", "sar_zero123.stages.vae:TrainVAEConfig",
            "vae", "train a VAE on SAR chips", "sar_zero123.stages.vae:run_vae"),
    Command("sar-zero123-prior", "python train/pretrain_prior.py", "prior",
            "sar_zero123.stages.prior:PriorConfig", "prior",
            "the multi-view prior: procedural corpus, VAE, UNet", "sar_zero123.stages.prior:run_prior"),
    Command("sar-zero123-finetune", "python train/finetune_pfm.py", "finetune",
            "sar_zero123.stages.finetune:FinetuneConfig", "finetune",
            "fine-tune a pipeline with L_simple + lambda PFM", "sar_zero123.stages.finetune:run_finetune"),
    Command("sar-zero123-evaluators", "python train/train_evaluators.py", "evaluators",
            "sar_zero123.stages.evaluators:TrainEvaluatorsConfig", "evaluators",
            "the evaluation classifier and azimuth / depression regressors",
            "sar_zero123.stages.evaluators:run_evaluators", _LOG_FORMAT),
    Command("sar-zero123-evaluate", "python train/evaluate.py", "evaluate",
            "sar_zero123.stages.evaluate:EvaluateConfig", "evaluate",
            "Table III / IV, views, speed against error", "sar_zero123.stages.evaluate:run_evaluate",
            _LOG_FORMAT),
    Command("sar-zero123-table1", "python train/table1.py", "table1",
            "sar_zero123.stages.table1:Table1Config", "table1",
            "Table I: augmentations for the SimCLR encoder", "sar_zero123.stages.table1:run_table1",
            _NAMED_LOG_FORMAT),
    Command("sar-zero123-synth-to-real", "python train/synth_to_real.py", "synth_to_real",
            "sar_zero123.stages.synth_to_real:SynthToRealConfig", "synth_to_real",
            "Table II: classifiers trained on simulated chips, tested on real ones",
            "sar_zero123.stages.synth_to_real:run_synth_to_real", _NAMED_LOG_FORMAT),
    Command("sar-zero123-generate", "python -m sar_zero123.generate", "generate",
            "sar_zero123.generate:GenerateConfig", "generate", "novel views of one chip",
            "sar_zero123.generate:main"),
    Command("sar-zero123-augment", "python -m sar_zero123.augment_dataset", "augment",
            "sar_zero123.augment_dataset:AugmentConfig", "augment",
            "a dataset plus generated views of its chips", "sar_zero123.augment_dataset:main"),
    Command("sar-zero123-proxy-retrieval", "python train/train_proxy_retrieval.py", "proxy_retrieval",
            "sar_zero123.stages.proxy_retrieval:ProxyRetrievalConfig", "proxy_retrieval",
            "the learned shortlist of the simulator proxy's fit",
            "sar_zero123.stages.proxy_retrieval:run_proxy_retrieval"),
    Command("sar-zero123-interpolate", "python -m sar_zero123.interpolate", "interpolate",
            "sar_zero123.interpolate:InterpolateConfig", "interpolate",
            "a fine-tuned pipeline's weights mixed with its prior's (WiSE-FT)",
            "sar_zero123.interpolate:main"),
)  # fmt: skip


def config_class(command: Command) -> type:
    """The config dataclass of ``command`` (imported on demand)."""
    return _imported(command.config)


def _imported(target: str) -> Any:
    """The object ``"module:name"`` names, its module imported on demand (so ``--help`` loads little)."""
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


# What a command prints and returns once its stage has run, from the folder the stage returned (and the
# seconds since the command started); a command without one returns the folder.
def _quickstart_report(report: Path, seconds: float) -> Path:
    print(f"report: {report}")
    return report


def _simulate_report(out: Path, seconds: float) -> Path:
    with open(out / "index.csv") as handle:
        n_chips = sum(1 for _ in handle) - 1
    print(f"{out / 'index.csv'}: {n_chips} chips ({seconds:.1f} s)")
    return out  # printed last by the console script, as every command's folder


def _json_report(name: str) -> Callable[[Path, float], Any]:
    """Prints the run folder (the last line on stdout, as for every command) and returns its file ``name``."""

    def report(folder: Path, seconds: float) -> Any:
        print(folder)
        return json.loads((folder / name).read_text())

    return report


def _evaluators_report(folder: Path, seconds: float) -> dict[str, dict[str, float]]:
    results = json.loads((folder / "metrics.json").read_text())["models"]
    for name, metrics in results.items():
        summary = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in metrics.items()
        )
        print(f"{name}: {summary}")
    print(folder)
    return results


def _evaluate_report(folder: Path, seconds: float) -> dict[str, Any]:
    from sar_zero123.stages.evaluate import load_evaluation

    print((folder / "table3.md").read_text())
    print(folder)
    return load_evaluation(folder)


_REPORTS: dict[str, tuple[Callable[[Path, float], Any], str]] = {
    "quickstart": (_quickstart_report, "the path of ``report.md``"),
    "simulate": (_simulate_report, "the dataset folder"),
    "simclr": (_json_report("metrics.json"), "the metrics written to ``metrics.json``"),
    "evaluators": (_evaluators_report, "``{name: test metrics}`` as written to ``metrics.json``"),
    "evaluate": (_evaluate_report, '``{"table3": ..., "speed_error": [...]}`` as written to disk'),
    "table1": (_json_report("table1.json"), "the dict written to ``table1.json``"),
    "synth_to_real": (_json_report("table2.json"), "the dict written to ``table2.json``"),
}


def _command(command: Command) -> Callable[[Sequence[str] | None], Any]:
    """The command function of ``command``: ``run(parse_config(config, argv))`` (a module's ``main(argv)``
    as it is), then what :data:`_REPORTS` prints and returns, else the folder the run returned."""
    report, returns = _REPORTS.get(command.function, (None, "its folder"))

    def function(argv: Sequence[str] | None = None) -> Any:
        from sar_zero123.config import parse_config

        run = _imported(command.run)
        if command.run.endswith(":main"):  # the module's own entry point parses its flags
            return run(argv)
        config = config_class(command)
        start = time.perf_counter()
        if command.log_format is not None:
            logging.basicConfig(level=logging.INFO, format=command.log_format)
        result = run(parse_config(config, argv))
        return result if report is None else report(result, time.perf_counter() - start)

    function.__name__ = function.__qualname__ = command.function
    function.__module__ = __name__
    function.__doc__ = f"``{command.script}``: {command.summary}; returns {returns}."
    return function


for _entry in COMMANDS:  # cli.finetune(argv=None), ...: one function per command
    globals()[_entry.function] = _command(_entry)
del _entry


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
