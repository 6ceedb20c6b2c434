"""The quickstart's recipes, and the run's own config.

A recipe (``sar_zero123/recipes/<name>.yaml`` or a file) is a few sections named after the quickstart's
stages (:data:`RECIPE_SECTIONS`), each holding fields of that stage's config class, merged onto its
defaults; ``shared`` (:class:`SharedSettings`) spans the stages, a nested ``sampler`` section holds a
sampling stage's sampler fields.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from sar_zero123.config import RemovedField, _coerce, _set_value, drop_removed_fields, removed_fields
from sar_zero123.data.splits import OOD_INTERVAL_WIDTH_DEG, check_protocol, ood_validation_intervals
from sar_zero123.model.sampler import SamplerSettings
from sar_zero123.pretrained import SIM_PRIOR_ROTATED, resolve_pretrained
from sar_zero123.stages.corpus import CorpusConfig
from sar_zero123.stages.evaluate import EvaluateConfig
from sar_zero123.stages.evaluators import TrainEvaluatorsConfig
from sar_zero123.stages.finetune import FinetuneConfig
from sar_zero123.stages.simclr import PretrainSimCLRConfig
from sar_zero123.stages.simulate import SimulateConfig
from sar_zero123.stages.vae import TrainVAEConfig
from sar_zero123.yaml_data import read_yaml

__all__ = [
    "DEFAULT_RECIPE", "RECIPES", "RECIPE_DIR", "RECIPE_SECTIONS", "REMOVED_RECIPE_FIELDS",
    "REMOVED_RECIPE_SECTIONS", "QuickstartConfig",
    "Recipe", "SharedSettings", "apply_overrides", "load_recipe", "recipe_names",
]  # fmt: skip


@dataclass(frozen=True)
class SharedSettings:
    """What spans the quickstart's stages (a recipe's ``shared`` section), and which optional stages run.

    Raises:
        ValueError: Naming the field, for a value out of range or a stage that needs a prior without one.
        FileNotFoundError: For a ``prior`` that is not a pipeline folder.
    """

    image_size: int = 64  # chip side in pixels of every stage
    # the pipeline (bundled name or folder) every fine-tune starts from, its VAE kept (the vae and base
    # sections unused); None trains a VAE and a base model from scratch
    prior: str | None = SIM_PRIOR_ROTATED
    mixed_precision: Literal["no", "fp16", "bf16"] = "no"  # accelerate mixed precision, every training stage
    # every training stage's resumable checkpoint interval (the last two kept)
    checkpointing_steps: int = 1000
    # target depressions of a second Table III from simulated 17 deg inputs; () skips it
    depression_targets_deg: tuple[float, ...] = (10.0, 30.0, 45.0)
    # with a prior: a procedural corpus (the corpus section) makes finetune.rehearsal_fraction of each batch
    rehearsal: bool = False

    REMOVED_FIELDS = {
        "decoder_fine_tune": RemovedField(False, "fine-tuning the prior's VAE decoder on the chips (the "
                                          "vae_decoder section) measured no gain in accuracy; the fine-tunes "
                                          "decode with the prior's VAE"),
    }  # fmt: skip

    def __post_init__(self) -> None:
        if isinstance(self.image_size, bool) or self.image_size < 16:
            raise ValueError(f"shared.image_size must be >= 16, got {self.image_size}")
        if isinstance(self.checkpointing_steps, bool) or self.checkpointing_steps < 1:
            raise ValueError(f"shared.checkpointing_steps must be >= 1, got {self.checkpointing_steps}")
        if any(not 0.0 < d < 90.0 for d in self.depression_targets_deg):
            raise ValueError(
                f"shared.depression_targets_deg must lie in (0, 90), got {self.depression_targets_deg}"
            )
        if self.rehearsal and self.prior is None:
            raise ValueError("shared.rehearsal: needs a prior (shared.prior) to fine-tune from")
        if self.prior is not None:
            folder = resolve_pretrained(self.prior)  # an unknown bundled name is refused there
            if not (folder / "model_index.json").is_file():
                raise FileNotFoundError(
                    f"shared.prior: {self.prior!r} is not a pipeline folder (no model_index.json)"
                )


#: A recipe's sections, each by its config class; ``base`` (no prior) is merged onto ``finetune``.
RECIPE_SECTIONS: dict[str, type] = {
    "shared": SharedSettings,
    "simulate": SimulateConfig,
    "simclr": PretrainSimCLRConfig,
    "vae": TrainVAEConfig,
    "corpus": CorpusConfig,
    "finetune": FinetuneConfig,
    "base": FinetuneConfig,
    "evaluators": TrainEvaluatorsConfig,
    "evaluate": EvaluateConfig,
}
#: Removed recipe sections, each with the removed ``shared`` switch it ran behind: where the switch holds
#: its old default the section never ran, so a recipe or a run's record that has it reads as before.
REMOVED_RECIPE_SECTIONS: dict[str, str] = {"vae_decoder": "decoder_fine_tune"}
#: A sampling stage's sampler fields, named ``SECTION.sampler.FIELD`` (a nested section).
SAMPLER_SECTION = "sampler"
_SAMPLER_FIELDS = tuple(item.name for item in dataclasses.fields(SamplerSettings))
#: Removed recipe fields and what replaced each (named when one is refused).
REMOVED_RECIPE_FIELDS: dict[str, str] = {
    "classes": "simulate.classes", "instances": "simulate.instances",
    "azimuth_step_deg": "simulate.azimuth_step_deg", "image_size": "shared.image_size",
    "encoder_cifar_stem": "simclr.cifar_stem and evaluators.cifar_stem",
    "encoder_depths": "simclr.depths and evaluators.depths",
    "encoder_widths": "simclr.hidden_sizes (embedding_size: its first) and evaluators.hidden_sizes",
    "simclr_steps": "simclr.max_train_steps", "simclr_batch_size": "simclr.global_batch_size",
    "vae_widths": "vae.block_out_channels", "vae_norm_groups": "vae.norm_num_groups",
    "vae_steps": "vae.max_train_steps",
    "vae_batch_size": "vae.train_batch_size", "vae_decoder_steps": "shared.decoder_fine_tune",
    "vae_feature_loss_weight": "shared.decoder_fine_tune", "prior": "shared.prior",
    "model_size": "base.size", "estimate_input_azimuth": "base.estimate_input_azimuth",
    "base_steps": "base.max_train_steps", "prediction_type": "base.prediction_type",
    "snr_gamma": "finetune.snr_gamma", "timestep_sampling": "finetune.timestep_sampling",
    "timestep_logit_mean": "finetune.timestep_logit_mean",
    "train_image_encoder": "finetune.train_image_encoder",
    "finetune_steps": "finetune.max_train_steps", "finetune_batch_size": "finetune.train_batch_size",
    "finetune_learning_rate": "finetune.learning_rate", "lr_scheduler": "finetune.lr_scheduler",
    "lr_warmup_steps": "finetune.lr_warmup_steps", "ema_decay": "finetune.use_ema and finetune.ema_decay",
    "pfm_fraction": "finetune.pfm_fraction", "pfm_projection_dim": "finetune.pfm_projection_dim",
    "pfm_balance": "finetune.pfm_balance", "pfm_min_snr": "finetune.pfm_min_snr",
    "rehearsal_vehicles": "corpus.num_vehicles, with shared.rehearsal=true",
    "rehearsal_fraction": "finetune.rehearsal_fraction", "finetune_lora_rank": "finetune.lora_rank",
    "evaluator_epochs": "evaluators.epochs and evaluators.probe_epochs",
    "evaluator_learning_rate": "evaluators.learning_rate", "eval_n": "evaluate.n",
    "eval_steps": "evaluate.sampler.num_inference_steps",
    # eval_strength, eval_start_from and the two contrast guidances' eval_ fields
    **{f"eval_{name}": f"evaluate.sampler.{name}" for name in _SAMPLER_FIELDS
       if name not in ("num_inference_steps", "scheduler", "guidance_scale")},
    "eval_speckle_looks": "evaluate.speckle_looks", "depression_targets_deg": "shared.depression_targets_deg",
    "speed_steps": "evaluate.steps", "speed_n": "evaluate.speed_n", "schedulers": "evaluate.schedulers",
    "checkpointing_steps": "shared.checkpointing_steps", "mixed_precision": "shared.mixed_precision",
}  # fmt: skip
RECIPE_DIR = Path(__file__).resolve().parents[1] / "recipes"
MAX_RECIPE_BYTES = 64 * 1024
#: Most recipes in one chain of ``extends``.
MAX_RECIPE_DEPTH = 8
_RECIPE_SUFFIXES = (".yaml", ".yml", ".json")


def recipe_names() -> list[str]:
    """The bundled recipes' names, sorted."""
    return sorted(path.stem for path in RECIPE_DIR.glob("*.yaml"))


