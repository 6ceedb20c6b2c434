"""Simulate a dataset folder of SAR chips (and a contact sheet) with the built-in simulator.

    python train/simulate.py --out sim_data [--contact_sheet] [--flag value ...]

The flags are the fields of :class:`sar_zero123.stages.simulate.SimulateConfig`; the stage is
:func:`sar_zero123.stages.simulate.run_simulate` (the same as ``sar-zero123-simulate``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sar_zero123 import cli
from sar_zero123.stages.simulate import SimulateConfig

__all__ = ["SimulateConfig", "main"]


def main(argv: Sequence[str] | None = None) -> Path:
    """Simulates the dataset; returns its folder."""
    return cli.simulate(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.simulate())
