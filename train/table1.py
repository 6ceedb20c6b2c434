"""Table I: one SimCLR encoder per augmentation preset, scored by four frozen-feature probes.

    python train/table1.py --data /path/to/mstar --protocol extended --epochs 500
    python train/table1.py --data /path/to/mstar --presets simclr-full speckle+monotonic \\
        --encoders runs/simclr-full runs/speckle   # probe existing encoders, one per preset

The flags are the fields of `sar_zero123.stages.table1.Table1Config`; the stage is
`sar_zero123.stages.table1.run_table1` (the SimCLR runs, probes, `table1.json`, `table1.md`, `tsne.png` and
the run-folder rule are described there). An `--output_dir` that holds a table is refused: `--resume`
continues an unfinished one with the same settings (or returns a finished one), `--restart` moves it aside.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sar_zero123 import cli
from sar_zero123.stages.table1 import Table1Config, format_markdown, plot_tsne

__all__ = ["Table1Config", "format_markdown", "main", "plot_tsne"]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Builds Table I; returns the dict written to `table1.json`."""
    return cli.table1(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.table1())
