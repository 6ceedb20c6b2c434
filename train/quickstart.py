"""End-to-end run on the built-in simulator (or a chip folder): the README's main command.

    python train/quickstart.py --output_dir runs/quickstart
    python train/quickstart.py --preset mstar --data /path/to/mstar --protocol ood-T72 --output_dir runs/mstar

With the default preset, on a 2-core CPU, it

1. simulates a small MSTAR-like dataset (`sar_zero123.sim`), one class held out (MSTAR-OOD style), unless
   `--data` names real chips (with `--protocol extended` or `ood-<CLASS>`), and views of the same vehicles at
   `Preset.depression_targets_deg` for depression requests,
2. pretrains a small SimCLR encoder with the Speckle Rayleigh + Monotonic augmentation (`pretrain_simclr.py`),
3. fine-tunes the bundled multi-view prior (`Preset.prior`, `sar-zero123/sim-prior`) with each PFM weight of
   `--lambdas` (default 0 and 4) from the same prior, as the paper fine-tunes one zero-1-to-3 checkpoint
   (`finetune_pfm.py`); presets without a prior first train a VAE (`train_vae.py`) and a base model from
   scratch,
4. trains the evaluator classifier, azimuth regressor and depression regressor (plus a probe on the SimCLR
   encoder) on all classes,
5. evaluates the fine-tuned pipelines (Table III, Table IV, views, lambda plot, speed against error, and a
   second Table III of depression requests from 17 deg inputs: `evaluate.py`),
6. writes `report.md` with the tables and figures.

Every stage calls the stage script's `main(argv)` (imported as `train.<name>`) in this process and is
skipped when its output already exists, and each training stage resumes from its newest checkpoint
(`Preset.checkpointing_steps`), so an interrupted run continues where it stopped, and a re-run
with more `--lambdas` trains only the new fine-tunes (then evaluates them all on the same pairs); a
re-run with other preset values (`--preset`, `--override`) in the same folder is refused. Presets:
`default` (the prior), `scratch` (the default trained from scratch), `long` (from scratch, longer), `mstar`
(real chips) and `smoke` (tiny settings in seconds, for tests); their measured times are in
docs/results/. The numbers are CPU quick-run numbers, far from the paper's setting (20,000 iterations from
an Objaverse checkpoint on real MSTAR at 128 px).
"""

from __future__ import annotations

import ast
import dataclasses
import json
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Literal

import torch

from sar_zero123.config import parse_config, save_config, write_json_atomic
from sar_zero123.data import SCALING_FILE
from sar_zero123.data.splits import check_protocol
from sar_zero123.models import SAR_ZERO123_SIZES
from sar_zero123.pretrained import SIM_PRIOR, resolve_pretrained
from sar_zero123.sim import TARGET_CLASSES, simulate_dataset

if not __package__:  # run as a file: Python put only train/ on sys.path (see train/__init__.py)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from train import evaluate, finetune_pfm, pretrain_simclr, train_evaluators, train_vae  # noqa: E402

logger = logging.getLogger(__name__)

#: Most evaluation pairs a preset may ask for (the evaluation generates each one).
MAX_EVAL_N = 100_000


