"""Train and score multi-view priors on one GPU inside a fixed time budget (issue 35's GPU recipe).

    python benchmarks/gpu_prior.py --out OUT --work WORK --evaluators EVAL/evaluators \\
        --arms rotated_input rotated_input@micro global --budget_minutes 8.5

One process, three stages, every one a library call (the stages of ``sar_zero123.stages``):

1. a fresh procedural corpus (:func:`~sar_zero123.sim.corpus.write_prior_corpus`) rendered by
   ``--corpus_workers`` processes: more vehicles with fewer views each than the bundled prior's corpus, as
   many as ``--corpus_minutes`` allows at the rate a pilot measures;
   and the evaluation chips of the eight named vehicles (never in any corpus), rendered as
   ``docs/results/history/prior.md`` renders them, unless ``--eval_data`` names them;
2. one prior per arm (:func:`~sar_zero123.stages.finetune.run_finetune` through
   :func:`~sar_zero123.stages.prior.prior_base_config`): the same corpus, VAE (the bundled prior's, latents
   cached once), batch and wall-clock budget (``max_train_minutes``); an arm differs only in its
   condition input (``global``: zero-1-to-3's, as the bundled prior; ``rotated_input``: also the input
   latent turned by ``d_az``, ``FinetuneConfig.spatial_pose``) and, when named ``<input>@<size>``, its size
   (``--size`` otherwise; ``@micro`` is the quickstart's size, one that can ship in the package);
3. Table III of every arm beside the bundled priors (``--baselines``), the floor and the ceilings, on the
   same pairs (:func:`~sar_zero123.stages.evaluate.run_evaluate`): azimuth requests 17 -> 17 deg
   (n = ``--n``) and depression requests 17 -> 10/30/45 deg (n = 1.5 ``--n``).

The training time per arm is what is left of ``--budget_minutes`` after the corpus, minus
``--eval_reserve_minutes``, split evenly. ``OUT/results.json`` is rewritten after each stage (a run stopped
early still reports what it finished), and each arm's pipeline comes back as ``OUT/<arm>.tar.part*`` with
its UNet stored in float16 and without its ``vae/`` (the bundled prior's): ``cat OUT/<arm>.tar.part* | tar x``
then copying ``sar_zero123/pretrained/sim_prior/vae`` into the folder restores it (the weights load into
float32). On a machine without ``diffusers``, install its wheel first (docs/usage/gpus.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import shutil
import subprocess
import sys
import tarfile
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from sar_zero123 import SIM_PRIOR, SIM_PRIOR_ROTATED, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.sim.corpus import write_prior_corpus
from sar_zero123.stages.evaluate import EvaluateConfig, load_evaluation, run_evaluate
from sar_zero123.stages.finetune import run_finetune
from sar_zero123.stages.prior import PriorConfig, prior_base_config

logger = logging.getLogger(__name__)

#: The arms' condition inputs (FinetuneConfig.spatial_pose); ``<input>@<size>`` trains that input at another
#: ``build_sar_zero123`` size than ``--size`` (``rotated_input@micro``: the quickstart's size, shippable).
ARMS = {"global": None, "rotated_input": "rotated_input"}


def arm_label(arm: str) -> str:
    """The arm's name in files and folders (letters, digits, ``._-`` only: ``rotated_input-micro``)."""
    return arm.replace("@", "-")


def parse_arm(arm: str, default_size: str) -> tuple[str | None, str]:
    """``(spatial_pose, size)`` of an arm such as ``global``, ``rotated_input`` or ``rotated_input@micro``.

    Raises:
        ValueError: Naming the arm, for an unknown condition input or size.
    """
    name, _, size = arm.partition("@")
    size = size or default_size
    if name not in ARMS or size not in SAR_ZERO123_SIZES:
        raise ValueError(
            f"arms: {arm!r} is not <input>[@<size>] with input one of {list(ARMS)} and size one of "
            f"{sorted(SAR_ZERO123_SIZES)}"
        )
    return ARMS[name], size