def removed_recipe_field(name: str) -> str | None:
    """The one-line refusal for a removed recipe field (``preset.NAME``, ``STAGE.NAME`` or ``NAME``), or
    ``None`` for a name :data:`REMOVED_RECIPE_FIELDS` does not list."""
    bare = name.rpartition(".")[2]
    if bare not in REMOVED_RECIPE_FIELDS:
        return None
    replacement = REMOVED_RECIPE_FIELDS[bare]
    section, _, field_name = replacement.partition(" ")[0].partition(".")
    gone = removed_fields(RECIPE_SECTIONS.get(section)).get(field_name)
    if gone is not None:  # its replacement was removed since: say why
        return f"{name} was removed: it became {section}.{field_name}, removed too: {gone.reason}"
    return f"{name} was removed: it is now {replacement}"


@functools.cache
def _hints(section: str) -> dict[str, Any]:
    """The fields a section may set, with their types (``sampler.``-prefixed for a sampler's)."""
    cls = RECIPE_SECTIONS[section]
    hints = typing.get_type_hints(cls)
    names = [item.name for item in dataclasses.fields(cls) if item.init]
    if issubclass(cls, SamplerSettings):
        return {(f"{SAMPLER_SECTION}.{n}" if n in _SAMPLER_FIELDS else n): hints[n] for n in names}
    return {name: hints[name] for name in names}


