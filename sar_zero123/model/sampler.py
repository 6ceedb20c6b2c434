"""How a pipeline samples, declared once: :class:`SamplerSettings`, the library's defaults and their checks.

Every sampling command's config inherits :class:`SamplerSettings` (fields, flags, help, validation). A
field left ``None`` takes the pipeline's recorded ``config.sampler``, else :data:`SAMPLER_DEFAULTS`, so a
command with no sampler option samples as measured best for its pipeline.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

from diffusers import (
    DDIMScheduler,
    DPMSolverMultistepScheduler,
    EulerDiscreteScheduler,
    UniPCMultistepScheduler,
)

__all__ = [
    "EXPORTED_SAMPLER", "MAX_GUIDANCE_SCALE", "MAX_INFERENCE_STEPS", "SAMPLER_DEFAULTS", "SCHEDULERS",
    "START_FROM", "SamplerSettings", "check_sampler_start", "describe_sampler", "resolve_sampler",
    "scheduler_name", "set_scheduler",
]  # fmt: skip

#: Larger guidance scales overflow the guided noise estimate (NaN images); zero-1-to-3 samples with 3.
MAX_GUIDANCE_SCALE = 100.0
#: Most denoising steps per view (the noise schedules have 1,000 training timesteps).
MAX_INFERENCE_STEPS = 1_000
#: The samplers a command may name, each built from the pipeline's scheduler config (its noise schedule).
SCHEDULERS = {
    "ddim": (DDIMScheduler, {}),
    "dpmsolver++": (DPMSolverMultistepScheduler, {"algorithm_type": "dpmsolver++"}),
    "euler": (EulerDiscreteScheduler, {}),
    "unipc": (UniPCMultistepScheduler, {}),
}
#: What an image-to-image call (``strength < 1``) starts from (:meth:`SARZero123Pipeline.__call__`).
START_FROM = ("input", "turned_input", "proxy")
#: The sampler settings a pipeline may record (``SARZero123Pipeline(sampler=...)``) and the library's
#: defaults for the rest; a call's argument overrides both.
SAMPLER_DEFAULTS: dict[str, Any] = {
    "num_inference_steps": 50,
    "guidance_scale": 3.0,
    "strength": 1.0,
    "heading_guidance_scale": 0.0,
    "depression_guidance_scale": 0.0,
    "start_from": "input",
    "proxy_strength": None,  # the strength of a start from the proxy (None: strength)
}


#: What a pipeline exported by this project's training records (a proxy model keeps its prior's sampler):
#: 20 DDIM steps, not zero-1-to-3's 50, which the library keeps for Objaverse checkpoints and the
#: paper-comparable evaluation.
EXPORTED_SAMPLER: dict[str, Any] = {"num_inference_steps": 20}


@dataclass
class SamplerSettings:
    """How a pipeline samples its views: the fields every sampling command's config inherits.

    A field left ``None`` takes the pipeline's recorded value, else :data:`SAMPLER_DEFAULTS`;
    ``scheduler`` ``None`` keeps the pipeline's own. Field names are the flags, so errors name the flag.

    Raises:
        ValueError: Naming the first field out of range.
    """

    num_inference_steps: int | None = None  # denoising steps
    scheduler: Literal["ddim", "dpmsolver++", "euler", "unipc"] | None = None  # None: the pipeline's own
    guidance_scale: float | None = None  # classifier-free guidance weight (<= 1 disables it)
    heading_guidance_scale: float | None = None  # guidance away from the flipped heading (d_az + 180); 0: off
    depression_guidance_scale: float | None = None  # guidance away from the input's depression (d_el = 0)
    strength: float | None = None  # in (0, 1]: below 1, start from a draft noised to this share (SDEdit)
    # the draft a strength < 1 starts from: "input" (the chip), "turned_input" (turned by d_az in the image
    # plane), or "proxy" (a simulator vehicle fitted to the chip at its pose, rendered at the request)
    start_from: Literal["input", "turned_input", "proxy"] | None = None

    def __post_init__(self) -> None:
        steps = self.num_inference_steps
        if steps is not None and (
            isinstance(steps, bool) or int(steps) != steps or not 1 <= steps <= MAX_INFERENCE_STEPS
        ):
            raise ValueError(
                f"num_inference_steps must be an integer in [1, {MAX_INFERENCE_STEPS:,}], got {steps!r}"
            )
        if self.scheduler is not None and self.scheduler not in SCHEDULERS:
            raise ValueError(f"scheduler must be one of {sorted(SCHEDULERS)} or None, got {self.scheduler!r}")
        scale = self.guidance_scale
        if scale is not None and (
            isinstance(scale, bool) or not (math.isfinite(scale) and scale <= MAX_GUIDANCE_SCALE)
        ):
            raise ValueError(f"guidance_scale must be finite and <= {MAX_GUIDANCE_SCALE:g}, got {scale!r}")
        if scale is not None and scale < 0.0:  # a negative weight guides towards the unconditional view
            raise ValueError(f"guidance_scale must be >= 0 (<= 1 turns guidance off), got {scale!r}")
        check_sampler_start(
            self.strength, self.heading_guidance_scale, {"num_inference_steps": steps},
            depression_guidance_scale=self.depression_guidance_scale, start_from=self.start_from,
        )  # fmt: skip

    def sampler_settings(self) -> SamplerSettings:
        """These settings alone, without a command config's other fields."""
        return SamplerSettings(**{item.name: getattr(self, item.name) for item in fields(SamplerSettings)})

    def sampler_arguments(self) -> dict[str, Any]:
        """The pipeline call's sampler arguments: every field but ``scheduler`` (``None``: recorded)."""
        names = [item.name for item in fields(SamplerSettings) if item.name != "scheduler"]
        return {name: getattr(self, name) for name in names}

    def resolved(self, recorded: Mapping[str, Any] | None) -> dict[str, Any]:
        """Every sampler value a call uses given the pipeline's recorded ``config.sampler``, and the
        scheduler."""
        return {"scheduler": self.scheduler, **resolve_sampler(self.sampler_arguments(), recorded)}

    def with_contrasts(
        self, heading: float | None = None, depression: float | None = None
    ) -> SamplerSettings:
        """A copy with the heading and the depression contrast guidance weights set (``None``: kept), for a
        caller that names the contrasts rather than the fields (the augmentation-benefit variant arms)."""
        values = {"heading_guidance_scale": heading, "depression_guidance_scale": depression}
        return replace(self, **{name: value for name, value in values.items() if value is not None})

    def apply_scheduler(self, pipe: Any) -> None:
        """Swaps ``pipe``'s scheduler for ``scheduler`` (:func:`set_scheduler`); ``None`` keeps it."""
        if self.scheduler is not None:
            set_scheduler(pipe, self.scheduler)


