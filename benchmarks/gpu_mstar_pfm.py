"""Issue 36 on one GPU: real MSTAR, lambda = 0 against lambda = 4, at a scale the CPU cannot reach.

    # here, once: the chips the preset reads, as small lossless files that fit a device call's 64 MiB
    python benchmarks/gpu_mstar_pfm.py crops --data ../shared/data/mstar --out .gpu/mstar64
    # on the GPU (benchmarks/gpu_mstar_session.sh installs the wheels first)
    python3 benchmarks/gpu_mstar_pfm.py run --data .gpu/mstar64 --out OUT --work /tmp/work \\
        --budget_minutes 9 --set finetune.train_batch_size=256 shared.mixed_precision=bf16

``run`` is the quickstart's chain (``train/quickstart.py --recipe mstar-prior --protocol ood-T72``): every
stage's config exactly as the quickstart plans it (:func:`sar_zero123.stages.quickstart.plan_stages`, with
``--recipe`` and ``--set`` applied), then four changes that fit it into one call of the device:

* SimCLR stops at ``--simclr_minutes`` (``max_train_minutes``) if its steps take longer;
* the fine-tunes (and a preset's base model) share what is left of ``--budget_minutes`` equally
  (``max_train_minutes``, their steps unbounded), after the evaluators, with ``--eval_reserve_minutes``
  kept for Table III; their cached latents stay on the device;
* Table III without the speed sweep, ``--eval_batch_size`` pairs per call;
* the stages run in the order SimCLR, (VAE,) evaluators, (base model,) fine-tunes, evaluation.

``OUT/results.json`` gathers each stage's seconds, the steps each fine-tune reached, the evaluators' test
metrics and every Table III row; ``OUT/table3.md`` is the evaluation's table. The comparison is within one
call: both lambdas get the same data, prior, encoder, evaluators, pairs and minutes.

``crops`` writes the centre crop each chip is read as (``image_size`` px, the crop
:func:`sar_zero123.data.center_crop_resize` takes at ``crop_size=None``) as an 8-bit PNG, with an
``index.csv`` of the same records: the stages read the same pixels as from the original folder. The crops
are a working copy of licensed data: keep them in a git-ignored folder, carry them to the device, delete
them after the call, and never commit them or weights trained on them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data.datasets import load_chip
from sar_zero123.data.index import load_index, write_index
from sar_zero123.stages.evaluate import EvaluateConfig
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig
from sar_zero123.stages.finetune import FinetuneConfig
from sar_zero123.stages.presets import RECIPES, QuickstartConfig
from sar_zero123.stages.quickstart import StagePlan, plan_stages
from sar_zero123.stages.simclr import PretrainSimCLRConfig
from sar_zero123.stages.vae import TrainVAEConfig

logger = logging.getLogger("gpu_mstar_pfm")

#: A fine-tune's steps are bounded by its minutes, not by a count.
UNBOUNDED_STEPS = 10_000_000


def write_crops(data: str | Path, out: str | Path, image_size: int = 64, every: int = 1) -> Path:
    """Each chip of ``data`` as the ``image_size`` px centre crop the stages read, an 8-bit PNG in ``out``;
    with ``every`` > 1 only every ``every``-th chip of each class, serial and depression in azimuth order
    (a sparser azimuth grid, for a call whose working tree would not fit otherwise).

    Raises:
        FileNotFoundError: If ``data`` has no chip index.
        ValueError: If ``out`` already holds files, ``every`` < 1, or a chip is not 8-bit (its crop would
            not be exact).
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"out: {out} already holds files; give an empty or new folder")
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    records = load_index(data)
    if every > 1:
        groups: dict[tuple, list] = {}
        for record in records:
            groups.setdefault((record.target_class, record.serial, record.depression_deg), []).append(record)
        kept = set()
        for group in groups.values():
            kept.update(id(record) for record in sorted(group, key=lambda r: r.azimuth_deg)[::every])
        records = [record for record in records if id(record) in kept]
    (out / "chips").mkdir(parents=True, exist_ok=True)
    cropped = []
    for number, record in enumerate(records):
        magnitude = load_chip(record.path, image_size)
        pixels = np.rint(magnitude * 255.0)
        if np.abs(pixels - magnitude * 255.0).max() > 1e-3:
            raise ValueError(f"{record.path}: not an 8-bit chip; its crop cannot be stored exactly as 8 bits")
        path = out / "chips" / f"{number:06d}.png"
        Image.fromarray(pixels.astype(np.uint8)).save(path, optimize=True)
        cropped.append(dataclasses.replace(record, path=path.resolve(), height=image_size, width=image_size))
    return write_index(cropped, out)


def _gpu_plans(args: argparse.Namespace) -> list[StagePlan]:
    """The quickstart's stages for this data and preset, in the order this call runs them."""
    config = QuickstartConfig(
        output_dir=args.work, recipe=args.recipe, data=args.data, protocol=args.protocol,
        lambdas=args.lambdas, seed=args.seed, set=args.set,
    )  # fmt: skip
    plans = {plan.name: plan for plan in plan_stages(config)}
    finetunes = [name for name in plans if name.startswith("finetune ")]
    order = [n for n in ("simclr", "vae", "evaluators", "base model", *finetunes, "evaluate") if n in plans]
    unknown = sorted(set(plans) - set(order))
    if unknown:  # a preset that simulates data or renders a corpus is not this call's
        raise ValueError(f"recipe {args.recipe!r} plans stages this call does not run: {unknown}")
    return [plans[name] for name in order]


def _with_budget(plan: StagePlan, args: argparse.Namespace, minutes: float | None) -> StagePlan:
    """``plan`` with this call's time limit and device settings."""
    config = plan.config
    if isinstance(config, PretrainSimCLRConfig):
        config = dataclasses.replace(config, max_train_minutes=args.simclr_minutes)
    elif isinstance(config, FinetuneConfig):
        if config.lr_scheduler not in ("constant", "constant_with_warmup"):  # set over UNBOUNDED_STEPS
            raise ValueError(f"stage {plan.name}: lr_scheduler {config.lr_scheduler!r} would decay over "
                             f"{UNBOUNDED_STEPS:,} steps; a fine-tune bounded by minutes takes 'constant'")
        config = dataclasses.replace(config, max_train_minutes=minutes, max_train_steps=UNBOUNDED_STEPS,
                                     checkpointing_steps=UNBOUNDED_STEPS, cache_on_device=True)  # fmt: skip
    elif isinstance(config, EvaluateConfig):
        config = dataclasses.replace(config, steps=[], schedulers=[], speed_n=None,
                                     eval_batch_size=args.eval_batch_size)  # fmt: skip
    elif not isinstance(config, TrainEvaluatorsConfig | TrainVAEConfig):
        raise TypeError(f"stage {plan.name}: no budget rule for {type(config).__name__}")
    return dataclasses.replace(plan, config=config)


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
    plans = _gpu_plans(args)
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
        plan = _with_budget(plan, args, minutes)
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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