@dataclass(frozen=True)
class Preset:
    """Sizes of one quickstart run (see `PRESETS`)."""

    classes: tuple[str, ...]  # simulated classes; the last one is held out (unseen)
    instances: int  # simulated objects per class
    azimuth_step_deg: float  # azimuth grid of the simulator
    model_size: str  # build_sar_zero123 size fine-tuned from scratch
    image_size: int  # chip side in pixels
    encoder_cifar_stem: bool  # 3x3 stride-1 stem (reference) or the 4x-downsampling ImageNet stem (faster)
    encoder_depths: tuple[int, ...]  # ResNet blocks per stage (SimCLR encoder and evaluators)
    encoder_widths: tuple[int, ...]  # ResNet stage widths
    simclr_steps: int  # SimCLR optimisation steps
    simclr_batch_size: int  # SimCLR chips per step
    vae_widths: tuple[int, ...]  # VAE block widths (3 blocks: 16x16 latents of a 64 px chip)
    vae_norm_groups: int  # GroupNorm groups of the VAE (divides every width)
    vae_steps: int  # VAE optimisation steps
    vae_batch_size: int  # chips per VAE step
    estimate_input_azimuth: bool  # the SAR-sized pose path (build_sar_zero123(estimate_input_azimuth=True))
    base_steps: int  # lambda = 0 steps of the base model both fine-tunes start from
    finetune_steps: int  # fine-tuning steps per lambda, from the base model
    finetune_batch_size: int  # pairs per fine-tuning step
    finetune_learning_rate: float  # AdamW learning rate of the UNet (from scratch: higher than the paper's)
    pfm_fraction: float  # share of the PFM-eligible samples of a batch that get PFM (unbiased, cheaper)
    pfm_projection_dim: int | None  # 10: the authors' 512->10 projection, so lambda = 4 means the paper's 4
    evaluator_epochs: int  # epochs of the scratch classifier and regressor
    evaluator_learning_rate: float  # AdamW peak learning rate of the evaluators
    eval_n: int  # evaluation samples (half seen, half unseen)
    eval_steps: int  # DDIM steps for Tables III/IV
    speed_steps: tuple[int, ...]  # step counts of the speed/error sweep
    speed_n: int  # samples per speed/error point
    schedulers: tuple[str, ...]  # samplers of the speed/error sweep
    lr_scheduler: str = "constant"  # diffusers LR schedule of the base model and of each fine-tune
    lr_warmup_steps: int = 0  # its warm-up steps (each stage)
    ema_decay: float | None = None  # EMA of the exported UNet (None: the last weights)
    train_image_encoder: bool = False  # train the (random) CLIP tower with the UNet
    # the base model's training target and loss weighting (finetune_pfm.py's fields of the same names; the
    # fine-tunes inherit the prediction type from the base model's scheduler)
    prediction_type: str = "epsilon"  # "epsilon" (zero-1-to-3, the paper) or "v_prediction"
    snr_gamma: float | None = None  # Min-SNR-gamma weighting of L_simple in every stage (None: unweighted)
    timestep_sampling: str = "uniform"  # training t density of every stage: "uniform" or "logit_normal"
    timestep_logit_mean: float = 0.0  # logit_normal: mean of logit(t / T) (> 0 favours high noise)
    # every training stage (SimCLR, VAE, base model, fine-tunes) saves a resumable checkpoint every this
    # many steps and keeps the last two; a re-run resumes an interrupted stage from its newest intact one
    checkpointing_steps: int = 1000
    # accelerate mixed precision of every training stage ("bf16" on a recent GPU); the evaluation samples
    # in float32 either way
    mixed_precision: str = "no"
    # a pretrained pipeline (a bundled name such as "sar-zero123/sim-prior", or a folder) that every fine-tune
    # starts from, as the paper fine-tunes zero-1-to-3: its VAE is kept and no base model is trained
    # (vae_* and base_steps unused); None trains the VAE and a base model from scratch
    prior: str | None = None
    # target depressions of a second Table III from 17 deg inputs (d_el = target - 17) on a simulated set
    # at 17 deg and these depressions, with a depression regressor among the evaluators; () skips it
    depression_targets_deg: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        # every field checked here, in the preset's own names, so that a bad --override fails before the
        # first stage instead of when its stage starts
        counts = ("instances", "simclr_steps", "simclr_batch_size", "vae_steps", "vae_batch_size",
                  "base_steps", "finetune_steps", "finetune_batch_size", "evaluator_epochs", "eval_steps",
                  "speed_n", "checkpointing_steps")  # fmt: skip
        for name in counts:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.eval_n < 4:
            raise ValueError(f"eval_n must be >= 4 (two seen and two unseen pairs), got {self.eval_n}")
        if self.eval_n > MAX_EVAL_N:
            raise ValueError(f"eval_n must be <= {MAX_EVAL_N}, got {self.eval_n}")
        if len(self.classes) < 2 or len(set(self.classes)) != len(self.classes):
            raise ValueError(f"classes must name at least two distinct classes, got {self.classes!r}")
        unknown = sorted(set(self.classes) - set(TARGET_CLASSES))
        if unknown:
            raise ValueError(f"classes: unknown {unknown}; simulator classes are {list(TARGET_CLASSES)}")
        if self.model_size not in SAR_ZERO123_SIZES:
            raise ValueError(
                f"model_size must be one of {sorted(SAR_ZERO123_SIZES)}, got {self.model_size!r}"
            )
        if self.image_size < 16:
            raise ValueError(f"image_size must be >= 16, got {self.image_size}")
        if not 0.0 < self.azimuth_step_deg <= 360.0:
            raise ValueError(f"azimuth_step_deg must lie in (0, 360], got {self.azimuth_step_deg}")
        if not 0.0 < self.pfm_fraction <= 1.0:
            raise ValueError(f"pfm_fraction must lie in (0, 1], got {self.pfm_fraction}")
        for name in ("finetune_learning_rate", "evaluator_learning_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.encoder_depths or len(self.encoder_depths) != len(self.encoder_widths):
            raise ValueError(
                f"encoder_depths {self.encoder_depths} and encoder_widths {self.encoder_widths} must be "
                "non-empty and of one length"
            )
        if not self.speed_steps or min(self.speed_steps) < 1:
            raise ValueError(f"speed_steps must be step counts >= 1, got {self.speed_steps}")
        unknown = sorted(set(self.schedulers) - set(evaluate.SCHEDULERS))
        if not self.schedulers or unknown:
            raise ValueError(
                f"schedulers: choose from {sorted(evaluate.SCHEDULERS)}, got {self.schedulers!r}"
            )
        if any(not 0.0 < d < 90.0 for d in self.depression_targets_deg):
            raise ValueError(f"depression_targets_deg must lie in (0, 90), got {self.depression_targets_deg}")
        if self.lr_warmup_steps < 0:
            raise ValueError(f"lr_warmup_steps must be >= 0, got {self.lr_warmup_steps}")
        if self.ema_decay is not None and not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must lie in [0, 1) or be None, got {self.ema_decay}")
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")
        if self.prediction_type not in ("epsilon", "v_prediction"):
            raise ValueError(
                f"prediction_type must be 'epsilon' or 'v_prediction', got {self.prediction_type!r}"
            )
        if self.timestep_sampling not in ("uniform", "logit_normal"):
            raise ValueError(
                f"timestep_sampling must be 'uniform' or 'logit_normal', got {self.timestep_sampling!r}"
            )
        if self.snr_gamma is not None and self.snr_gamma <= 0:
            raise ValueError(f"snr_gamma must be > 0 or None, got {self.snr_gamma}")
        if any(width % self.vae_norm_groups for width in self.vae_widths):
            raise ValueError(
                f"vae_norm_groups {self.vae_norm_groups} must divide each of vae_widths {self.vae_widths}"
            )


DEFAULT_PRESET = Preset(
    # TANK held out, as MSTAR-OOD holds out the T72 tank; the seen SPG has its turret at the rear like
    # MSTAR's seen 2S1. Held out instead, the SPG is read back to front by an azimuth estimator trained
    # on the other three (learning.md, section 6a).
    classes=("APC", "TRUCK", "SPG", "TANK"),
    instances=1,
    azimuth_step_deg=5.0,
    model_size="micro",
    image_size=64,
    encoder_cifar_stem=False,
    encoder_depths=(1, 1, 1, 1),
    encoder_widths=(16, 32, 64, 128),
    simclr_steps=200,
    simclr_batch_size=64,
    # a VAE with a quarter of the "small" one's parameters trains faster per chip, so the same stage time
    # buys more chips and a better reconstruction (docs/results/learning.md, section 6b)
    vae_widths=(16, 32, 64),
    vae_norm_groups=8,
    vae_steps=540,
    vae_batch_size=8,
    estimate_input_azimuth=True,
    # enough steps for pose use to emerge, within the quickstart's time budget (learning.md, 7c-7d)
    base_steps=3000,
    # v prediction with Min-SNR-5 weighting: on the same steps it turns more views to the requested pose
    # and keeps their class more often than epsilon L_simple (learning.md, section 9h)
    prediction_type="v_prediction",
    snr_gamma=5.0,
    # from the prior, 1,000 steps turn the held-out vehicle best (200 keep more of the prior's depression
    # following; docs/results/prior.md, section 5)
    finetune_steps=1000,
    finetune_batch_size=16,
    finetune_learning_rate=1e-3,
    pfm_fraction=0.25,
    pfm_projection_dim=10,
    evaluator_epochs=40,
    evaluator_learning_rate=2e-3,
    eval_n=128,
    eval_steps=20,
    speed_steps=(5, 20),
    speed_n=4,
    schedulers=("ddim", "dpmsolver++", "euler"),
    # the paper's regime: both fine-tunes start from the bundled multi-view prior (its VAE kept)
    prior=SIM_PRIOR,
    depression_targets_deg=(10.0, 30.0, 45.0),
)

PRESETS: dict[str, Preset] = {
    "default": DEFAULT_PRESET,
    # the default trained from scratch (VAE and a base model of base_steps, then the fine-tunes): the
    # comparison row for the prior
    "scratch": dataclasses.replace(DEFAULT_PRESET, prior=None, finetune_steps=200),
    # the scratch preset trained longer, for the seen-accuracy and unseen-vehicle targets: the same
    # simulated data, the VAE trained 3,000 steps instead of 540 and 15,000 base steps, with the default's
    # v prediction and Min-SNR-5, which keeps the seen class more often than epsilon L_simple on the same
    # data, VAE and evaluators (run times and results: docs/results/learning.md, sections 6d, 8c, 9 and 9i)
    "long": dataclasses.replace(
        DEFAULT_PRESET, vae_steps=3000, base_steps=15000, finetune_steps=600, eval_n=256,
        speed_steps=(5, 10, 20, 50), speed_n=32, prior=None,
    ),
    # Real chips (`--data /path/to/mstar --protocol ood-T72` or `extended`): 64 px centre crops at the
    # native 0.2 m spacing, about 6,000 training chips, so fewer evaluator epochs and more base steps, and
    # the "small" model's VAE trained 600 x 16 (run time and results: docs/results/mstar_novel_views.md).
    # Simulator fields unused.
    "mstar": dataclasses.replace(
        DEFAULT_PRESET, vae_widths=(32, 64, 128), vae_norm_groups=32, vae_steps=600, vae_batch_size=16,
        base_steps=8000, finetune_steps=1000,
        evaluator_epochs=20, eval_n=400, speed_steps=(5, 10, 20), speed_n=16,
        prediction_type="epsilon", snr_gamma=None,  # as measured (mstar_novel_views.md)
        prior=None,  # the prior's dB scaling and chips are the simulator's
        depression_targets_deg=(),  # real chips: 15 and 17 deg only
    ),
    "smoke": Preset(
        classes=("TANK", "APC", "TRUCK"),
        instances=1,
        azimuth_step_deg=60.0,
        model_size="tiny",
        image_size=32,
        encoder_cifar_stem=True,
        encoder_depths=(1, 1),
        encoder_widths=(8, 16),
        vae_widths=(16, 32),
        vae_norm_groups=8,
        simclr_steps=2,
        simclr_batch_size=8,
        vae_steps=2,
        vae_batch_size=4,
        estimate_input_azimuth=True,
        base_steps=2,
        finetune_steps=2,
        finetune_batch_size=2,
        finetune_learning_rate=1e-4,
        pfm_fraction=1.0,
        pfm_projection_dim=10,
        evaluator_epochs=1,
        evaluator_learning_rate=1e-3,
        eval_n=4,
        eval_steps=2,
        speed_steps=(1,),
        speed_n=2,
        schedulers=("ddim", "euler"),
        # the optional training settings, so that the smoke test runs them
        lr_scheduler="cosine",
        lr_warmup_steps=1,
        ema_decay=0.9,
        train_image_encoder=True,
        prediction_type="v_prediction",
        snr_gamma=5.0,
        timestep_sampling="logit_normal",
        checkpointing_steps=1,
        depression_targets_deg=(30.0,),
    ),
}


@dataclass
class QuickstartConfig:
    """Simulate (or read `data`), pretrain SimCLR, fine-tune each lambda, train evaluators, evaluate."""

    output_dir: str = "runs/quickstart"  # run folder (every stage writes a subfolder; report.md at the top)
    # "default" (the bundled prior), "scratch" (from scratch), "long", "mstar" (real data), "smoke" (seconds)
    preset: Literal["default", "scratch", "long", "mstar", "smoke"] = "default"
    data: str | None = None  # chip folder (index.csv or raw MSTAR files); None simulates the preset's classes
    protocol: str | None = None  # "extended" or "ood-<CLASS>"; None = ood-<last simulated class>
    # PFM weights fine-tuned from the base model and evaluated side by side (a lambda sweep: 0 1 4 16);
    # a re-run in the same folder with more values trains only the new ones
    lambdas: list[float] = field(default_factory=lambda: [0.0, 4.0])
    seed: int = 0  # seed of every stage
    # preset fields replaced for this run, FIELD=VALUE with a Python literal (base_steps=3000,
    # lr_scheduler=cosine, vae_widths=16,32,64); the run's preset.json records the result
    override: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        if not self.lambdas or min(self.lambdas) < 0 or len(set(self.lambdas)) != len(self.lambdas):
            raise ValueError(f"lambdas must be distinct values >= 0, got {self.lambdas}")
        if self.data is not None and not Path(self.data).is_dir():
            raise FileNotFoundError(f"data: expected a chip folder, got {self.data}")
        if self.data is not None and self.protocol is None:
            raise ValueError("protocol: give 'extended' or 'ood-<CLASS>' with --data (e.g. ood-T72)")
        apply_overrides(PRESETS[self.preset], self.override)  # a bad override fails before any stage
        if self.protocol is not None and check_protocol(self.protocol) == "soc":
            # evaluate.py pairs seen/unseen views by `extended` or `ood-*`: fail here, not after training
            raise ValueError("protocol: the quickstart evaluates 'extended' or 'ood-<CLASS>', got 'soc'")


def apply_overrides(preset: Preset, overrides: Sequence[str]) -> Preset:
    """`preset` with the `FIELD=VALUE` items of `overrides` replaced (`VALUE` a Python literal; a bare word
    is a string; a list becomes a tuple); the preset's own checks run on the result.

    Raises:
        ValueError: naming the item, for an unknown field, a missing ``=``, or a value whose type differs
            from the preset's (an int is accepted for a float field; a field that is ``None`` takes any).
    """
    fields = {f.name for f in dataclasses.fields(Preset)}
    changes: dict[str, Any] = {}
    for item in overrides:
        name, separator, text = item.partition("=")
        if not separator or name not in fields:
            raise ValueError(f"override: expected FIELD=VALUE, FIELD one of {sorted(fields)}; got {item!r}")
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text  # a bare word: lr_scheduler=cosine
        if isinstance(value, list):
            value = tuple(value)
        current = getattr(preset, name)
        same_type = isinstance(value, type(current)) and isinstance(value, bool) == isinstance(current, bool)
        int_for_float = isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool)
        if current is not None and value is not None and not (same_type or int_for_float):
            raise ValueError(
                f"override: {name} takes a {type(current).__name__} like {current!r}, got {item!r}"
            )
        changes[name] = float(value) if int_for_float else value
    return dataclasses.replace(preset, **changes)