def _typed(section: str, name: str, value: Any) -> Any:
    """``value`` as ``section``'s field ``name`` (``sampler.FIELD`` for a sampler field) takes it.

    Raises:
        ValueError: Naming ``section.name``, for an unknown or removed field, or a value of another type.
    """
    hints = _hints(section)
    gone = removed_fields(RECIPE_SECTIONS[section]).get(name)
    if gone is not None:
        raise ValueError(f"{section}.{name} was removed: {gone.reason}")
    if name not in hints:
        removed = removed_recipe_field(f"{section}.{name}")
        if removed is not None and name not in _SAMPLER_FIELDS:
            raise ValueError(removed)
        if f"{SAMPLER_SECTION}.{name}" in hints:
            raise ValueError(f"{section}.{name}: a sampler field; name it {section}.{SAMPLER_SECTION}.{name}")
        raise ValueError(f"{section}.{name} is not a field of {section}; its fields are {sorted(hints)}")
    return _coerce(f"{section}.{name}", value, hints[name])


def _section_values(where: str, section: str, values: Any) -> dict[str, Any]:
    """A recipe section's mapping, typed; a nested sampler section flattened to ``sampler.FIELD`` keys."""
    if not isinstance(values, dict):
        raise ValueError(f"{where}: {section} must map fields to values, got {values!r}")
    typed: dict[str, Any] = {}
    values = drop_removed_fields(RECIPE_SECTIONS[section], values, section)
    for name, value in values.items():
        nested = f"{SAMPLER_SECTION}.{_SAMPLER_FIELDS[0]}" in _hints(section)
        if name == SAMPLER_SECTION and nested and isinstance(value, dict):
            for inner, item in value.items():
                typed[f"{SAMPLER_SECTION}.{inner}"] = _typed(section, f"{SAMPLER_SECTION}.{inner}", item)
        else:
            typed[name] = _typed(section, name, value)
    return typed


