"""``python -m sar_zero123.augmentation_benefit``: every field of :class:`AugmentationBenefitConfig` as a
flag (its comment the help), ``--quick`` for the reduced run; prints the arms' table."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import torch

from sar_zero123.config import field_comments

from .arms import AugmentationBenefit
from .config import QUICK, VIEW_FILTERS, AugmentationBenefitConfig
from .gains import format_table

#: The command's one-line description (its --help).
DESCRIPTION = "Do generated views help a classifier that has few real views?"


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Parses the flags, runs every selected arm into ``--out`` and prints the table; returns the summary."""
    parser = argparse.ArgumentParser(
        prog="python -m sar_zero123.augmentation_benefit", description=DESCRIPTION
    )
    defaults = AugmentationBenefitConfig()
    comments = field_comments(AugmentationBenefitConfig)  # each field's comment in the source, as its help
    for name, value in asdict(defaults).items():
        flag, words = f"--{name}", {"default": value, "help": comments.get(name)}
        if isinstance(value, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, **words)
        elif name == "seeds":
            parser.add_argument(flag, nargs="+", type=int, **words)
        elif name == "view_filters":
            parser.add_argument(flag, nargs="*", choices=VIEW_FILTERS, **words)
        elif isinstance(value, list):  # no value: no such arms
            parser.add_argument(flag, nargs="*", type=int, **words)
        elif name in ("rehearsal_data", "eoc1_data", "unseen_class"):
            parser.add_argument(flag, type=lambda s: None if s.lower() == "none" else s, **words)
        elif name in ("strength", "heading_guidance", "depression_guidance"):
            parser.add_argument(flag, type=lambda s: None if s.lower() == "none" else float(s), **words)
        else:
            parser.add_argument(flag, type=type(value), **words)
    parser.add_argument("--quick", action="store_true", help=f"the reduced run: {QUICK}")
    args = vars(parser.parse_args(argv))
    if args.pop("quick"):
        args.update(QUICK)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(max(torch.get_num_threads(), 1))
    summary = AugmentationBenefit(AugmentationBenefitConfig(**args)).run()
    print(format_table(summary))
    return summary


if __name__ == "__main__":
    main()
