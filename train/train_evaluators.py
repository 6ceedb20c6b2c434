"""Train the evaluator models that score generated views (Table III, Table IV).

    python train/train_evaluators.py --output_dir runs/evaluators --data /path/to/mstar

The flags are the fields of `sar_zero123.stages.evaluators.TrainEvaluatorsConfig`; the stage is
`sar_zero123.stages.evaluators.run_evaluators` (the models, `metrics.json` and the run-folder rule are
described there). An `--output_dir` that holds a run is refused: `--resume` continues an unfinished run
with the same settings (or returns a finished one), `--restart` moves the old run aside.
"""

from __future__ import annotations

import json
import logging

from sar_zero123.config import parse_config
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig, run_evaluators


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    """Trains classifier, regressor, probes and depression regressor; returns `{name: test metrics}` as
    written to `metrics.json`."""
    config = parse_config(TrainEvaluatorsConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    folder = run_evaluators(config)
    results = json.loads((folder / "metrics.json").read_text())["models"]
    for name, metrics in results.items():
        summary = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in metrics.items()
        )
        print(f"{name}: {summary}")
    return results


if __name__ == "__main__":
    main()
