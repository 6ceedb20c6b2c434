"""SamplerSettings: the sampler's fields declared once, resolved against a pipeline's record."""

from __future__ import annotations

import dataclasses

import pytest

from sar_zero123.augment_dataset import AugmentConfig
from sar_zero123.generate import GenerateConfig
from sar_zero123.model.sampler import (
    SAMPLER_DEFAULTS,
    SCHEDULERS,
    SamplerSettings,
    describe_sampler,
    resolve_sampler,
    scheduler_name,
    set_scheduler,
)
from sar_zero123.stages.evaluate import EvaluateConfig

SAMPLER_FIELDS = [item.name for item in dataclasses.fields(SamplerSettings)]


def test_every_sampling_command_inherits_the_fields_and_leaves_them_to_the_pipeline() -> None:
    for config in (GenerateConfig, AugmentConfig, EvaluateConfig):
        assert issubclass(config, SamplerSettings)
        fields = {item.name: item for item in dataclasses.fields(config)}
        # declared once: every sampler field's default is None, the pipeline's recorded value
        assert all(fields[name].default is None for name in SAMPLER_FIELDS), config
        assert all(name not in config.__dict__.get("__annotations__", {}) for name in SAMPLER_FIELDS), config


def test_a_field_left_none_is_the_recorded_value_then_the_librarys() -> None:
    recorded = {"num_inference_steps": 20, "heading_guidance_scale": 1.5, "start_from": "proxy",
                "proxy_strength": 0.3}  # fmt: skip
    assert SamplerSettings().resolved(recorded) == {
        "scheduler": None, "num_inference_steps": 20, "guidance_scale": 3.0, "heading_guidance_scale": 1.5,
        "depression_guidance_scale": 0.0, "strength": 0.3, "start_from": "proxy",
    }  # fmt: skip
    # a given value wins; a given strength is never replaced by the recorded proxy strength
    given = SamplerSettings(num_inference_steps=5, strength=0.5, scheduler="euler").resolved(recorded)
    assert (given["num_inference_steps"], given["strength"], given["scheduler"]) == (5, 0.5, "euler")
    # a start from the input does not take the proxy's strength
    assert SamplerSettings(start_from="input").resolved(recorded)["strength"] == 1.0
    # without the input's azimuth a recorded proxy start is the input's, at the recorded strength
    plain = resolve_sampler({}, recorded, input_azimuth_given=False)
    assert (plain["start_from"], plain["strength"]) == ("input", 1.0)
    # a strength left to the record runs at least one of the call's steps; a given one is never changed
    short = {**recorded, "proxy_strength": 0.3}
    assert resolve_sampler({"num_inference_steps": 2}, short)["strength"] == pytest.approx(0.5)
    assert resolve_sampler({"num_inference_steps": 2, "strength": 0.3}, short)["strength"] == 0.3
    # nothing recorded: the library's defaults
    library = SamplerSettings().resolved(None)
    assert {k: library[k] for k in SAMPLER_DEFAULTS if k != "proxy_strength"} == {
        k: v for k, v in SAMPLER_DEFAULTS.items() if k != "proxy_strength"
    }
    assert SamplerSettings(guidance_scale=2.0).sampler_arguments() == {
        "num_inference_steps": None, "guidance_scale": 2.0, "heading_guidance_scale": None,
        "depression_guidance_scale": None, "strength": None, "start_from": None,
    }  # fmt: skip


def test_a_recorded_sampler_is_described_in_words() -> None:
    plain = {"num_inference_steps": 50, "guidance_scale": 3.0, "heading_guidance_scale": 0.0, "strength": 1.0}
    assert describe_sampler(plain) == "50 DDIM steps, guidance 3.0"
    guided = {**plain, "num_inference_steps": 20, "heading_guidance_scale": 1.5, "strength": 0.8,
              "start_from": "turned_input"}  # fmt: skip
    expected = "20 DDIM steps, guidance 3.0, heading guidance 1.5, from the turned input at strength 0.8"
    assert describe_sampler(guided) == expected


def test_a_command_config_passes_its_sampler_whole_and_nothing_else() -> None:
    config = EvaluateConfig(pipeline=["p"], num_inference_steps=4, strength=0.5, scheduler="euler")
    settings = config.sampler_settings()
    assert type(settings) is SamplerSettings  # the command's other fields stay behind
    assert dataclasses.asdict(settings) == {
        "num_inference_steps": 4, "scheduler": "euler", "guidance_scale": None,
        "heading_guidance_scale": None, "depression_guidance_scale": None, "strength": 0.5,
        "start_from": None,
    }  # fmt: skip
    assert settings.sampler_arguments() == config.sampler_arguments()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_inference_steps": 0}, r"num_inference_steps must be an integer in \[1, 1,000\], got 0"),
        ({"num_inference_steps": 2.5}, "num_inference_steps must be an integer"),
        ({"num_inference_steps": True}, "num_inference_steps must be an integer"),
        ({"scheduler": "pndm"}, "scheduler must be one of"),
        ({"guidance_scale": float("nan")}, "guidance_scale must be finite and <= 100"),
        ({"guidance_scale": 1e3}, "guidance_scale must be finite and <= 100"),
        ({"heading_guidance_scale": -1.0}, r"heading_guidance_scale must lie in \[0, 100\]"),
        ({"depression_guidance_scale": float("inf")}, r"depression_guidance_scale must lie in \[0, 100\]"),
        ({"strength": 0.0}, r"strength must lie in \(0, 1\]"),
        ({"strength": 0.1, "num_inference_steps": 5}, "strength 0.1 x num_inference_steps 5 leaves no"),
        ({"start_from": "noise"}, "start_from must be one of"),
    ],
)
def test_bad_values_are_refused_by_name_in_every_command(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        SamplerSettings(**kwargs)
    with pytest.raises(ValueError, match=match):  # the same check, where a command declares its fields
        EvaluateConfig(pipeline=["p"], **kwargs)


def test_scheduler_names_round_trip_and_keep_the_noise_schedule() -> None:
    class Holder:
        scheduler = SCHEDULERS["ddim"][0](num_train_timesteps=1000, beta_schedule="scaled_linear")

    holder = Holder()
    for name in SCHEDULERS:
        set_scheduler(holder, name)
        config = dict(holder.scheduler.config)
        assert scheduler_name(type(holder.scheduler).__name__, config) == name
        assert config["beta_schedule"] == "scaled_linear"
    assert scheduler_name("PNDMScheduler", {}) is None
    SamplerSettings().apply_scheduler(holder)  # None keeps the pipeline's own
    assert scheduler_name(type(holder.scheduler).__name__, dict(holder.scheduler.config)) == "unipc"
    with pytest.raises(ValueError, match="scheduler must be one of"):
        set_scheduler(holder, "pndm")


def test_with_contrasts_sets_the_named_contrast_weights_and_keeps_the_rest() -> None:
    plain = SamplerSettings(num_inference_steps=10, scheduler="ddim", guidance_scale=3.0, strength=0.5)
    guided = plain.with_contrasts(heading=2.0)
    assert dataclasses.asdict(guided) == {**dataclasses.asdict(plain), "heading_guidance_scale": 2.0}
    both = guided.with_contrasts(depression=1.5)
    assert (both.heading_guidance_scale, both.depression_guidance_scale) == (2.0, 1.5)
    assert plain.heading_guidance_scale is None  # a copy: the settings it came from are unchanged
    with pytest.raises(ValueError, match=r"heading_guidance_scale must lie in \[0, 100\], got -1"):
        plain.with_contrasts(heading=-1.0)
