"""Runs sized to a device call's budget (stages/budget.py), on the CPU: the corpus that fits, the arms and
their start, the returned weights, and the quickstart's stages under one time limit."""

from __future__ import annotations

import dataclasses
import io
import json
import tarfile
from pathlib import Path

import pytest
import torch
from chip_folders import write_png_chip_folder

from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.stages.budget import (
    affordable_vehicles,
    arm_config,
    arm_label,
    budgeted_plans,
    init_pipeline,
    pack_pipeline,
    parse_arm,
    with_budget,
)
from sar_zero123.stages.evaluate import EvaluateConfig
from sar_zero123.stages.finetune import FinetuneConfig, run_finetune
from sar_zero123.stages.presets import QuickstartConfig
from sar_zero123.stages.simclr import PretrainSimCLRConfig


def test_corpus_vehicles_fit_the_budget_at_the_pilot_rate_and_a_written_corpus_keeps_its_number(tmp_path):
    def affordable():
        return affordable_vehicles(tmp_path, 5000, views_per_vehicle=2, minutes=1e-4, workers=1, seed=0)

    assert affordable() == 64  # the floor: any rate fits fewer in 6 ms
    assert not (tmp_path / "corpus_pilot").exists()  # the pilot leaves nothing behind
    (tmp_path / "corpus").mkdir()
    (tmp_path / "corpus" / "corpus.json").write_text(json.dumps({"num_vehicles": 1234}))
    assert affordable() == 1234


def test_arms_name_a_condition_input_and_optionally_a_size() -> None:
    assert parse_arm("global", "medium") == (None, "medium")
    assert parse_arm("rotated_input@micro", "medium") == ("rotated_input", "micro")
    assert arm_label("rotated_input@micro") == "rotated_input-micro"  # a name $OUT returns
    for arm in ("rays", "rotated_input@huge"):
        with pytest.raises(ValueError, match=rf"arms: '{arm}' is not <input>\[@<size>\]"):
            parse_arm(arm, "medium")


def test_packed_parts_restore_the_pipeline_with_a_float16_unet_loading_as_float32(tmp_path):
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    pipe.save_pretrained(tmp_path / "arm" / "pipeline")
    out = tmp_path / "out"
    out.mkdir()
    parts = pack_pipeline(tmp_path / "arm" / "pipeline", out, "rotated_input")
    assert parts == ["rotated_input.tar.part00"]
    payload = b"".join((out / name).read_bytes() for name in parts)
    with tarfile.open(fileobj=io.BytesIO(payload)) as tar:
        names = tar.getnames()
        tar.extractall(tmp_path / "back", filter="data")
    assert "rotated_input_pipeline/unet/config.json" in names and not any("/vae" in n for n in names)
    restored = tmp_path / "back" / "rotated_input_pipeline"
    pipe.vae.save_pretrained(restored / "vae")  # the vae comes from the package, as the docstring says
    loaded = SARZero123Pipeline.from_pretrained(restored)
    assert loaded.unet.dtype == torch.float32
    assert loaded.pose_projection.config.spatial_pose == "rotated_input"
    for name, value in pipe.unet.state_dict().items():
        torch.testing.assert_close(loaded.unet.state_dict()[name], value.half().float())
    assert Path(restored / "unet").is_dir()


def test_an_arm_starts_from_the_init_pipeline_and_refuses_another_condition_input(tmp_path):
    from sar_zero123.sim.corpus import write_prior_corpus

    start = tmp_path / "start"
    pipe = build_sar_zero123("tiny", seed=3, spatial_pose="rotated_input", input_depression=True)
    pipe.save_pretrained(start)
    corpus = write_prior_corpus(tmp_path / "corpus", num_vehicles=3, views_per_vehicle=3,
                                num_validation_vehicles=1, size=32, progress=False)  # fmt: skip
    prior = {"output_dir": str(tmp_path / "work" / "arm"), "corpus": str(corpus), "vae": str(start / "vae"),
             "train_batch_size": 2, "base_steps": 1, "learning_rate": 1e-30, "mixed_precision": "no"}
    settings = {"lr_scheduler": "cosine", "lr_warmup_steps": 0, "num_workers": 0, "cache_on_device": False}
    arm = arm_config("rotated_input@tiny", 5.0, size="medium", prior=prior, init=str(start), **settings)
    run_finetune(arm)
    pipeline = Path(arm.output_dir) / "pipeline"
    config = json.loads((pipeline.parent / "config.json").read_text())
    recorded = (config["lr_scheduler"], config["max_train_steps"], config["max_train_minutes"])
    assert recorded == ("cosine", 1, 5.0)
    trained = SARZero123Pipeline.from_pretrained(pipeline)
    initial = SARZero123Pipeline.from_pretrained(start)
    # a step at a vanishing learning rate leaves the init's weights: the arm started from them, at their size
    before = initial.unet.state_dict()
    for name, value in trained.unet.state_dict().items():
        torch.testing.assert_close(value, before[name], msg=name)
    assert trained.pose_projection.config.spatial_pose == "rotated_input"
    with pytest.raises(ValueError, match=r"takes the condition input 'rotated_input', arm 'global@tiny'"):
        arm_config("global@tiny", 5.0, size="medium", prior=prior, init=str(start), **settings)
    assert init_pipeline("none", None, "global") is None



def test_the_call_runs_the_quickstart_stages_with_its_budget_in_its_order(tmp_path):
    data = write_png_chip_folder(tmp_path / "chips")
    settings = ["finetune.train_batch_size=8", "finetune.lr_scheduler=constant"]
    config = QuickstartConfig(output_dir=str(tmp_path / "work"), recipe="smoke", data=str(data),
                              protocol="ood-B", lambdas=[0.0, 4.0], set=settings)  # fmt: skip
    plans = budgeted_plans(config)
    assert [plan.name for plan in plans] == [
        "simclr", "vae", "evaluators", "base model", "finetune lambda=0", "finetune lambda=4", "evaluate"
    ]
    budgeted = [with_budget(plan, 1.25, simclr_minutes=0.5, eval_batch_size=4) for plan in plans]
    simclr, finetune, evaluate = budgeted[0].config, budgeted[5].config, budgeted[-1].config
    assert isinstance(simclr, PretrainSimCLRConfig) and simclr.max_train_minutes == 0.5
    assert isinstance(finetune, FinetuneConfig) and finetune.max_train_minutes == 1.25
    assert finetune.train_batch_size == 8 and finetune.cache_on_device and finetune.pfm_weight == 4.0
    # everything else as the quickstart plans it
    planned = plans[5].config
    restored = dataclasses.replace(finetune, max_train_minutes=None, max_train_steps=planned.max_train_steps,
                                   checkpointing_steps=planned.checkpointing_steps, cache_on_device=False)
    assert restored == planned
    assert isinstance(evaluate, EvaluateConfig) and evaluate.steps == [] and evaluate.eval_batch_size == 4
    assert evaluate.pipeline == [str(tmp_path / "work" / f"finetune_lambda{w}" / "pipeline") for w in (0, 4)]
    # a decaying schedule would be spread over the unbounded steps: refused, naming the stage
    cosine = budgeted_plans(dataclasses.replace(config, set=["finetune.train_batch_size=8",
                                                             "finetune.lr_scheduler=cosine"]))[5]  # fmt: skip
    with pytest.raises(ValueError, match="finetune lambda=4: lr_scheduler 'cosine' would decay"):
        with_budget(cosine, 1.25, simclr_minutes=0.5, eval_batch_size=4)