#: The named vehicles' evaluation chips (docs/results/history/prior.md, section 5).
EVAL_CLASSES = ("TANK", "APC", "TRUCK", "DOZER", "SPG", "RADAR", "AAGUN", "SCOUT")
EVAL_DEPRESSIONS = ("10", "15", "17", "30", "45")
PART_BYTES = 15 * 2**20  # under the 16 MiB a returned file may hold


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
    # 256 pairs ran 11-12 steps/s on an H100 (docs/results/history/prior.md, section 6): more pairs per step
    parser.add_argument("--train_batch_size", type=int, default=1024, help="pairs per step")
    parser.add_argument("--learning_rate", type=float, default=8e-4, help="AdamW peak, after the warm-up")
    parser.add_argument("--lr_warmup_steps", type=int, default=200, help="linear warm-up steps")
    parser.add_argument("--max_train_steps", type=int, default=100000, help="cap (the clock stops first)")
    parser.add_argument(
        "--lr_scheduler",
        default="constant_with_warmup",
        help="diffusers schedule after the warm-up; a decaying one (cosine) reaches 0 at --max_train_steps, "
        "so set those to the steps the budget fits (docs/results/history/prior.md, section 6, "
        "'A decaying learning rate for the warm start')",
    )
    parser.add_argument("--mixed_precision", default="bf16", choices=["no", "fp16", "bf16"])
    parser.add_argument(
        "--num_workers", type=int, default=4, help="DataLoader workers (with --no-cache_on_device)"
    )
    parser.add_argument(
        "--cache_on_device",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="latents on the GPU, batches drawn there (FinetuneConfig.cache_on_device)",
    )
    parser.add_argument("--n", type=int, default=256, help="azimuth pairs (depression pairs: 1.5 n)")
    parser.add_argument("--eval_batch_size", type=int, default=128, help="pairs per sampling call")
    parser.add_argument(
        "--baselines",
        nargs="*",
        default=[SIM_PRIOR, SIM_PRIOR_ROTATED],
        help="bundled priors (names or folders) scored beside the arms; none: only the arms",
    )
    parser.add_argument(
        "--compile",
        default=None,
        choices=["default", "reduce-overhead", "max-autotune"],
        help="compile the trained modules with torch.compile (inductor) in this mode, as "
        "`accelerate launch --dynamo_backend inductor --dynamo_mode MODE` does; a step of the "
        "micro UNet launches about 8,000 operators, which bound the steps/s on a GPU",
    )
    parser.add_argument(
        "--init",
        default=None,
        help="start every arm from this pipeline's weights (a bundled name or a folder, e.g. "
        "sar-zero123/sim-prior-rotated) instead of from scratch; its condition input must be the arm's",
    )
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def init_pipeline(init: str | None, spatial_pose: str | None, arm: str) -> Path | None:
    """The folder an arm starts from (``--init``), or None (from scratch).

    Raises:
        ValueError: Naming the arm, when the pipeline's condition input is not the arm's.
    """
    if init is None or init.lower() == "none":
        return None
    folder = resolve_pretrained(init)
    found = json.loads((folder / "pose_projection" / "config.json").read_text()).get("spatial_pose")
    if found != spatial_pose:
        raise ValueError(
            f"init: {init} takes the condition input {found or 'global'!r}, arm {arm!r} needs "
            f"{spatial_pose or 'global'!r}"
        )
    return folder


class Results:
    """``results.json`` in ``out``, rewritten atomically after every change."""

    def __init__(self, path: Path, settings: dict[str, Any]) -> None:
        self.path = path
        self.data: dict[str, Any] = {"settings": settings, "device": device_name(), "stages": {}}
        self.write()

    def stage(self, name: str, **facts: Any) -> None:
        self.data["stages"].setdefault(name, {}).update(facts)
        self.write()

    def write(self) -> None:
        write_json_atomic(self.data, self.path)


def device_name() -> str:
    if torch.cuda.is_available():
        return f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}"
    return f"cpu, torch {torch.__version__}"


def render_eval_data(folder: Path, seed: int) -> Path:
    """The named vehicles at every 5 deg of azimuth, docs/results/history/prior.md's command (section 5)."""
    if (folder / "index.csv").is_file():
        return folder
    command = [sys.executable, "train/simulate.py", "--out", str(folder), "--classes", *EVAL_CLASSES,
               "--instances", "1", "--azimuth_step_deg", "5", "--depressions_deg", *EVAL_DEPRESSIONS,
               "--size", "64", "--seed", str(seed)]  # fmt: skip
    subprocess.run(command, check=True)
    return folder


def corpus_vehicles(args: argparse.Namespace, work: Path) -> int:
    """``--num_vehicles``, or fewer where the render rate of two pilots says they would overrun
    ``--corpus_minutes``.

    The pilots render one and then five vehicles per worker into a scratch folder (removed after); the
    difference of their times is the rate without the pool's start-up, which a single pilot of two vehicles
    per worker counted as rendering (an H100 machine's 16 cores: 24 vehicles/s by one pilot, then 193
    vehicles/s rendering the corpus itself). A corpus already in ``work/corpus`` (a re-run) keeps the number
    it was written with.
    """
    options = work / "corpus" / "corpus.json"
    if options.is_file():
        return int(json.loads(options.read_text())["num_vehicles"])
    pilot = work / "corpus_pilot"
    timings = []
    for per_worker in (1, 5):
        shutil.rmtree(pilot, ignore_errors=True)
        count = max(per_worker * args.corpus_workers, 2)
        start = time.monotonic()
        write_prior_corpus(pilot, num_vehicles=count, views_per_vehicle=args.views_per_vehicle,
                           num_validation_vehicles=1, seed=args.seed, num_workers=args.corpus_workers,
                           progress=False)  # fmt: skip
        timings.append((count, time.monotonic() - start))
    shutil.rmtree(pilot, ignore_errors=True)
    (few, few_seconds), (many, many_seconds) = timings
    extra = many_seconds - few_seconds
    rate = (many - few) / extra if extra > 0 else many / many_seconds  # vehicles per second, rendering
    start_up = max(few_seconds - few / rate, 0.0)
    affordable = int(0.9 * rate * max(60.0 * args.corpus_minutes - start_up, 0.0))
    logger.info("corpus pilots: %.1f vehicles/s after %.1f s start-up; %d fit %.1f min", rate, start_up,
                affordable, args.corpus_minutes)  # fmt: skip
    return max(min(args.num_vehicles, affordable), 64)


