"""Train and score multi-view priors on one GPU inside a fixed time budget (docs/usage/gpus.md).

    python benchmarks/gpu_prior.py --out OUT --work WORK --evaluators EVAL/evaluators \\
        --arms rotated_input rotated_input@micro global --budget_minutes 8.5

1. a procedural corpus of as many vehicles as ``--corpus_minutes`` allows at a pilot's render rate
   (:func:`~sar_zero123.stages.budget.affordable_vehicles`), and the eight named vehicles' evaluation chips
   (never in any corpus) unless ``--eval_data`` names them;
2. one prior per arm (:func:`~sar_zero123.stages.budget.arm_config`): the same corpus, VAE (the bundled
   prior's), batch and minutes (what is left of ``--budget_minutes`` after the corpus and
   ``--eval_reserve_minutes``, split evenly); an arm differs in its condition input and, as
   ``<input>@<size>``, its size; each comes back as ``OUT/<arm>.tar.part*``
   (:func:`~sar_zero123.stages.budget.pack_pipeline`; restore with ``cat OUT/<arm>.tar.part* | tar x`` and
   a copy of ``sar_zero123/pretrained/sim_prior_rotated/vae``);
3. Table III of every arm beside ``--baselines`` on the same pairs: azimuth requests 17 -> 17 deg (n =
   ``--n``) and depression requests 17 -> 10/30/45 deg (n = 1.5 ``--n``).

``OUT/results.json`` is rewritten after each stage: a run stopped early still reports what it finished.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from _common import gpu_device, script_parser
from diffusers import UNet2DConditionModel

from sar_zero123 import SIM_PRIOR_ROTATED, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.sim.corpus import write_prior_corpus
from sar_zero123.stages.budget import affordable_vehicles, arm_config, arm_label, pack_pipeline, parse_arm
from sar_zero123.stages.evaluate import EvaluateConfig, load_evaluation, run_evaluate
from sar_zero123.stages.finetune import run_finetune

logger = logging.getLogger(__name__)

#: The named vehicles' evaluation chips (never in any corpus).
EVAL_CLASSES = ("TANK", "APC", "TRUCK", "DOZER", "SPG", "RADAR", "AAGUN", "SCOUT")
EVAL_DEPRESSIONS = ("10", "15", "17", "30", "45")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = script_parser(__doc__)
    parser.add_argument("--out", required=True, help="results.json and the pipelines (tar parts)")
    parser.add_argument("--work", required=True, help="corpus, run folders and evaluations")
    parser.add_argument("--evaluators", required=True, help="train_evaluators.py folder (named vehicles)")
    parser.add_argument("--eval_data", default=None, help="the named vehicles' chips; None renders them")
    parser.add_argument("--arms", nargs="+", default=["rotated_input", "rotated_input@micro"],
                        help="global, rotated_input, each optionally @<size>")  # fmt: skip
    parser.add_argument("--budget_minutes", type=float, default=8.5, help="wall time of the whole script")
    parser.add_argument("--eval_reserve_minutes", type=float, default=1.5, help="kept for the evaluations")
    parser.add_argument("--setup_minutes", type=float, default=0.6, help="each arm's set-up and export")
    parser.add_argument("--num_vehicles", type=int, default=6000, help="procedural vehicles in the corpus")
    parser.add_argument("--views_per_vehicle", type=int, default=12, help="chips per vehicle")
    parser.add_argument("--corpus_minutes", type=float, default=1.0, help="most the corpus may take")
    parser.add_argument("--corpus_workers", type=int, default=16, help="processes rendering the corpus")
    parser.add_argument("--size", default="medium", help="build_sar_zero123 size of every arm")
    parser.add_argument("--train_batch_size", type=int, default=1024, help="pairs per step")
    parser.add_argument("--learning_rate", type=float, default=8e-4, help="AdamW peak, after the warm-up")
    parser.add_argument("--lr_warmup_steps", type=int, default=200, help="linear warm-up steps")
    parser.add_argument("--max_train_steps", type=int, default=100000, help="cap (the clock stops first)")
    parser.add_argument("--lr_scheduler", default="constant_with_warmup",
                        help="diffusers schedule after the warm-up; a decaying one (cosine) reaches 0 at "
                        "--max_train_steps: set those to the steps the budget fits")  # fmt: skip
    parser.add_argument("--mixed_precision", default="bf16", choices=["no", "fp16", "bf16"])
    parser.add_argument("--num_workers", type=int, default=4, help="DataLoader workers (no device cache)")
    parser.add_argument("--cache_on_device", action=argparse.BooleanOptionalAction, default=True,
                        help="latents on the GPU, batches drawn there (FinetuneConfig.cache_on_device)")
    parser.add_argument("--n", type=int, default=256, help="azimuth pairs (depression pairs: 1.5 n)")
    parser.add_argument("--eval_batch_size", type=int, default=128, help="pairs per sampling call")
    parser.add_argument("--baselines", nargs="*", default=[SIM_PRIOR_ROTATED],
                        help="bundled priors (names or folders) scored beside the arms; none: only the arms")
    parser.add_argument("--compile", default=None, choices=["default", "reduce-overhead", "max-autotune"],
                        help="compile the trained modules with torch.compile (inductor) in this mode, as "
                        "`accelerate launch --dynamo_backend inductor --dynamo_mode MODE` does")
    parser.add_argument("--init", default=None,
                        help="start every arm from this pipeline's weights (a bundled name or a folder) "
                        "instead of from scratch; its condition input must be the arm's")  # fmt: skip
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


class Results:
    """``results.json`` in ``out``, rewritten atomically after every change."""

    def __init__(self, path: Path, settings: dict[str, Any]) -> None:
        self.path, self.data = path, {"settings": settings, "device": gpu_device(), "stages": {}}
        write_json_atomic(self.data, self.path)

    def stage(self, name: str, **facts: Any) -> None:
        self.data["stages"].setdefault(name, {}).update(facts)
        write_json_atomic(self.data, self.path)


def render_eval_data(folder: Path, seed: int) -> Path:
    """The named vehicles at every 5 deg of azimuth and five depressions, 64 px."""
    if (folder / "index.csv").is_file():
        return folder
    command = [sys.executable, "train/simulate.py", "--out", str(folder), "--classes", *EVAL_CLASSES,
               "--instances", "1", "--azimuth_step_deg", "5", "--depressions_deg", *EVAL_DEPRESSIONS,
               "--size", "64", "--seed", str(seed)]  # fmt: skip
    subprocess.run(command, check=True)
    return folder


def train_arm(args: argparse.Namespace, arm: str, corpus: Path, vae: Path, minutes: float) -> Path:
    """One prior on ``corpus`` for ``minutes`` of training steps; returns its pipeline folder."""
    prior = {"output_dir": str(Path(args.work) / arm_label(arm)), "corpus": str(corpus), "vae": str(vae),
             "train_batch_size": args.train_batch_size, "base_steps": args.max_train_steps,
             "learning_rate": args.learning_rate, "mixed_precision": args.mixed_precision, "seed": args.seed}
    config = arm_config(arm, minutes, size=args.size, prior=prior, init=args.init,
                        lr_scheduler=args.lr_scheduler, lr_warmup_steps=args.lr_warmup_steps,
                        num_workers=args.num_workers, cache_on_device=args.cache_on_device)  # fmt: skip
    run_finetune(config)
    return Path(config.output_dir) / "pipeline"


def evaluate(
    args: argparse.Namespace, name: str, pipelines: dict[str, Path], data: Path, **pairs: Any
) -> dict[str, Any]:
    """Table III of ``pipelines`` on one pair set (the floor and the ceilings come with it)."""
    config = EvaluateConfig(
        pipeline=[str(path) for path in pipelines.values()], pipeline_names=list(pipelines),
        evaluators=args.evaluators, data=str(data), protocol="extended", input_depression_deg=17.0,
        num_inference_steps=20, eval_batch_size=args.eval_batch_size,
        output_dir=str(Path(args.work) / f"eval_{name}"), seed=args.seed, **pairs,
    )  # fmt: skip
    return load_evaluation(run_evaluate(config))["table3"]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    for arm in args.arms:  # refused before any work
        parse_arm(arm, args.size)
    begin = time.monotonic()
    out, work = Path(args.out), Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    results = Results(out / "results.json", vars(args))
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True

    # 1. corpus (as many vehicles as --corpus_minutes allows, at a pilot's rate) and evaluation chips
    start = time.monotonic()
    num_vehicles = affordable_vehicles(work, args.num_vehicles, args.views_per_vehicle, args.corpus_minutes,
                                       args.corpus_workers, args.seed)
    corpus = write_prior_corpus(
        work / "corpus", num_vehicles=num_vehicles, views_per_vehicle=args.views_per_vehicle,
        seed=args.seed, num_workers=args.corpus_workers, progress=False,
    )  # fmt: skip
    chips = num_vehicles * args.views_per_vehicle
    results.stage("corpus", seconds=time.monotonic() - start, vehicles=num_vehicles, chips=chips)
    start = time.monotonic()
    data = Path(args.eval_data) if args.eval_data else render_eval_data(work / "eval_data", args.seed)
    results.stage("eval_data", seconds=time.monotonic() - start, folder=str(data))

    # 2. the arms, each with the same share of what is left
    elapsed = (time.monotonic() - begin) / 60.0
    per_arm = (args.budget_minutes - elapsed - args.eval_reserve_minutes) / len(args.arms)
    per_arm -= args.setup_minutes  # each arm's set-up (chips read, latents cached) and export
    if per_arm <= 0.2:
        raise ValueError(f"budget_minutes {args.budget_minutes}: no training time is left after the corpus")
    vae = resolve_pretrained(SIM_PRIOR_ROTATED) / "vae"
    if args.compile:  # accelerate's own switch: every Accelerator made from here on compiles what it prepares
        os.environ.update(ACCELERATE_DYNAMO_BACKEND="inductor", ACCELERATE_DYNAMO_MODE=args.compile)
        # Static shapes. With mixed precision, accelerate wraps every prepared module's forward in one shared
        # function, so dynamo meets the pose projection and the UNet in the same frame; its automatic dynamic
        # shapes then recompiled the UNet symbolically for minutes and crashed (one H100, 2026-11-27).
        os.environ["ACCELERATE_DYNAMO_USE_DYNAMIC"] = "False"
    pipelines: dict[str, Path] = {}
    for arm in args.arms:
        start = time.monotonic()
        try:
            pipelines[arm] = train_arm(args, arm, corpus, vae, per_arm)
        except Exception:  # one arm's failure must not cost the other arms' results
            results.stage(f"train_{arm}", error=traceback.format_exc())
            continue
        state = json.loads((pipelines[arm].parent / "train_state.json").read_text())
        steps = int(state["global_step"])
        unet = UNet2DConditionModel.from_pretrained(pipelines[arm] / "unet")
        results.stage(f"train_{arm}", seconds=time.monotonic() - start, train_minutes=per_arm, steps=steps,
                      pairs=steps * args.train_batch_size, pairs_per_second=steps * args.train_batch_size /
                      (60 * per_arm), unet_parameters=sum(p.numel() for p in unet.parameters()))  # fmt: skip
        try:  # the weights come back even if a later stage runs out of time
            results.stage(f"train_{arm}", parts=pack_pipeline(pipelines[arm], out, arm_label(arm)))
        except Exception:
            results.stage(f"train_{arm}", pack_error=traceback.format_exc())

    # 3. Table III of every arm beside the bundled prior, same pairs
    rows = {Path(name).name: resolve_pretrained(name) for name in args.baselines} | pipelines
    for name, pairs in (
        ("azimuth", {"target_depressions_deg": [17.0], "n": args.n}),
        # a corpus of uniform draws may miss the range's very ends by a fraction of a degree
        ("depression", {"target_depressions_deg": [10.0, 30.0, 45.0], "same_depression": False,
                        "n": args.n * 3 // 2, "outside_trained_range": True}),
    ):  # fmt: skip
        start = time.monotonic()
        try:
            table = evaluate(args, name, rows, data, **pairs)
            results.stage(f"eval_{name}", seconds=time.monotonic() - start, table3=table)
        except Exception:
            results.stage(f"eval_{name}", error=traceback.format_exc())

    results.stage("total", seconds=time.monotonic() - begin)
    return results.data


if __name__ == "__main__":
    main()