def _recipe_file(recipe: str) -> Path:
    """A bundled recipe's file by name, or a recipe file given by path.

    Raises:
        FileNotFoundError: For a name that is neither a bundled recipe nor a file.
        ValueError: For a file of another suffix, or larger than :data:`MAX_RECIPE_BYTES`.
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


def _recipe_values(recipe: str, seen: tuple[str, ...] = ()) -> dict[str, dict[str, Any]]:
    """Every section's values a recipe sets, merged onto the recipes it extends (a recipe's own values win).

    Raises:
        ValueError: Naming the recipe, for a bad file, section, field or value, or a chain of ``extends``
            that loops or is deeper than :data:`MAX_RECIPE_DEPTH`.
    """
    if recipe in seen or len(seen) >= MAX_RECIPE_DEPTH:
        raise ValueError(f"recipe: the chain of extends {' -> '.join([*seen, recipe])} loops or is too deep")
    path = _recipe_file(recipe)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"recipe {recipe!r}: not valid YAML ({error})") from None
    data = read_yaml(text, f"recipe {recipe!r}")
    if not isinstance(data, dict):
        kind = type(data).__name__
        raise ValueError(f"recipe {recipe!r}: expected a mapping of sections to fields, got {kind}")
    data = dict(data)
    parent = data.pop("extends", None)
    if parent is not None and (not isinstance(parent, str) or parent not in recipe_names()):
        names = ", ".join(recipe_names())
        raise ValueError(f"recipe {recipe!r}: extends must name a bundled recipe ({names}), got {parent!r}")
    values: dict[str, dict[str, Any]] = {}
    for section, mapping in data.items():
        if section in REMOVED_RECIPE_SECTIONS:  # it ran only behind its switch, refused in shared if set
            continue
        if section not in RECIPE_SECTIONS:
            names = mapping if isinstance(mapping, dict) else {}
            removed = [message for name in names if (message := removed_recipe_field(f"{section}.{name}"))]
            if removed:
                raise ValueError(f"recipe {recipe!r}: {removed[0]}")
            raise ValueError(
                f"recipe {recipe!r}: unknown section {section!r}; sections are {list(RECIPE_SECTIONS)}"
            )
        try:
            values[section] = _section_values(f"recipe {recipe!r}", section, mapping)
        except ValueError as error:
            raise ValueError(f"recipe {recipe!r}: {error}") from None
    base = _recipe_values(parent, (*seen, recipe)) if parent is not None else {}
    return {name: {**base.get(name, {}), **values.get(name, {})} for name in RECIPE_SECTIONS}


@dataclass(frozen=True)
class Recipe:
    """A resolved recipe: each section's values (differences from its config class's defaults)."""

    name: str  # the recipe's name or file
    sections: Mapping[str, Mapping[str, Any]]  # section -> field (``sampler.FIELD``) -> value

    def __post_init__(self) -> None:
        SharedSettings(**self.sections["shared"])  # checked with the recipe

    @property
    def shared(self) -> SharedSettings:
        """The ``shared`` section, checked."""
        return SharedSettings(**self.sections["shared"])

    def value(self, section: str, name: str) -> Any:
        """The value ``section`` gives ``name`` (``sampler.FIELD`` too): the recipe's, else its class's
        default (``base`` falls back on ``finetune``)."""
        values = self.sections[section]
        if name in values:
            return values[name]
        if section == "base" and name in self.sections["finetune"]:
            return self.sections["finetune"][name]
        item = {f.name: f for f in dataclasses.fields(RECIPE_SECTIONS[section])}[name.rpartition(".")[2]]
        return item.default if item.default is not dataclasses.MISSING else item.default_factory()  # type: ignore[misc]

    def stage_values(self, section: str, without: Sequence[str] = (), **plumbing: Any) -> dict[str, Any]:
        """The keyword arguments of ``section``'s config: its recipe values but ``without``, and
        ``plumbing`` (what the quickstart itself sets).

        Raises:
            ValueError: For a recipe value the quickstart sets itself.
        """
        own = self.sections[section]
        if section == "base":
            own = {**self.sections["finetune"], **own}
        values = {name.rpartition(".")[2]: value for name, value in own.items()}
        values = {name: value for name, value in values.items() if name not in without}
        taken = sorted(set(values) & set(plumbing))
        if taken:
            raise ValueError(
                f"{section}.{taken[0]} is set by the quickstart itself (from shared, the run's folder or its "
                "flags); leave it out of the recipe"
            )
        return {**values, **plumbing}

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The sections the recipe sets, as written to ``recipe.json`` (sampler fields nested)."""
        out: dict[str, dict[str, Any]] = {}
        for section, values in self.sections.items():
            nested: dict[str, Any] = {}
            for name, value in values.items():
                head, dot, inner = name.partition(".")
                if dot:
                    nested.setdefault(head, {})[inner] = value
                else:
                    nested[name] = list(value) if isinstance(value, tuple) else value
            if nested:
                out[section] = nested
        return out

    def flat(self) -> dict[str, Any]:
        """Every value the recipe sets, one key per field (``SECTION.FIELD``), and every shared setting."""
        shared = {f"shared.{k}": v for k, v in dataclasses.asdict(self.shared).items()}
        return {**shared, **{f"{section}.{name}": value for section, values in self.sections.items()
                             if section != "shared" for name, value in values.items()}}  # fmt: skip