def check_same_preset(out: Path, preset: Preset) -> None:
    """Refuse to continue a run folder made with other preset values: a finished stage is skipped by the
    files it left, so a changed value would be silently ignored for it (e.g. `--override base_steps=...`).

    Raises:
        ValueError: naming each field whose value differs from the folder's ``preset.json``.
    """
    path = out / "preset.json"
    if not path.is_file():
        return
    # through JSON, so that tuples and lists compare alike
    new = json.loads(json.dumps(dataclasses.asdict(preset)))
    old = json.loads(path.read_text())
    changed = {name: (old.get(name), value) for name, value in new.items() if old.get(name, value) != value}
    if changed:
        listed = ", ".join(f"{name} {was!r} -> {now!r}" for name, (was, now) in sorted(changed.items()))
        raise ValueError(
            f"output_dir: {str(out)!r} holds a run made with other preset values ({listed}); its finished "
            "stages would be reused as they are: give a new --output_dir"
        )


def script_argv(module: ModuleType, values: dict[str, Any]) -> list[str]:
    """Flags for a stage script from `values`; every key must be a field of its config dataclass.

    Raises:
        ValueError: naming the script and the option it does not declare (a renamed flag must fail
            here, not silently fall back to the script's default).
    """
    config_classes = [
        obj
        for obj in vars(module).values()
        if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__
    ]
    fields = {f.name for cls in config_classes for f in dataclasses.fields(cls)}
    argv: list[str] = []
    for name, value in values.items():
        if name not in fields:
            raise ValueError(f"{module.__name__} has no option {name!r}; expected one of {sorted(fields)}")
        if isinstance(value, bool):
            argv.append(f"--{name}" if value else f"--no-{name}")
        elif isinstance(value, (list, tuple)):
            argv += [f"--{name}", *map(str, value)]
        else:
            argv += [f"--{name}", str(value)]
    return argv


