"""Fine-tune a zero-1-to-3 style SAR novel-view model with Projected Feature Matching (Eq. 21).

    accelerate launch train/finetune_pfm.py --encoder runs/simclr/encoder --pfm_weight 4 \\
        [--config finetune.yaml] [--data /path/to/mstar --protocol extended] [--flag value ...]

The flags are the fields of :class:`sar_zero123.stages.FinetuneConfig`; the stage is
:func:`sar_zero123.stages.run_finetune`. A folder that already holds a run is continued only with
``--resume_from_checkpoint latest`` and started over only with ``--restart`` (the old run is moved aside).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sar_zero123 import cli
from sar_zero123.stages.finetune import FinetuneConfig

__all__ = ["FinetuneConfig", "main"]


def main(argv: Sequence[str] | None = None) -> Path:
    """Run a fine-tune; returns the run folder."""
    return cli.finetune(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.finetune())
