"""The quickstart's presets: the sizes of each end-to-end run, and the run's own config.

:class:`Preset` holds every size of one run (data, SimCLR, VAE, base model, fine-tunes, evaluators,
evaluation); :data:`PRESETS` names the shipped ones; :class:`QuickstartConfig` is what the user chooses
(a preset, overrides of its fields, the data, the protocol, the PFM weights, the seed). Every field is
checked when the preset is built, in the preset's own names, so a bad ``--set`` fails before the
first stage. :func:`~sar_zero123.stages.quickstart.run_quickstart` runs them.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import logging
import math
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sar_zero123.config import RemovedField
from sar_zero123.data.splits import OOD_INTERVAL_WIDTH_DEG, check_protocol, ood_validation_intervals
from sar_zero123.domain import read_number
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.conditioning import downsampling_factor
from sar_zero123.model.pipeline import START_FROM, check_sampler_start
from sar_zero123.model.sampler import SCHEDULERS
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.sim import TARGET_CLASSES
from sar_zero123.stages.evaluate import MAX_EVALUATION_PAIRS, MAX_SWEEP_STEP_COUNTS
from sar_zero123.training.losses import (
    TRAINED_PREDICTION_TYPES,
    LossSettings,
    check_prediction_type,
)
from sar_zero123.yaml_data import read_yaml

__all__ = [
    "DEFAULT_PRESET", "MAX_EVAL_N", "PRESETS", "RECIPE_DIR", "RECIPE_STAGES", "Preset", "QuickstartConfig",
    "apply_overrides", "load_recipe", "recipe_names",
]  # fmt: skip

logger = logging.getLogger(__name__)

#: Most evaluation pairs a preset may ask for (the evaluation stage's own bound).
MAX_EVAL_N = MAX_EVALUATION_PAIRS


@dataclass(frozen=True)
class Preset:
    """Every setting of one quickstart run, by stage (:data:`RECIPE_STAGES`): a recipe file's values merged
    onto the default recipe's (:func:`load_recipe`; ``sar_zero123/recipes/default.yaml`` sets them all)."""

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
    lr_scheduler: str  # diffusers LR schedule of the base model and of each fine-tune
    lr_warmup_steps: int  # its warm-up steps (each stage)
    ema_decay: float | None  # EMA of the exported UNet (None: the last weights)
    train_image_encoder: bool  # train the (random) CLIP tower with the UNet
    # the base model's training target and loss weighting (finetune_pfm.py's fields of the same names; the
    # fine-tunes inherit the prediction type from the base model's scheduler)
    prediction_type: str  # "epsilon" (zero-1-to-3, the paper) or "v_prediction"
    snr_gamma: float | None  # Min-SNR-gamma weighting of L_simple in every stage (None: unweighted)
    timestep_sampling: str  # training t density of every stage: "uniform" or "logit_normal"
    timestep_logit_mean: float  # logit_normal: mean of logit(t / T) (> 0 favours high noise)
    # every training stage (SimCLR, VAE, base model, fine-tunes) saves a resumable checkpoint every this
    # many steps and keeps the last two; a re-run resumes an interrupted stage from its newest intact one
    checkpointing_steps: int
    # accelerate mixed precision of every training stage ("bf16" on a recent GPU); the evaluation samples
    # in float32 either way
    mixed_precision: str
    # a pretrained pipeline (a bundled name such as "sar-zero123/sim-prior", or a folder) that every fine-tune
    # starts from, as the paper fine-tunes zero-1-to-3: its VAE is kept and no base model is trained
    # (vae_* and base_steps unused); None trains the VAE and a base model from scratch
    prior: str | None
    # target depressions of a second Table III from 17 deg inputs (d_el = target - 17) on a simulated set
    # at 17 deg and these depressions, with a depression regressor among the evaluators; () skips it
    depression_targets_deg: tuple[float, ...]
    # with a prior: fine-tune its VAE's decoder alone (the encoder, hence the latents the prior's UNet knows,
    # kept) this many steps on the training chips, with vae_feature_loss_weight times the feature loss through
    # the SimCLR encoder, before the fine-tunes, which then decode with it; 0 keeps the prior's VAE
    vae_decoder_steps: int
    vae_feature_loss_weight: float
    # the evaluation also scores every view and VAE round trip with speckle re-added (readd_speckle with this
    # many looks: 1 for MSTAR), as rows "<row> + speckle"; None: not
    eval_speckle_looks: int | None
    # how lambda scales PFM in the lambda > 0 fine-tunes (finetune_pfm.py's --pfm_balance: "none" is Eq. 21's
    # fixed weight, "adaptive" makes PFM pull lambda times as hard as L_simple) and where PFM applies
    # (--pfm_min_snr: PFM only where SNR(t) >= this)
    pfm_balance: str
    pfm_min_snr: float
    # rehearsal (with a prior): a corpus of this many procedural vehicles, rendered with the prior's corpus
    # options into rehearsal/corpus (one vehicle held out as its validation class), whose pairs across
    # depressions make rehearsal_fraction of every fine-tune batch, so that the fine-tunes keep the prior's
    # depression requests; 0: the task's pairs only
    rehearsal_vehicles: int
    rehearsal_fraction: float
    # the fine-tunes train rank-r LoRA factors beside the frozen UNet (finetune_pfm.py's --lora_rank, merged
    # at export) instead of every UNet weight; None: every weight trains. It keeps depression requests as
    # a lower learning rate does, no better
    finetune_lora_rank: int | None
    # how both evaluations sample (train/evaluate.py's --heading_guidance_scale and --strength): guidance
    # away from the flipped heading (0: off), and in (0, 1] the share of the steps sampled from the input's
    # noised latent (1: from noise)
    eval_heading_guidance_scale: float
    eval_strength: float
    # what eval_strength < 1 starts from (train/evaluate.py's --start_from): "input", "turned_input", or
    # "proxy", a simulator vehicle fitted to each input at its pose from index.csv and re-rendered at the
    # request
    eval_start_from: str
    # guidance away from the input's depression (train/evaluate.py's --depression_guidance_scale; 0: off):
    # changes only requests with d_el != 0, the depression evaluation's
    eval_depression_guidance_scale: float

    def _check_image_size(self) -> None:
        """The prior exists and the chips fit its VAE and UNet (or ``model_size``'s): checked before any
        stage, since the fine-tunes would refuse them only after SimCLR and the VAE."""
        if self.prior is not None:
            folder = resolve_pretrained(self.prior)  # an unknown bundled name is refused there
            if not (folder / "model_index.json").is_file():
                raise FileNotFoundError(
                    f"prior: {self.prior!r} is not a pipeline folder (no model_index.json)"
                )
            widths = [
                json.loads((folder / part / "config.json").read_text())["block_out_channels"]
                for part in ("vae", "unet")
            ]
            source = f"the prior {self.prior!r}"
        else:
            spec = SAR_ZERO123_SIZES[self.model_size]
            widths = [spec["vae"]["block_out_channels"], spec["unet"]["block_out_channels"]]
            source = f"model_size {self.model_size!r}"
        multiple = downsampling_factor(widths[0]) * downsampling_factor(widths[1])
        if self.image_size % multiple:
            raise ValueError(
                f"image_size must be a multiple of {multiple} for {source} (VAE x UNet downsampling), "
                f"got {self.image_size}"
            )

    def __post_init__(self) -> None:
        # every field checked here, in the preset's own names, so that a bad --set fails before the
        # first stage instead of when its stage starts
        counts = ("instances", "simclr_steps", "simclr_batch_size", "vae_steps", "vae_batch_size",
                  "base_steps", "finetune_steps", "finetune_batch_size", "evaluator_epochs", "eval_steps",
                  "speed_n", "checkpointing_steps")  # fmt: skip
        for name in counts:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        rank = self.finetune_lora_rank
        if rank is not None and (isinstance(rank, bool) or not isinstance(rank, int) or rank < 1):
            raise ValueError(f"finetune_lora_rank must be None or an integer >= 1, got {rank!r}")
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
        # the loss settings a recipe carries are validated by their owner, once
        LossSettings(
            **{
                f.name: getattr(self, f.name)
                for f in dataclasses.fields(LossSettings)
                if hasattr(self, f.name)
            }
        )
        for name in ("finetune_learning_rate", "evaluator_learning_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.encoder_depths or len(self.encoder_depths) != len(self.encoder_widths):
            raise ValueError(
                f"encoder_depths {self.encoder_depths} and encoder_widths {self.encoder_widths} must be "
                "non-empty and of one length"
            )
        steps = self.speed_steps
        if not steps or min(steps) < 1 or len(set(steps)) != len(steps):
            raise ValueError(f"speed_steps must be distinct step counts >= 1, got {self.speed_steps}")
        if len(self.speed_steps) > MAX_SWEEP_STEP_COUNTS:
            raise ValueError(f"speed_steps: at most {MAX_SWEEP_STEP_COUNTS} step counts, got {len(steps)}")
        if self.speed_n > self.eval_n // 2:
            raise ValueError(
                f"speed_n must be <= eval_n // 2 = {self.eval_n // 2} (the speed sweep samples seen pairs), "
                f"got {self.speed_n}"
            )
        if len(set(self.schedulers)) != len(self.schedulers):
            raise ValueError(f"schedulers must be distinct, got {self.schedulers!r}")
        unknown = sorted(set(self.schedulers) - set(SCHEDULERS))
        if not self.schedulers or unknown:
            raise ValueError(f"schedulers: choose from {sorted(SCHEDULERS)}, got {self.schedulers!r}")
        if any(not 0.0 < d < 90.0 for d in self.depression_targets_deg):
            raise ValueError(f"depression_targets_deg must lie in (0, 90), got {self.depression_targets_deg}")
        if self.lr_warmup_steps < 0:
            raise ValueError(f"lr_warmup_steps must be >= 0, got {self.lr_warmup_steps}")
        if self.ema_decay is not None and not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must lie in [0, 1) or be None, got {self.ema_decay}")
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")
        check_prediction_type(self.prediction_type, TRAINED_PREDICTION_TYPES)
        steps = self.vae_decoder_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ValueError(f"vae_decoder_steps must be an integer >= 0, got {steps!r}")
        if steps and self.prior is None:
            raise ValueError(
                "vae_decoder_steps: fine-tunes a prior's decoder; set prior, or train a VAE (vae_steps)"
            )
        if not self.vae_feature_loss_weight >= 0:
            raise ValueError(f"vae_feature_loss_weight must be >= 0, got {self.vae_feature_loss_weight}")
        self._check_image_size()
        vehicles = self.rehearsal_vehicles
        if isinstance(vehicles, bool) or not isinstance(vehicles, int) or vehicles < 0 or vehicles == 1:
            raise ValueError(
                f"rehearsal_vehicles must be 0 (no rehearsal) or an integer >= 2, got {vehicles!r}"
            )
        if vehicles and self.prior is None:
            raise ValueError("rehearsal_vehicles: rehearses a prior's corpus in its fine-tunes; set prior")
        if not 0.0 < self.rehearsal_fraction < 1.0:
            raise ValueError(f"rehearsal_fraction must lie in (0, 1), got {self.rehearsal_fraction}")
        check_sampler_start(self.eval_strength, self.eval_heading_guidance_scale,
                            {"eval_steps": self.eval_steps, "speed_steps": min(self.speed_steps)},
                            prefix="eval_",
                            depression_guidance_scale=self.eval_depression_guidance_scale)  # fmt: skip
        if self.eval_start_from not in START_FROM:
            raise ValueError(f"eval_start_from must be one of {START_FROM}, got {self.eval_start_from!r}")
        looks = self.eval_speckle_looks
        if looks is not None and (isinstance(looks, bool) or not isinstance(looks, int) or looks < 1):
            raise ValueError(f"eval_speckle_looks must be an integer >= 1 or None, got {looks!r}")
        if any(width % self.vae_norm_groups for width in self.vae_widths):
            raise ValueError(
                f"vae_norm_groups {self.vae_norm_groups} must divide each of vae_widths {self.vae_widths}"
            )


#: The bundled recipes (``sar_zero123/recipes/<name>.yaml``): small, diffable YAML files of per-stage values,
#: each merged onto the recipe it ``extends`` (``default`` holds every field).
RECIPE_DIR = Path(__file__).resolve().parents[1] / "recipes"
#: Every :class:`Preset` field under the stage it sizes: a recipe's sections, and ``--set STAGE.FIELD=VALUE``.
RECIPE_STAGES: dict[str, tuple[str, ...]] = {
    "data": ("classes", "instances", "azimuth_step_deg", "image_size"),
    "simclr": ("encoder_cifar_stem", "encoder_depths", "encoder_widths", "simclr_steps", "simclr_batch_size"),
    "vae": ("vae_widths", "vae_norm_groups", "vae_steps", "vae_batch_size", "vae_decoder_steps",
            "vae_feature_loss_weight"),
    "model": ("prior", "model_size", "estimate_input_azimuth", "base_steps", "prediction_type", "snr_gamma",
              "timestep_sampling", "timestep_logit_mean", "train_image_encoder"),
    "finetune": ("finetune_steps", "finetune_batch_size", "finetune_learning_rate", "lr_scheduler",
                 "lr_warmup_steps", "ema_decay", "pfm_fraction", "pfm_projection_dim", "pfm_balance",
                 "pfm_min_snr", "rehearsal_vehicles", "rehearsal_fraction", "finetune_lora_rank"),
    "evaluators": ("evaluator_epochs", "evaluator_learning_rate"),
    "evaluate": ("eval_n", "eval_steps", "eval_heading_guidance_scale", "eval_strength", "eval_start_from",
                 "eval_depression_guidance_scale", "eval_speckle_looks", "depression_targets_deg",
                 "speed_steps", "speed_n", "schedulers"),
    "run": ("checkpointing_steps", "mixed_precision"),
}  # fmt: skip
_STAGE_OF = {name: stage for stage, names in RECIPE_STAGES.items() for name in names}
#: A recipe file is a few kilobytes; a larger one is not a recipe.
MAX_RECIPE_BYTES = 64 * 1024
#: Most recipes in one chain of ``extends``.
MAX_RECIPE_DEPTH = 8
_RECIPE_SUFFIXES = (".yaml", ".yml", ".json")


def recipe_names() -> list[str]:
    """The bundled recipes' names, sorted."""
    return sorted(path.stem for path in RECIPE_DIR.glob("*.yaml"))


def _typed(name: str, value: Any) -> Any:
    """``value`` as field ``name`` of :class:`Preset` takes it (a list becomes a tuple, an int a float).

    Raises:
        ValueError: Naming the field, for a value of another type.
    """
    annotation = typing.get_type_hints(Preset)[name]
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    allowed = typing.get_args(annotation) if union else (annotation,)
    if value is None and type(None) in allowed:
        return None
    for kind in allowed:
        if typing.get_origin(kind) is tuple:
            item = typing.get_args(kind)[0]
            if isinstance(value, list | tuple) and all(_is_a(v, item) for v in value):
                return tuple(float(v) if item is float else v for v in value)
        elif kind is not type(None) and _is_a(value, kind):
            return float(value) if kind is float else value
    raise ValueError(f"{name} takes {_type_name(annotation)}, got {value!r}")


def _is_a(value: Any, kind: type) -> bool:
    """``value`` is a ``kind`` (a bool is not a number; an int is a float)."""
    if isinstance(value, bool):
        return kind is bool
    if kind is float:
        return isinstance(value, int | float) and math.isfinite(value)  # YAML reads .inf and 1e999 as inf
    return isinstance(value, kind)


def _type_name(annotation: Any) -> str:
    return str(annotation).replace("typing.", "").replace("<class '", "").replace("'>", "")


def _recipe_file(recipe: str) -> Path:
    """A bundled recipe's file by name, or a recipe file given by path.

    Raises:
        FileNotFoundError: For a name that is neither a bundled recipe nor a file.
        ValueError: For a file that is not ``.yaml``/``.yml``/``.json``, or larger than
            :data:`MAX_RECIPE_BYTES`.
    """
    if recipe in recipe_names():
        return RECIPE_DIR / f"{recipe}.yaml"
    path = Path(recipe)
    if not path.is_file():
        raise FileNotFoundError(
            f"recipe: {recipe!r} is neither a bundled recipe ({', '.join(recipe_names())}) nor a file"
        )
    if path.suffix.lower() not in _RECIPE_SUFFIXES:
        raise ValueError(f"recipe: expected a {'/'.join(_RECIPE_SUFFIXES)} file, got {recipe!r}")
    if path.stat().st_size > MAX_RECIPE_BYTES:
        raise ValueError(f"recipe: {recipe!r} holds {path.stat().st_size:,} bytes, more than a recipe's "
                         f"{MAX_RECIPE_BYTES:,}")  # fmt: skip
    return path


def _recipe_values(recipe: str, seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """Every field a recipe sets, merged onto the recipes it extends (a recipe's own values win).

    Raises:
        ValueError: Naming the recipe, for a file that is not a mapping of stages to fields, an unknown stage
            or field, a field under another stage than its own, a field given twice, or a chain of
            ``extends`` that loops or is deeper than :data:`MAX_RECIPE_DEPTH`.
    """
    if recipe in seen or len(seen) >= MAX_RECIPE_DEPTH:
        raise ValueError(f"recipe: the chain of extends {' -> '.join([*seen, recipe])} loops or is too deep")
    path = _recipe_file(recipe)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"recipe {recipe!r}: not valid YAML ({error})") from None
    data = read_yaml(text, f"recipe {recipe!r}")  # data only: no tags, aliases, deep nesting or repeats
    if not isinstance(data, dict):
        kind = type(data).__name__
        raise ValueError(f"recipe {recipe!r}: expected a mapping of stages to fields, got {kind}")
    data = dict(data)
    parent = data.pop("extends", None)
    if parent is not None and (not isinstance(parent, str) or parent not in recipe_names()):
        names = ", ".join(recipe_names())
        raise ValueError(f"recipe {recipe!r}: extends must name a bundled recipe ({names}), got {parent!r}")
    values: dict[str, Any] = {}
    for stage, section in data.items():
        if stage not in RECIPE_STAGES:
            raise ValueError(f"recipe {recipe!r}: unknown stage {stage!r}; stages are {list(RECIPE_STAGES)}")
        if not isinstance(section, dict):
            raise ValueError(f"recipe {recipe!r}: {stage} must map fields to values, got {section!r}")
        for name, value in section.items():
            if _STAGE_OF.get(name) != stage:
                where = f"; it belongs under {_STAGE_OF[name]}" if name in _STAGE_OF else ""
                raise ValueError(f"recipe {recipe!r}: {stage}.{name} is not a field of {stage}{where}")
            values[name] = _typed(name, value)
    base = _recipe_values(parent, (*seen, recipe)) if parent is not None else {}
    return {**base, **values}


def load_recipe(recipe: str) -> Preset:
    """The :class:`Preset` of a bundled recipe (by name) or a recipe file (by path), checked.

    Raises:
        FileNotFoundError: For an unknown name or a missing file.
        ValueError: Naming the recipe and field, for anything :func:`_recipe_values` or :class:`Preset`
            refuses, or a recipe that leaves a field unset (extend ``default``, which sets them all).
    """
    values = _recipe_values(recipe)
    missing = [f.name for f in dataclasses.fields(Preset) if f.name not in values]
    if missing:
        raise ValueError(f"recipe {recipe!r}: no value for {missing}; add extends: default")
    try:
        return Preset(**values)
    except ValueError as error:
        raise ValueError(f"recipe {recipe!r}: {error}") from None


#: The bundled recipes, loaded: each a checked :class:`Preset`.
PRESETS: dict[str, Preset] = {name: load_recipe(name) for name in recipe_names()}
DEFAULT_PRESET = PRESETS["default"]


@dataclass
class QuickstartConfig:
    """Simulate (or read `data`), pretrain SimCLR, fine-tune each lambda, train evaluators, evaluate."""

    output_dir: str = "runs/quickstart"  # run folder (every stage writes a subfolder; report.md at the top)
    # a bundled recipe (sar_zero123/recipes: default, the bundled prior fine-tuned on the simulator; scratch;
    # long; mstar, real data from scratch; mstar-prior, real data from the prior, the paper's regime; proxy;
    # rehearsal; gentle; smoke, seconds) or a recipe file of your own (YAML, extends: default)
    recipe: str = "default"
    data: str | None = None  # chip folder (index.csv or raw MSTAR files); None simulates the recipe's classes
    protocol: str | None = None  # "extended" or "ood-<CLASS>"; None = ood-<last simulated class>
    # PFM weights fine-tuned from the base model and evaluated side by side (a lambda sweep: 0 1 4 16);
    # a re-run in the same folder with more values trains only the new ones
    lambdas: list[float] = field(default_factory=lambda: [0.0, 4.0])
    seed: int = 0  # seed of every stage
    # recipe fields replaced for this run, [STAGE.]FIELD=VALUE with a Python literal (finetune.finetune_steps=
    # 3000, lr_scheduler=cosine, vae_widths=16,32,64); the run's preset.json records the result
    set: list[str] = field(default_factory=list)
    # continue this folder: an interrupted run resumes each stage, a finished one is kept, and more --lambdas
    # train only the new fine-tunes (then every lambda is evaluated again on the same pairs)
    resume: bool = False
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over

    #: Removed fields: a flag, a ``--config`` file or a run folder's ``config.json`` that sets one is refused
    #: in one line naming the field that replaced it.
    REMOVED_FIELDS = {
        "preset": RemovedField(None, "it is now recipe (--recipe NAME)"),
        "override": RemovedField(None, "it is now set (--set STAGE.FIELD=VALUE)"),
    }

    def __post_init__(self) -> None:
        if self.resume and self.restart:
            raise ValueError("resume and restart: choose one (continue this run, or move it aside)")
        if not self.lambdas or min(self.lambdas) < 0 or len(set(self.lambdas)) != len(self.lambdas):
            raise ValueError(f"lambdas must be distinct values >= 0, got {self.lambdas}")
        if self.data is not None and not Path(self.data).is_dir():
            raise FileNotFoundError(f"data: expected a chip folder, got {self.data}")
        if self.data is not None and self.protocol is None:
            raise ValueError("protocol: give 'extended' or 'ood-<CLASS>' with --data (e.g. ood-T72)")
        preset = self.preset()  # a bad recipe or --set fails before any stage
        if self.data is None and (self.protocol is None or self.protocol.startswith("ood-")):
            _check_simulated_validation_split(preset.azimuth_step_deg, self.seed)
        if self.protocol is not None and check_protocol(self.protocol) == "soc":
            # evaluate.py pairs seen/unseen views by `extended` or `ood-*`: fail here, not after training
            raise ValueError("protocol: the quickstart evaluates 'extended' or 'ood-<CLASS>', got 'soc'")

    def preset(self) -> Preset:
        """The run's settings: the recipe with ``set``'s values (each checked)."""
        return apply_overrides(load_recipe(self.recipe), self.set)


def _check_simulated_validation_split(azimuth_step_deg: float, seed: int) -> None:
    """Refuse a seed whose ``ood-*`` validation intervals hold none of the simulated azimuths (``k * step``):
    the split would be empty and the run would fail after simulation and SimCLR."""
    if not azimuth_step_deg > 0:  # the simulator's own check names it
        return
    intervals = ood_validation_intervals(seed)
    count = math.ceil(360.0 / azimuth_step_deg - 1e-9)

    def holds_one(start: float, end: float) -> bool:  # the first k * step >= start, without listing them all
        first = max(0, math.ceil(start / azimuth_step_deg) - 1)  # one lower: the division may round up
        return any(k < count and start <= k * azimuth_step_deg < end for k in range(first, first + 3))

    if not any(holds_one(start, end) for start, end in intervals):
        starts = ", ".join(f"{start:g}" for start, _ in intervals)
        raise ValueError(
            f"seed: the ood protocol's validation split holds the azimuths of {len(intervals)} "
            f"{OOD_INTERVAL_WIDTH_DEG:g}-deg intervals drawn with --seed {seed} (starting at {starts} deg), "
            f"and no simulated chip lies in them with azimuth_step_deg={azimuth_step_deg:g}: choose another "
            f"--seed, or a finer grid (--set azimuth_step_deg={OOD_INTERVAL_WIDTH_DEG:g} always works)"
        )


def _check_plain_numbers(text: str) -> None:
    """Refuse a number of a Python literal not written plainly (:func:`~sar_zero123.domain.read_number`):
    ``literal_eval`` reads ``1_0`` as 10, ``0x10`` as 16 and ``1j`` as a complex number."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError:
        return  # a bare word
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and type(node.value) in (int, float, complex):
            written = ast.get_source_segment(text.strip(), node) or ""
            read_number(written, integer=type(node.value) is int)


def apply_overrides(preset: Preset, overrides: Sequence[str]) -> Preset:
    """`preset` with the `[STAGE.]FIELD=VALUE` items of `overrides` replaced (`VALUE` a Python literal; a bare
    word is a string; a list becomes a tuple); the preset's own checks run on the result.

    Raises:
        ValueError: naming the item, for an unknown field, a stage the field is not under, a missing ``=``,
            or a value of another type than the field's (an int is accepted for a float field).
    """
    changes: dict[str, Any] = {}
    for item in overrides:
        key, separator, text = item.partition("=")
        stage, dot, name = key.rpartition(".")
        if not separator or name not in _STAGE_OF or (dot and _STAGE_OF[name] != stage):
            raise ValueError(
                f"set: expected [STAGE.]FIELD=VALUE with FIELD one of {sorted(_STAGE_OF)} under its stage "
                f"({', '.join(RECIPE_STAGES)}); got {item!r}"
            )
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text  # a bare word: lr_scheduler=cosine
        try:
            _check_plain_numbers(text)
            changes[name] = _typed(name, value)
        except ValueError as error:
            raise ValueError(f"set: {error} (in {item!r})") from None
    return dataclasses.replace(preset, **changes)