def resolve_sampler(
    given: Mapping[str, Any], recorded: Mapping[str, Any] | None, input_azimuth_given: bool = True
) -> dict[str, Any]:
    """The sampler a pipeline call runs: the one place these rules live.

    An argument ``given`` as ``None`` takes the ``recorded`` value, else :data:`SAMPLER_DEFAULTS`'. A
    recorded proxy start falls back to the input without an input azimuth; a proxy start takes the
    recorded ``proxy_strength`` when no strength is given; a recorded strength runs at least one step.

    Returns:
        Every sampler argument's value (``proxy_strength`` excluded).
    """
    recorded = {**SAMPLER_DEFAULTS, **(recorded or {})}
    values = {name: recorded[name] if given.get(name) is None else given[name]
              for name in SAMPLER_DEFAULTS if name != "proxy_strength"}  # fmt: skip
    if values["start_from"] == "proxy" and given.get("start_from") is None and not input_azimuth_given:
        values["start_from"] = "input"  # a recorded proxy start needs the input's pose
    strength_given = given.get("strength") is not None
    if values["start_from"] == "proxy" and not strength_given and recorded["proxy_strength"] is not None:
        values["strength"] = recorded["proxy_strength"]  # a proxy is a nearer draft: less of it is noised
    steps = values["num_inference_steps"]
    if not strength_given and isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1:
        # a recorded strength runs at least one step of a call's own step count (0.3 x 2 steps: 1 step)
        values["strength"] = min(1.0, max(values["strength"], (1.0 + 1e-9) / steps))
    return values