def load_recipe(recipe: str) -> Recipe:
    """The :class:`Recipe` of a bundled recipe (by name) or a recipe file (by path).

    Raises:
        FileNotFoundError: For an unknown name, a missing file or a missing prior.
        ValueError: Naming the recipe and field, for anything :func:`_recipe_values` or
            :class:`SharedSettings` refuses.
    """
    sections = _recipe_values(recipe)
    try:
        return Recipe(recipe, sections)
    except (ValueError, TypeError) as error:
        raise ValueError(f"recipe {recipe!r}: {error}") from None


def apply_overrides(recipe: Recipe, overrides: Sequence[str]) -> Recipe:
    """``recipe`` with the ``SECTION.FIELD=VALUE`` items of ``overrides`` set (values as ``--set`` reads).

    Raises:
        ValueError: Naming the item, for a missing ``=`` or section, an unknown or removed field, or a value
            of another type than the field's.
    """
    sections = {name: dict(values) for name, values in recipe.sections.items()}
    for item in overrides:
        key, separator, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if section in REMOVED_RECIPE_SECTIONS:
            switch = REMOVED_RECIPE_SECTIONS[section]
            reason = SharedSettings.REMOVED_FIELDS[switch].reason
            raise ValueError(f"set: {section} was removed with shared.{switch}: {reason} (in {item!r})")
        if not separator or not dot or section not in RECIPE_SECTIONS:
            removed = removed_recipe_field(key.strip())
            if removed is not None:
                raise ValueError(f"set: {removed} (in {item!r})")
            raise ValueError(
                f"set: expected SECTION.FIELD=VALUE with SECTION one of {', '.join(RECIPE_SECTIONS)}; "
                f"got {item!r}"
            )
        hints = _hints(section)
        try:
            if name not in hints:
                _typed(section, name, None)  # refuses the name, naming a removed field's replacement
        except ValueError as error:
            raise ValueError(f"set: {error} (in {item!r})") from None
        value = _set_value(text.strip().strip("'\""), hints[name], key)  # its refusal names the item
        sections[section][name] = _typed(section, name, value)
    try:
        return Recipe(recipe.name, sections)
    except (ValueError, TypeError) as error:
        raise ValueError(f"set: {error}") from None


