"""End-to-end run on the built-in simulator (or a chip folder): the README's main command.

    python train/quickstart.py --output_dir runs/quickstart
    python train/quickstart.py --recipe mstar --data /path/to/mstar --protocol ood-T72 --output_dir runs/mstar

With the default recipe, on a 2-core CPU, it

1. simulates a small MSTAR-like dataset (`sar_zero123.sim`), one class held out (MSTAR-OOD style), unless
   `--data` names real chips (with `--protocol extended` or `ood-<CLASS>`), and views of the same vehicles at
   `shared.depression_targets_deg` for depression requests,
2. pretrains a small SimCLR encoder with the Speckle Rayleigh + Monotonic augmentation (`pretrain_simclr.py`),
3. fine-tunes the bundled multi-view prior (`shared.prior`, `sar-zero123/sim-prior-rotated`) with each PFM
   weight of `--lambdas` (default 0 and 4) from the same prior, as the paper fine-tunes one zero-1-to-3
   checkpoint (`finetune_pfm.py`); recipes without a prior first train a VAE (`train_vae.py`) and a base
   model from scratch,
4. trains the evaluator classifier, azimuth regressor and depression regressor (plus a probe on the SimCLR
   encoder) on all classes,
5. evaluates the fine-tuned pipelines (Table III, Table IV, views, lambda plot, speed against error, and a
   second Table III of depression requests from 17 deg inputs: `evaluate.py`),
6. writes `report.md` with the tables and figures.

Every stage is a library call (`sar_zero123.stages`) with a typed config, all built and checked before the
first stage runs. The folder is a run folder: `--resume` continues it (an interrupted stage resumes from
its newest checkpoint, `shared.checkpointing_steps`; a finished one is kept; more `--lambdas` train only
the new fine-tunes, then evaluate them all on the same pairs), `--restart` moves it aside, and any other
setting in a used folder is refused, naming each difference. Recipes (`--recipe`, sections of stage fields
merged onto each stage config's defaults; `--set SECTION.FIELD=VALUE`):
`default` (the prior), `scratch` (the default trained from scratch), `long` (from scratch, longer), `mstar`
(real chips) and `smoke` (tiny settings in seconds, for tests); their measured times are in
docs/results/. The numbers are CPU quick-run numbers, far from the paper's setting (20,000 iterations from
an Objaverse checkpoint on real MSTAR at 128 px).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sar_zero123 import cli
from sar_zero123.stages.presets import DEFAULT_RECIPE, RECIPES, QuickstartConfig, Recipe, apply_overrides
from sar_zero123.stages.quickstart import plan_stages

__all__ = [
    "DEFAULT_RECIPE", "RECIPES", "QuickstartConfig", "Recipe", "apply_overrides", "main", "plan_stages",
]  # fmt: skip


def main(argv: Sequence[str] | None = None) -> Path:
    """Runs the whole chain; returns the path of `report.md`."""
    return cli.quickstart(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.quickstart())
