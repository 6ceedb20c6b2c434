"""``python -m sar_zero123.sim --out DIR``: simulate a dataset folder (and a contact sheet)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

from sar_zero123.sim.dataset import simulate_dataset
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
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command; returns the exit status."""
    args = build_parser().parse_args(argv)
    start = time.perf_counter()
    out = simulate_dataset(
        args.out,
        classes=args.classes,
        instances=args.instances,
        azimuth_step_deg=args.azimuth_step,
        depressions_deg=tuple(args.depressions),
        size=args.size,
        seed=args.seed,
        azimuth_jitter_deg=args.azimuth_jitter,
        normalization=args.normalization,
    )
    with open(out / "index.csv") as f:
        n_chips = sum(1 for _ in f) - 1
    print(f"wrote {n_chips} chips and {out / 'index.csv'} in {time.perf_counter() - start:.1f} s")
    if args.contact_sheet:
        from sar_zero123.sim.contact_sheet import contact_sheet

        sheet = contact_sheet(
            out / "contact_sheet.png",
            classes=args.classes,
            depression_deg=args.depressions[-1],
            size=args.size,
            seed=args.seed,
            real_root=args.real_root,
        )
        print(f"wrote {sheet}")
    if args.procedural_sheet > 0:
        from sar_zero123.sim.contact_sheet import procedural_contact_sheet

        sheet = procedural_contact_sheet(out / "procedural_sheet.png", seeds=range(args.procedural_sheet))
        print(f"wrote {sheet}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