def describe_sampler(values: Mapping[str, Any]) -> str:
    """A sampler in words for a report, e.g. "20 DDIM steps, guidance 3.0, heading guidance 1.5, from the
    input at strength 0.8" (heading guidance only when on, the start only below strength 1).
    """
    text = f"{values['num_inference_steps']} DDIM steps, guidance {values['guidance_scale']}"
    heading = values.get("heading_guidance_scale") or 0.0
    if heading:
        text += f", heading guidance {heading}"
    strength = values.get("strength", 1.0)
    if strength < 1.0:
        text += f", from the {values.get('start_from', 'input').replace('_', ' ')} at strength {strength}"
    return text


def set_scheduler(pipe: Any, name: str) -> None:
    """Swaps the pipeline's sampler for one of :data:`SCHEDULERS`, keeping the noise schedule.

    Raises:
        ValueError: For a name not in :data:`SCHEDULERS`.
    """
    if name not in SCHEDULERS:
        raise ValueError(f"scheduler must be one of {sorted(SCHEDULERS)}, got {name!r}")
    scheduler_class, overrides = SCHEDULERS[name]
    pipe.scheduler = scheduler_class.from_config(pipe.scheduler.config, **overrides)


def scheduler_name(scheduler_class_name: str, config: Mapping[str, Any] | None = None) -> str | None:
    """The :data:`SCHEDULERS` name of a scheduler (its class name and config), or ``None`` for another."""
    for name, (scheduler_class, overrides) in SCHEDULERS.items():
        if scheduler_class.__name__ == scheduler_class_name and all(
            (config or {}).get(key, value) == value for key, value in overrides.items()
        ):
            return name
    return None


def check_sampler_start(
    strength: float | None,
    heading_guidance_scale: float | None,
    steps: Mapping[str, int | None],
    depression_guidance_scale: float | None = 0.0,
    start_from: str | None = "input",
) -> None:
    """Refuse, at a config's boundary, a sampler the pipeline cannot run, naming the field.

    Contrast weights outside [0, ``MAX_GUIDANCE_SCALE``], ``strength`` outside (0, 1] or leaving no step
    of one of ``steps`` (field name: step count), a ``start_from`` not in :data:`START_FROM`. ``None``
    (left to the recorded sampler) is checked by the pipeline at the call.

    Raises:
        ValueError: On any of the above.
    """
    scales = (heading_guidance_scale, depression_guidance_scale)
    _check_contrast_scales(*(0.0 if scale is None else scale for scale in scales), "{}")
    if strength is not None:
        _check_strength(strength, {name: count for name, count in steps.items() if count is not None})
    if start_from is not None and start_from not in START_FROM:
        raise ValueError(f"start_from must be one of {START_FROM}, got {start_from!r}")


def _check_contrast_scales(heading: float, depression: float, name_format: str) -> None:
    """Both contrast weights in [0, ``MAX_GUIDANCE_SCALE``], each named ``name_format.format(name)``.

    Raises:
        ValueError: For a bool, NaN or a weight outside the range.
    """
    for name, scale in (("heading_guidance_scale", heading), ("depression_guidance_scale", depression)):
        if isinstance(scale, bool) or not 0.0 <= scale <= MAX_GUIDANCE_SCALE:  # NaN fails too
            field = name_format.format(name)
            raise ValueError(f"{field} must lie in [0, {MAX_GUIDANCE_SCALE:g}], got {scale}")


def _check_strength(strength: float, steps: Mapping[str, int], prefix: str = "") -> None:
    """``strength`` in (0, 1] leaving at least one denoising step of each of ``steps`` (name: step count)."""
    if isinstance(strength, bool) or not (
        isinstance(strength, numbers.Real) and math.isfinite(strength) and 0.0 < strength <= 1.0
    ):
        raise ValueError(f"{prefix}strength must lie in (0, 1], got {strength!r}")
    for name, count in steps.items():
        if int(count * strength) < 1:
            raise ValueError(
                f"{prefix}strength {strength} x {name} {count} leaves no denoising step; raise either"
            )
