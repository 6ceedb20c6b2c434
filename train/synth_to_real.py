"""Table II: synthetic-to-real transfer on SAMPLE with co-domain augmentations.

    python train/synth_to_real.py --sample /path/to/SAMPLE --output_dir runs/table2

The flags are the fields of `sar_zero123.stages.synth_to_real.SynthToRealConfig`; the stage is
`sar_zero123.stages.synth_to_real.run_synth_to_real` (the classifiers, `table2.json`, `table2.md` and the
run-folder rule are described there). An `--output_dir` that holds a table is refused: `--resume`
continues an unfinished one with the same settings (or returns a finished one), `--restart` moves it aside.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sar_zero123 import cli
from sar_zero123.stages.synth_to_real import SynthToRealConfig

__all__ = ["SynthToRealConfig", "main"]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Builds Table II; returns the dict written to `table2.json`."""
    return cli.synth_to_real(argv)


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    raise SystemExit(cli.console.synth_to_real())
