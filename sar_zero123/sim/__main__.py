"""``python -m sar_zero123.sim --out DIR`` (or ``sar-zero123-simulate``): simulate a dataset folder (and a
contact sheet).

The flags are the fields of :class:`sar_zero123.stages.simulate.SimulateConfig` (``--azimuth_step_deg``,
``--azimuth-step-deg``); the older ``--azimuth-step``, ``--azimuth-jitter`` and ``--depressions`` are still
accepted.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

#: Flags of the hand-written parser this command had before its flags became SimulateConfig's fields.
OLDER_FLAGS = {
    "--azimuth-step": "azimuth_step_deg",
    "--azimuth_step": "azimuth_step_deg",
    "--azimuth-jitter": "azimuth_jitter_deg",
    "--azimuth_jitter": "azimuth_jitter_deg",
    "--depressions": "depressions_deg",
}


def main(argv: Sequence[str] | None = None, prog: str = "python -m sar_zero123.sim") -> int:
    """Run the command (``prog`` names it in usage lines); returns the exit status."""
    # imported here: the simulator package itself imports nothing from the run plumbing
    from sar_zero123.config import parse_config
    from sar_zero123.stages.simulate import SimulateConfig, run_simulate

    start = time.perf_counter()
    config = parse_config(SimulateConfig, argv, prog=prog, aliases=OLDER_FLAGS)
    out = run_simulate(config)
    with open(out / "index.csv") as f:
        n_chips = sum(1 for _ in f) - 1
    print(f"{out / 'index.csv'}: {n_chips} chips ({time.perf_counter() - start:.1f} s)")
    print(out)  # the output folder, the last line on stdout as for every command
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
