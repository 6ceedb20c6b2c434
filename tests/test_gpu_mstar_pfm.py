"""The GPU MSTAR PFM call's pieces that run anywhere: the exact crops it carries, and the stages it plans."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import Image

from benchmarks import gpu_mstar_pfm
from sar_zero123.data.datasets import load_chip
from sar_zero123.data.index import ChipRecord, load_index, write_index
from sar_zero123.stages.evaluate import EvaluateConfig
from sar_zero123.stages.finetune import FinetuneConfig
from sar_zero123.stages.simclr import PretrainSimCLRConfig


def _chips(root, size=(20, 24)):
    """Two classes x two depressions of 8-bit PNG chips larger than the crop, with an index.csv."""
    rng = np.random.default_rng(0)
    root.mkdir(parents=True)
    records = []
    for target_class in ("A", "B"):
        for depression in (15.0, 17.0):
            for i in range(3):
                path = root / f"{target_class}_{int(depression)}_{i}.png"
                Image.fromarray(rng.integers(0, 256, size=size, dtype=np.uint8)).save(path)
                records.append(ChipRecord(path, target_class, f"s{i % 2}", depression, 120.0 * i + 7.5))
    write_index(records, root)
    return root


def test_crops_are_the_pixels_the_stages_read_and_keep_every_record(tmp_path):
    source = _chips(tmp_path / "source")
    gpu_mstar_pfm.write_crops(source, tmp_path / "crops", image_size=16)
    before, after = load_index(source), load_index(tmp_path / "crops")
    assert len(after) == len(before) == 12
    for old, new in zip(before, after):
        assert (new.height, new.width) == (16, 16) and new.path.parent == tmp_path / "crops" / "chips"
        keep = ("target_class", "serial", "depression_deg", "azimuth_deg", "target_type", "source")
        assert [getattr(new, k) for k in keep] == [getattr(old, k) for k in keep]
        np.testing.assert_array_equal(load_chip(new.path, 16), load_chip(old.path, 16))  # exact
    with pytest.raises(ValueError, match="already holds files"):
        gpu_mstar_pfm.write_crops(source, tmp_path / "crops", image_size=16)
    # every other chip of each class, serial and depression in azimuth order (serial s0: 7.5 and 247.5 deg)
    sparse = load_index(gpu_mstar_pfm.write_crops(source, tmp_path / "sparse", image_size=16, every=2).parent)
    assert sorted((r.target_class, r.serial, r.depression_deg, r.azimuth_deg) for r in sparse) == sorted(
        (c, s, d, a) for c in "AB" for d in (15.0, 17.0) for s, a in (("s0", 7.5), ("s1", 127.5))
    )


def test_the_call_runs_the_quickstart_stages_with_its_budget_in_its_order(tmp_path):
    data = _chips(tmp_path / "chips")
    args = gpu_mstar_pfm.build_parser().parse_args([
        "run", "--data", str(data), "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"),
        "--recipe", "smoke", "--protocol", "ood-B",
        "--set", "finetune.train_batch_size=8", "finetune.lr_scheduler=constant",
        "--simclr_minutes", "0.5", "--eval_batch_size", "4",
    ])  # fmt: skip
    plans = gpu_mstar_pfm._gpu_plans(args)
    assert [plan.name for plan in plans] == [
        "simclr", "vae", "evaluators", "base model", "finetune lambda=0", "finetune lambda=4", "evaluate"
    ]
    budgeted = [gpu_mstar_pfm._with_budget(plan, args, 1.25) for plan in plans]
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
    args.set = ["finetune.train_batch_size=8", "finetune.lr_scheduler=cosine"]
    cosine = gpu_mstar_pfm._gpu_plans(args)[5]
    with pytest.raises(ValueError, match="finetune lambda=4: lr_scheduler 'cosine' would decay"):
        gpu_mstar_pfm._with_budget(cosine, args, 1.25)
