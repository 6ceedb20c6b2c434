"""Real MSTAR on one GPU: lambda = 0 against lambda = 4, at a scale the CPU cannot reach (docs/usage/gpus.md).

    # here, once: the chips the recipe reads, as small lossless files that fit a device call's 64 MiB
    python benchmarks/gpu_mstar_pfm.py crops --data ../shared/data/mstar --out .gpu/mstar64
    # on the GPU (benchmarks/gpu_mstar_session.sh installs the wheels first)
    python3 benchmarks/gpu_mstar_pfm.py run --data .gpu/mstar64 --out OUT --work /tmp/work \\
        --budget_minutes 9 --set finetune.train_batch_size=256 shared.mixed_precision=bf16

``run`` is the quickstart's chain (``--recipe mstar-prior --protocol ood-T72``), every stage's config as the
quickstart plans it, fitted into one device call (:func:`~sar_zero123.stages.budget.with_budget`): SimCLR
stops at ``--simclr_minutes``; the fine-tunes share what is left of ``--budget_minutes`` equally, with
``--eval_reserve_minutes`` kept for Table III (no speed sweep). ``OUT/results.json`` gathers each stage's
seconds, steps and metrics and every Table III row; ``OUT/table3.md`` is the evaluation's table.

``crops`` writes each chip as the exact centre crop the stages read
(:func:`~sar_zero123.data.crops.write_crops`): a working copy of licensed data; keep it in a git-ignored
folder and delete it after the call.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from _common import script_parser

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data.crops import write_crops
from sar_zero123.stages.budget import budgeted_plans, with_budget
from sar_zero123.stages.finetune import FinetuneConfig
from sar_zero123.stages.presets import RECIPES, QuickstartConfig
from sar_zero123.stages.quickstart import StagePlan

logger = logging.getLogger("gpu_mstar_pfm")


def _stage_result(plan: StagePlan) -> dict[str, Any]:
    """What a finished stage reports: a fine-tune's steps, the evaluators' and SimCLR's metrics."""
    folder = plan.folder
    result: dict[str, Any] = {}
    for name in ("metrics.json", "train_state.json"):
        if (folder / name).is_file():
            result[name.removesuffix(".json")] = json.loads((folder / name).read_text())
    return result


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Runs the stages under ``args.budget_minutes``; writes ``results.json`` (after every stage) and
    ``table3.md`` to ``args.out``."""
    start = time.monotonic()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plans = budgeted_plans(QuickstartConfig(output_dir=args.work, recipe=args.recipe, data=args.data,
                                            protocol=args.protocol, lambdas=args.lambdas, seed=args.seed,
                                            set=args.set))  # fmt: skip
    trainings = [plan for plan in plans if isinstance(plan.config, FinetuneConfig)]
    results: dict[str, Any] = {"argv": sys.argv[1:], "recipe": args.recipe, "set": args.set,
                               "budget_minutes": args.budget_minutes, "stages": {}}  # fmt: skip
    for plan in plans:
        minutes = None
        if isinstance(plan.config, FinetuneConfig):  # an equal share of what is left, the evaluation kept
            left = args.budget_minutes - (time.monotonic() - start) / 60.0 - args.eval_reserve_minutes
            remaining = sum(1 for p in trainings if p.name not in results["stages"])
            minutes = left / remaining
            if minutes <= 0.05:
                raise RuntimeError(f"stage {plan.name}: {left:.2f} min left for {remaining} fine-tunes")
        plan = with_budget(plan, minutes, args.simclr_minutes, args.eval_batch_size)
        begin = time.monotonic()
        logger.info("stage %s%s", plan.name, "" if minutes is None else f" ({minutes:.2f} min)")
        plan.run(plan.config)
        results["stages"][plan.name] = {"seconds": time.monotonic() - begin, "minutes_given": minutes,
                                        **_stage_result(plan)}  # fmt: skip
        write_json_atomic(results, out / "results.json")
    evaluation = plans[-1].folder
    results["table3"] = json.loads((evaluation / "table3.json").read_text())
    results["seconds"] = time.monotonic() - start
    write_json_atomic(results, out / "results.json")
    (out / "table3.md").write_text((evaluation / "table3.md").read_text())
    return results


def build_parser() -> argparse.ArgumentParser:
    """The two commands, ``crops`` and ``run``, and their flags."""
    parser = script_parser(__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    crops = commands.add_parser("crops", help="write the chips as the centre crops the preset reads")
    crops.add_argument("--data", required=True, help="chip folder with index.csv (e.g. ../shared/data/mstar)")
    crops.add_argument("--out", required=True, help="new, git-ignored folder")
    crops.add_argument("--image_size", type=int, default=64)
    crops.add_argument("--every", type=int, default=1, help="keep every K-th chip in azimuth (default: all)")
    call = commands.add_parser("run", help="the quickstart's stages under one time budget")
    call.add_argument("--data", required=True, help="chip folder (the crops above)")
    call.add_argument("--out", required=True, help="results.json and table3.md")
    call.add_argument("--work", required=True, help="run folders of the stages")
    call.add_argument("--recipe", default="mstar-prior", choices=sorted(RECIPES))
    call.add_argument("--protocol", default="ood-T72")
    call.add_argument("--lambdas", nargs="+", type=float, default=[0.0, 4.0])
    call.add_argument("--set", nargs="*", default=[], help="recipe fields, as train/quickstart.py's")
    call.add_argument("--budget_minutes", type=float, default=9.0)
    call.add_argument("--simclr_minutes", type=float, default=1.5)
    call.add_argument("--eval_reserve_minutes", type=float, default=1.0)
    call.add_argument("--eval_batch_size", type=int, default=100)
    call.add_argument("--seed", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    if args.command == "crops":
        print(write_crops(args.data, args.out, args.image_size, args.every))
        return
    for name in ("budget_minutes", "simclr_minutes", "eval_reserve_minutes"):
        if not getattr(args, name) > 0:
            parser.error(f"--{name} must be > 0")
    print(json.dumps({k: v for k, v in run(args).items() if k != "table3"}, indent=1))


if __name__ == "__main__":
    main()
