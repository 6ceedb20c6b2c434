"""Train the evaluator models that score generated views (Table III, Table IV).

    python train/train_evaluators.py --output_dir runs/evaluators --data /path/to/mstar

The flags are the fields of `sar_zero123.stages.evaluators.TrainEvaluatorsConfig`; the stage is
`sar_zero123.stages.evaluators.run_evaluators` (the models, `metrics.json` and the run-folder rule are
described there). An `--output_dir` that holds a run is refused: `--resume` continues an unfinished run
with the same settings (or returns a finished one), `--restart` moves the old run aside.
"""

from __future__ import annotations

from sar_zero123 import cli


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    """Trains classifier, regressor, probes and depression regressor; returns `{name: test metrics}` as
    written to `metrics.json`."""
    return cli.evaluators(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.evaluators())
