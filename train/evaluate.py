"""Evaluate novel-view pipelines with the paper's protocol (Table III, Table IV, Fig. 7/8, Fig. 12, speed).

    python train/evaluate.py --pipeline runs/pfm0/pipeline --pipeline runs/pfm4/pipeline \\
        --evaluators runs/evaluators --data /path/to/mstar --protocol ood-T72 --n 1000 \\
        --num-inference-steps 50 --guidance-scale 3.0 --seed 0 --output_dir runs/eval

The flags are the fields of `sar_zero123.stages.evaluate.EvaluateConfig`; the stage is
`sar_zero123.stages.evaluate.run_evaluate` (the protocol, the outputs and the run-folder rule are described
there). An `--output_dir` that holds a run is refused: `--resume` returns a finished run with the same
settings (or redoes an unfinished one), `--restart` moves the old run aside.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sar_zero123 import cli
from sar_zero123.model.sampler import SCHEDULERS

__all__ = ["SCHEDULERS", "main"]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Runs the evaluation; returns `{"table3": ..., "speed_error": [...]}` as written to disk."""
    return cli.evaluate(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.evaluate())