def run_stage(name: str, done: Path | bool, timings: dict[str, float], function, *args) -> Any:
    """Runs one stage unless it is done (`done`: a path that exists once it is, or a flag); records its wall
    time."""
    if done is True or (isinstance(done, Path) and done.exists()):
        logger.info("stage %s: done (%s), skipping", name, done)
        timings[name] = 0.0
        return None
    logger.info("stage %s", name)
    begin = time.perf_counter()
    result = function(*args)
    timings[name] = time.perf_counter() - begin
    logger.info("stage %s took %.1f s", name, timings[name])
    return result


def main(argv: Sequence[str] | None = None) -> Path:
    """Runs the whole chain; returns the path of `report.md`."""
    config = parse_config(QuickstartConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    preset = apply_overrides(PRESETS[config.preset], config.override)
    out = Path(config.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    check_same_preset(out, preset)
    save_config(config, out)
    write_json_atomic(dataclasses.asdict(preset), out / "preset.json")
    timings: dict[str, float] = {}
    protocol = config.protocol or f"ood-{preset.classes[-1]}"
    held_out = protocol[len("ood-") :] if protocol.startswith("ood-") else None
    data = out / "data" if config.data is None else Path(config.data)
    common = {"data": str(data), "seed": config.seed, "image_size": preset.image_size}
    # the training stages (the evaluation script has no such option)
    training = {"mixed_precision": preset.mixed_precision}
    encoder_shape = {
        "cifar_stem": preset.encoder_cifar_stem,
        "depths": preset.encoder_depths,
        "hidden_sizes": preset.encoder_widths,
    }

    # 1. simulated dataset (15 and 17 deg, as MSTAR), unless real chips are given, and views of the same
    #    vehicles at other depressions for the depression Table III and its regressor
    depression_data = out / "data_depression"
    simulated = [("simulate", data, (15.0, 17.0))]
    if preset.depression_targets_deg:
        depressions = tuple(sorted({17.0, *preset.depression_targets_deg}))
        simulated.append(("simulate depressions", depression_data, depressions))
    for name, folder, depressions in simulated if config.data is None else []:
        run_stage(name, folder / "index.csv", timings, simulate_dataset, folder, preset.classes,
                  preset.instances, preset.azimuth_step_deg, depressions, preset.image_size, config.seed)

    # 2. SimCLR encoder with Speckle Rayleigh + Monotonic (on the seen classes' train split)
    simclr_dir = out / "simclr"
    simclr_args = {
        **common,
        **training,
        **encoder_shape,
        "output_dir": str(simclr_dir),
        "protocol": protocol,
        "preset": "speckle+monotonic",
        "embedding_size": preset.encoder_widths[0],
        "global_batch_size": preset.simclr_batch_size,
        "max_train_steps": preset.simclr_steps,
        "epochs": 10_000,
        "checkpointing_steps": preset.checkpointing_steps,
        "checkpoints_total_limit": 2,
        "resume_from_checkpoint": "latest",
        "report_to": "none",
    }
    run_stage("simclr", simclr_dir / "encoder" / "model.safetensors", timings, pretrain_simclr.main,
              script_argv(pretrain_simclr, simclr_args))

    # 3. VAE sized for SAR chips: the preset's widths, the model's depth and latent shape (any VAE with the
    #    model's latent shape replaces its own, models.check_vae_fits)
    vae_run = out / "vae"
    vae_dir = vae_run / "vae"
    vae_shape = SAR_ZERO123_SIZES[preset.model_size]["vae"]
    vae_args = {
        **common,
        **training,
        "output_dir": str(vae_run),
        "protocol": protocol,
        "block_out_channels": preset.vae_widths,
        "layers_per_block": vae_shape["layers_per_block"],
        "latent_channels": vae_shape["latent_channels"],
        "norm_num_groups": preset.vae_norm_groups,
        "train_batch_size": preset.vae_batch_size,
        "max_train_steps": preset.vae_steps,
        "learning_rate": 1e-3,
        "num_eval_images": 16,
        "checkpointing_steps": preset.checkpointing_steps,
        "checkpoints_total_limit": 2,
        "resume_from_checkpoint": "latest",
        "report_to": "none",
    }
    # decibel_scaling.json is the last file train_vae writes into its VAE folder; a prior keeps its own VAE
    if preset.prior is None:
        run_stage("vae", vae_dir / SCALING_FILE, timings, train_vae.main, script_argv(train_vae, vae_args))

    # 4. a base model (lambda = 0), then fine-tunes from it with lambda = 0 and lambda = 4, as the paper
    #    fine-tunes one pretrained zero-1-to-3 checkpoint with and without PFM
    def finetune_stage(name: str, run_dir: Path, steps: int, weight: float, pretrained: Path | None) -> Path:
        finetune_args = {
            **common,
            **training,
            "output_dir": str(run_dir),
            "protocol": protocol,
            "pfm_weight": weight,
            "pfm_fraction": preset.pfm_fraction,
            "encoder": str(simclr_dir / "encoder"),
            "train_batch_size": preset.finetune_batch_size,
            "max_train_steps": steps,
            "learning_rate": preset.finetune_learning_rate,
            "lr_scheduler": preset.lr_scheduler,
            "lr_warmup_steps": preset.lr_warmup_steps,
            "use_ema": preset.ema_decay is not None,
            "train_image_encoder": preset.train_image_encoder,
            "timestep_sampling": preset.timestep_sampling,
            "timestep_logit_mean": preset.timestep_logit_mean,
            "validation_steps": 0,
            "checkpointing_steps": preset.checkpointing_steps,
            "checkpoints_total_limit": 2,
            "resume_from_checkpoint": "latest",
            "report_to": "none",
        }
        if preset.ema_decay is not None:
            finetune_args["ema_decay"] = preset.ema_decay
        if preset.snr_gamma is not None:
            finetune_args["snr_gamma"] = preset.snr_gamma
        if preset.pfm_projection_dim is not None:
            finetune_args["pfm_projection_dim"] = preset.pfm_projection_dim
        if preset.prior is None:
            finetune_args["vae"] = str(vae_dir)
        if pretrained is None:
            finetune_args["size"] = preset.model_size
            finetune_args["estimate_input_azimuth"] = preset.estimate_input_azimuth
            finetune_args["prediction_type"] = preset.prediction_type
        else:
            finetune_args["pretrained"] = str(pretrained)
        done = run_dir / "pipeline" / "model_index.json"
        run_stage(name, done, timings, finetune_pfm.main, script_argv(finetune_pfm, finetune_args))
        return run_dir / "pipeline"

    if preset.prior is None:
        base = finetune_stage("base model", out / "base", preset.base_steps, 0.0, None)
    else:  # the paper's regime: both fine-tunes start from one pretrained multi-view prior
        base = resolve_pretrained(preset.prior)
    pipelines = {}
    for weight in config.lambdas:
        name = f"lambda={weight:g}"
        pipelines[name] = finetune_stage(
            f"finetune {name}", out / f"finetune_lambda{weight:g}", preset.finetune_steps, weight, base
        )

    # 5. evaluators on all classes (train split at 17 deg), plus a Table IV probe on the SimCLR encoder
    evaluator_dir = out / "evaluators"
    evaluator_args = {
        **common,
        **training,
        **encoder_shape,
        "output_dir": str(evaluator_dir),
        "epochs": preset.evaluator_epochs,
        "probe_epochs": preset.evaluator_epochs,
        "learning_rate": preset.evaluator_learning_rate,
        "train_batch_size": 32,
        "simclr_encoders": [str(simclr_dir)],
    }
    if (depression_data / "index.csv").is_file():
        evaluator_args["depression_data"] = str(depression_data)
    run_stage("evaluators", evaluator_dir / "metrics.json", timings, train_evaluators.main,
              script_argv(train_evaluators, evaluator_args))

    # 6. evaluation
    def evaluate_stage(name: str, eval_dir: Path, values: dict[str, Any]) -> None:
        eval_argv = [
            *[token for path in pipelines.values() for token in ("--pipeline", str(path))],
            *script_argv(
                evaluate,
                {
                    "seed": config.seed,
                    "pipeline_names": list(pipelines),
                    "lambdas": list(config.lambdas),
                    "evaluators": str(evaluator_dir),
                    "protocol": protocol,
                    "n": preset.eval_n,
                    "num_inference_steps": preset.eval_steps,
                    "guidance_scale": 3.0,
                    "crop_size": min(64, preset.image_size),
                    "eval_batch_size": 8,
                    "output_dir": str(eval_dir),
                    **values,
                },
            ),
        ]
        table3 = eval_dir / "table3.json"
        evaluated = table3.is_file() and set(pipelines) <= set(json.loads(table3.read_text())["results"])
        run_stage(name, evaluated, timings, evaluate.main, eval_argv)

    speed = {"steps": preset.speed_steps, "schedulers": list(preset.schedulers), "speed_n": preset.speed_n}
    evaluate_stage("evaluate", out / "eval", {"data": str(data), **speed})
    # 6b. depression requests from 17 deg inputs (same evaluators; both groups' pairs change depression)
    if (depression_data / "index.csv").is_file():
        evaluate_stage(
            "evaluate depressions",
            out / "eval_depression",
            {
                "data": str(depression_data),
                "same_depression": False,
                "input_depression_deg": 17.0,
                "target_depressions_deg": list(preset.depression_targets_deg),
                "outside_trained_range": True,  # a from-scratch model never saw d_el != 0: score it anyway
            },
        )

    # 7. report
    write_json_atomic(timings, out / "timings.json")
    report = write_report(out, preset, config, held_out, timings)
    print(f"wrote {report}")
    return report


def write_report(
    out: Path, preset: Preset, config: QuickstartConfig, held_out: str | None, timings: dict
) -> Path:
    """`report.md`: setup, evaluator quality, Table III, Table IV, speed/error, figures, timings."""
    eval_dir = out / "eval"
    table3 = json.loads((eval_dir / "table3.json").read_text())
    evaluator_metrics = json.loads((out / "evaluators" / "metrics.json").read_text())["models"]
    device = "CUDA " + torch.cuda.get_device_name() if torch.cuda.is_available() else "CPU"
    total = sum(timings.values())
    data_kind = "simulated data" if config.data is None else f"real chips from `{config.data}`"
    if config.data is None:
        data_line = (
            f"Data: simulator classes {list(preset.classes)} ({preset.instances} object each, azimuth step "
            f"{preset.azimuth_step_deg:g} deg, 15 and 17 deg depression, {preset.image_size} px). "
        )
    else:
        data_line = f"Data: `{config.data}`, {preset.image_size} px centre crops. "
    if held_out is None:
        protocol_line = (
            "Protocol `extended`: the model trains on the 17 deg chips of every class and is evaluated on "
            "pairs of 15 deg test views (seen classes only). "
        )
    else:
        protocol_line = (
            f"Protocol `ood-{held_out}`: {held_out} is never seen in SimCLR or fine-tuning; evaluation pairs "
            "are half seen (15 deg test views of the other classes) and half unseen (all views of the "
            "held-out class). "
        )
    if preset.prior is None:
        start = f"a `{preset.model_size}` model trained from scratch for {preset.base_steps} steps (lambda 0)"
    else:
        start = f"the pretrained multi-view prior `{preset.prior}` (procedural simulated vehicles)"
    lines = [
        "# sar_zero123 quickstart report",
        "",
        f"Preset `{config.preset}`, seed {config.seed}, device {device} ({torch.get_num_threads()} threads), "
        f"total {total / 60:.1f} min. **CPU quick-run numbers on {data_kind}**: {start}, then fine-tuned for "
        f"{preset.finetune_steps} steps with each lambda (PFM on {preset.pfm_fraction:g} of the "
        f"eligible samples, features projected to {preset.pfm_projection_dim} dimensions as the authors "
        "did), not the paper's zero-1-to-3 fine-tune (Objaverse initialisation, 20,000 iterations, real "
        "MSTAR); compare the rows with each other, not with the paper.",
        "",
        data_line
        + protocol_line
        + "The evaluators are trained on the 17 deg chips of all classes, as in the paper.",
        "",
        "## Evaluators (test split, 15 deg)",
        "",
        "| Model | Test accuracy (%) | Test azimuth error (deg) | train / test chips |",
        "| --- | --- | --- | --- |",
    ]
    for name, values in evaluator_metrics.items():
        accuracy = values.get("test_accuracy")
        error = values.get("test_azimuth_error_deg")
        lines.append(
            f"| {name} | {'-' if accuracy is None else f'{100 * accuracy:.1f}'} | "
            f"{'-' if error is None else f'{error:.1f}'} | {values.get('n_train')} / {values.get('n_test')} |"
        )
    lines += [
        "",
        f"## Table III ({table3['num_inference_steps']} DDIM steps, guidance {table3['guidance_scale']})",
        "",
        "`input copy (floor)` returns the input view unchanged (a generator that ignores the pose); "
        "`real target (ceiling)` scores the true target view and `VAE round trip (ceiling)` the target "
        "encoded and decoded by the VAE, the best a latent model with this VAE can do. A model must beat the "
        "floor on azimuth error; `Az. gap closed` is the fraction of the floor-to-VAE-ceiling gap it closes.",
        "",
        (eval_dir / "table3.md").read_text(),
        "## Table IV (azimuth error of generated views under each evaluator backbone)",
        "",
        (eval_dir / "table4.md").read_text(),
    ]
    if (eval_dir / "speed_error.md").is_file():
        lines += ["## Speed against error", "", (eval_dir / "speed_error.md").read_text(),
                  "![speed and error](eval/speed_error.png)", ""]
    columns = " | ".join(f"lambda={weight:g}" for weight in config.lambdas)
    lines += [f"## Generated views (input | {columns} | target)", "", "![views](eval/views.png)", ""]
    if (eval_dir / "lambda_sweep.png").is_file():
        lines += ["## Metrics against lambda", "", "![lambda](eval/lambda_sweep.png)", ""]
    depression_dir = out / "eval_depression"
    if (depression_dir / "table3.md").is_file():
        targets = ", ".join(f"{d:g}" for d in preset.depression_targets_deg)
        lifted = json.loads((depression_dir / "table3.json").read_text()).get("outside_trained_range", {})
        outside = [
            name
            for name, ranges in lifted.items()
            if not all(
                ranges["trained_d_el_deg"][0] <= d - 17.0 <= ranges["trained_d_el_deg"][1]
                for d in preset.depression_targets_deg
            )
        ]
        warning = (
            f"**{', '.join(outside)} never trained on these depression changes** (trained d_el range "
            f"{lifted[outside[0]]['trained_d_el_deg']} deg): a pipeline refuses such requests; they are "
            "scored here only to measure it. "
            if outside
            else ""
        )
        lines += [
            f"## Depression changes (17 deg inputs, targets at {targets} deg)",
            "",
            "The same models asked for a depression change (and the pair's azimuth change) on simulated "
            f"views of the same vehicles at {targets} deg. `Dep. err.` is the depression regressor's error "
            "on the generated view against the requested depression; `Closer to target dep.` the share of "
            "pairs whose blurred view correlates better with the true view at the requested depression than "
            "with the true view at the input's depression (same target azimuth). " + warning,
            "",
            (depression_dir / "table3.md").read_text(),
            "![depression views](eval_depression/views.png)",
            "",
        ]
    lines += ["## Stage timings", "", "| Stage | seconds |", "| --- | --- |"]
    lines += [f"| {name} | {seconds:.1f} |" for name, seconds in timings.items()]
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    return report


if __name__ == "__main__":
    main()
