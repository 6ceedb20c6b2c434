"""Table II: synthetic-to-real transfer on SAMPLE with co-domain augmentations.

    python train/synth_to_real.py --sample /path/to/SAMPLE --output_dir runs/table2

The flags are the fields of `sar_zero123.stages.synth_to_real.SynthToRealConfig`; the stage is
`sar_zero123.stages.synth_to_real.run_synth_to_real` (the classifiers, `table2.json`, `table2.md` and the
run-folder rule are described there). An `--output_dir` that holds a table is refused: `--resume`
continues an unfinished one with the same settings (or returns a finished one), `--restart` moves it aside.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from typing import Any

from sar_zero123.config import parse_config
from sar_zero123.stages.synth_to_real import SynthToRealConfig, run_synth_to_real

__all__ = ["SynthToRealConfig", "main"]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Builds Table II; returns the dict written to `table2.json`."""
    config = parse_config(SynthToRealConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return json.loads((run_synth_to_real(config) / "table2.json").read_text())


if __name__ == "__main__":
    main()
