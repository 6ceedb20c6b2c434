"""SimCLR pretraining of the SAR encoder with co-domain augmentations (paper Sec. III, Table I).

    accelerate launch train/pretrain_simclr.py --output_dir runs/simclr            # simulator data
    accelerate launch train/pretrain_simclr.py --data /path/to/mstar --protocol extended \\
        --output_dir runs/simclr --resume_from_checkpoint latest

The flags are the fields of :class:`sar_zero123.stages.PretrainSimCLRConfig` (defaults: the paper's);
the stage is :func:`sar_zero123.stages.run_simclr`. A folder that already holds a run is continued only
with ``--resume_from_checkpoint latest`` and started over only with ``--restart``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sar_zero123 import cli
from sar_zero123.stages.simclr import PretrainSimCLRConfig, select_chips

__all__ = ["PretrainSimCLRConfig", "main", "select_chips"]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Runs SimCLR pretraining; returns the metrics written to `metrics.json`."""
    return cli.simclr(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.simclr())
