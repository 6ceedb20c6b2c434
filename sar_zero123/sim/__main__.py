"""``python -m sar_zero123.sim --out DIR``: simulate a dataset folder (and a contact sheet)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

from sar_zero123.sim.targets import TARGET_CLASSES


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = argparse.ArgumentParser(
        prog="python -m sar_zero123.sim",
        description="Simulate SAR target chips: writes DIR/index.csv and DIR/chips/<dep>deg/<CLASS>/*.npy.",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--classes", nargs="+", default=None, help=f"classes (default all: {' '.join(TARGET_CLASSES)})"
    )
    p.add_argument("--instances", type=int, default=2, help="instances (serials) per class")
    p.add_argument("--azimuth-step", type=float, default=5.0, help="azimuth grid step in degrees")
    p.add_argument(
        "--azimuth-jitter", type=float, default=0.0, help="seeded per-chip azimuth jitter width (deg)"
    )
    p.add_argument(
        "--depressions", type=float, nargs="+", default=[15.0, 17.0], help="depression angles (deg)"
    )
    p.add_argument("--size", type=int, default=128, help="chip size in pixels")
    p.add_argument("--seed", type=int, default=0, help="dataset seed")
    p.add_argument(
        "--normalization",
        choices=("peak", "calibrated"),
        default="peak",
        help="per-chip peak or fixed calibration",
    )
    p.add_argument("--contact-sheet", action="store_true", help="also write DIR/contact_sheet.png")
    p.add_argument("--real-root", default=None, help="MSTAR image folder to show beside the simulated chips")
    p.add_argument(
        "--procedural-sheet",
        type=int,
        default=0,
        metavar="N",
        help="also write DIR/procedural_sheet.png of procedural vehicles 0..N-1 at 17 and 45 deg",
    )
    p.add_argument(
        "--resume", action="store_true", help="redo an unfinished dataset in DIR with the same settings"
    )
    p.add_argument(
        "--restart", action="store_true", help="move an existing DIR aside (never deleted) and simulate anew"
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command; returns the exit status."""
    # imported here: the simulator package itself imports nothing from the run plumbing
    from sar_zero123.stages.simulate import SimulateConfig, run_simulate

    args = build_parser().parse_args(argv)
    start = time.perf_counter()
    config = SimulateConfig(
        out=args.out,
        classes=list(args.classes or TARGET_CLASSES),
        instances=args.instances,
        azimuth_step_deg=args.azimuth_step,
        azimuth_jitter_deg=args.azimuth_jitter,
        depressions_deg=list(args.depressions),
        size=args.size,
        seed=args.seed,
        normalization=args.normalization,
        contact_sheet=args.contact_sheet,
        real_root=args.real_root,
        procedural_sheet=args.procedural_sheet,
        resume=args.resume,
        restart=args.restart,
    )
    out = run_simulate(config)
    with open(out / "index.csv") as f:
        n_chips = sum(1 for _ in f) - 1
    print(f"{out / 'index.csv'}: {n_chips} chips ({time.perf_counter() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
