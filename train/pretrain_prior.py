"""Pretrain the multi-view SAR prior on procedural simulated vehicles (the package's bundled prior).

    python train/pretrain_prior.py --output_dir runs/prior
    accelerate launch train/pretrain_prior.py --output_dir runs/prior --mixed_precision bf16   # GPUs

The flags are the fields of :class:`sar_zero123.stages.PriorConfig`; the stage is
:func:`sar_zero123.stages.run_prior` (corpus, VAE, UNet, each resumable: a re-run of the same command
continues where it stopped, and more ``--base_steps`` extend the UNet). ``--restart`` moves an earlier run
aside. The pipeline lands in ``output_dir/base/pipeline``; ``docs/results/history/prior.md`` gives the
measured recipe.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sar_zero123 import cli
from sar_zero123.stages.prior import PriorConfig

__all__ = ["PriorConfig", "main"]


def main(argv: Sequence[str] | None = None) -> Path:
    """Run (or resume) the three stages; returns the prior's pipeline folder."""
    return cli.prior(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.prior())