def train_arm(args: argparse.Namespace, arm: str, corpus: Path, vae: Path, minutes: float) -> Path:
    """One prior on ``corpus`` for ``minutes`` of training steps (from ``--init``'s weights when given);
    returns its pipeline folder."""
    spatial_pose, size = parse_arm(arm, args.size)
    prior = PriorConfig(
        output_dir=str(Path(args.work) / arm_label(arm)),
        corpus=str(corpus),
        model_size=size,
        spatial_pose=spatial_pose,
        vae=str(vae),
        train_batch_size=args.train_batch_size,
        base_steps=args.max_train_steps,
        learning_rate=args.learning_rate,
        mixed_precision=args.mixed_precision,
        seed=args.seed,
    )
    config = prior_base_config(prior, vae, corpus)
    start = init_pipeline(args.init, spatial_pose, arm)
    if start is not None:  # the pipeline keeps its own condition input, size and prediction type
        config = dataclasses.replace(
            config, pretrained=str(start), spatial_pose=None, input_depression=False, prediction_type=None
        )
    config = dataclasses.replace(
        config,
        max_train_minutes=minutes,
        lr_scheduler=args.lr_scheduler,
        lr_warmup_steps=args.lr_warmup_steps,
        checkpointing_steps=args.max_train_steps,
        checkpoints_total_limit=1,
        num_workers=args.num_workers,
        cache_on_device=args.cache_on_device,
    )
    run_finetune(config)
    return Path(config.output_dir) / "pipeline"


def evaluate(
    args: argparse.Namespace, name: str, pipelines: dict[str, Path], data: Path, **pairs: Any
) -> dict[str, Any]:
    """Table III of ``pipelines`` on one pair set (the floor and the ceilings come with it)."""
    config = EvaluateConfig(
        pipeline=[str(path) for path in pipelines.values()],
        pipeline_names=list(pipelines),
        evaluators=args.evaluators,
        data=str(data),
        protocol="extended",
        input_depression_deg=17.0,
        num_inference_steps=20,
        eval_batch_size=args.eval_batch_size,
        output_dir=str(Path(args.work) / f"eval_{name}"),
        seed=args.seed,
        **pairs,
    )
    return load_evaluation(run_evaluate(config))["table3"]


def pack(pipeline: Path, out: Path, arm: str) -> list[str]:
    """The pipeline folder with its UNet in float16, as ``out/<arm>.tar.part00, 01, ...``."""
    from diffusers import UNet2DConditionModel

    unet = UNet2DConditionModel.from_pretrained(pipeline / "unet")
    unet.to(torch.float16).save_pretrained(pipeline / "unet")
    archive = out / f"{arm}.tar"
    with tarfile.open(archive, "w") as tar:  # vae/ is the bundled prior's: restored from the package
        tar.add(pipeline, arcname=f"{arm}_pipeline", filter=_without_vae)
    payload = archive.read_bytes()
    archive.unlink()
    parts = []
    for index, start in enumerate(range(0, len(payload), PART_BYTES)):
        part = out / f"{arm}.tar.part{index:02d}"
        part.write_bytes(payload[start : start + PART_BYTES])
        parts.append(part.name)
    return parts


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
    num_vehicles = corpus_vehicles(args, work)
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
    vae = resolve_pretrained(SIM_PRIOR) / "vae"
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
        unet_parameters = sum(p.numel() for p in _load_unet(pipelines[arm]).parameters())
        results.stage(f"train_{arm}", seconds=time.monotonic() - start, train_minutes=per_arm, steps=steps,
                      pairs=steps * args.train_batch_size, pairs_per_second=steps * args.train_batch_size /
                      (60 * per_arm), unet_parameters=unet_parameters)  # fmt: skip
        try:  # the weights come back even if a later stage runs out of time
            results.stage(f"train_{arm}", parts=pack(pipelines[arm], out, arm_label(arm)))
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


def _without_vae(member: tarfile.TarInfo) -> tarfile.TarInfo | None:
    """Leaves out the VAE (restored from the package) and the manifest, which sealed the folder with the
    float32 UNet and that VAE: the restored folder loads as an unsealed one (with a warning)."""
    return None if "/vae" in member.name or member.name.endswith("/manifest.json") else member


def _load_unet(pipeline: Path) -> torch.nn.Module:
    from diffusers import UNet2DConditionModel

    return UNet2DConditionModel.from_pretrained(pipeline / "unet")


if __name__ == "__main__":
    main()