RECIPES: dict[str, Recipe] = {name: load_recipe(name) for name in recipe_names()}
DEFAULT_RECIPE = RECIPES["default"]


@dataclass
class QuickstartConfig:
    """Simulate (or read `data`), pretrain SimCLR, fine-tune each lambda, train evaluators, evaluate."""

    output_dir: str = "runs/quickstart"  # run folder (every stage writes a subfolder; report.md at the top)
    # a bundled recipe (sar_zero123/recipes: default, scratch, long, mstar, mstar-prior, proxy, rehearsal,
    # gentle, smoke) or a recipe file of your own (YAML, extends: default)
    recipe: str = "default"
    data: str | None = None  # chip folder (index.csv or raw MSTAR files); None simulates the recipe's classes
    protocol: str | None = None  # "extended" or "ood-<CLASS>"; None = ood-<last simulated class>
    # PFM weights fine-tuned and evaluated side by side; a re-run with more values trains only the new ones
    lambdas: list[float] = field(default_factory=lambda: [0.0, 4.0])
    seed: int = 0  # seed of every stage
    # recipe fields replaced for this run, SECTION.FIELD=VALUE (finetune.max_train_steps=3000,
    # evaluate.sampler.strength=1); recipe.json records the result
    set: list[str] = field(default_factory=list)
    # continue this folder: each stage resumes or is kept; more --lambdas train only the new fine-tunes
    resume: bool = False
    restart: bool = False  # move an existing run in output_dir aside (never deleted) and start over

    REMOVED_FIELDS = {
        "preset": RemovedField(None, "it is now recipe (--recipe NAME)"),
        "override": RemovedField(None, "it is now set (--set SECTION.FIELD=VALUE)"),
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
        recipe = self.resolved_recipe()  # a bad recipe or --set fails before any stage
        if self.data is None and (self.protocol is None or self.protocol.startswith("ood-")):
            _check_simulated_validation_split(recipe.value("simulate", "azimuth_step_deg"), self.seed)
        if self.protocol is not None and check_protocol(self.protocol) == "soc":
            raise ValueError("protocol: the quickstart evaluates 'extended' or 'ood-<CLASS>', got 'soc'")

    def resolved_recipe(self) -> Recipe:
        """The run's settings: the recipe with ``set``'s values (each checked)."""
        return apply_overrides(load_recipe(self.recipe), self.set)


def _check_simulated_validation_split(azimuth_step_deg: float, seed: int) -> None:
    """Refuse a seed whose ``ood-*`` validation intervals hold none of the simulated azimuths."""
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
            f"--seed, or a finer grid (--set simulate.azimuth_step_deg={OOD_INTERVAL_WIDTH_DEG:g} always "
            "works)"
        )


def refuse_old_record(record: Mapping[str, Any] | None, where: str) -> list[str]:
    """Refuse a quickstart run folder whose record holds the removed ``preset.*`` fields, or a removed recipe
    field at another value than its old default, naming the first; returns the record's keys of removed
    fields and sections (``recipe.SECTION.FIELD``), which this run no longer records.
    """
    config = (record or {}).get("config", {})
    old = sorted(key for key in config if key.startswith("preset."))
    if old:
        message = removed_recipe_field(old[0]) or f"{old[0]} was removed"
        raise ValueError(f"{where}: a run of the old recipe fields ({message}); --restart moves it aside")
    gone = []
    for key, value in config.items():
        head, _, rest = key.partition(".")
        section, _, name = rest.partition(".")
        if head == "recipe" and section in REMOVED_RECIPE_SECTIONS:  # checked by its switch, in shared
            gone.append(key)
        elif head == "recipe" and name in removed_fields(RECIPE_SECTIONS.get(section)):
            drop_removed_fields(RECIPE_SECTIONS[section], {name: value}, f"{where}: recipe.{section}")
            gone.append(key)
    return gone
