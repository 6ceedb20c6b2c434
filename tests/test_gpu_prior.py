"""The GPU prior recipe's pieces that run anywhere: the corpus budget and the returned weights."""

from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path

import pytest
import torch

from benchmarks import gpu_prior
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline


def test_corpus_vehicles_fit_the_budget_at_the_pilot_rate_and_a_written_corpus_keeps_its_number(tmp_path):
    args = gpu_prior.parse_args(["--out", "o", "--work", str(tmp_path), "--evaluators", "e", "--num_vehicles",
                                 "5000", "--corpus_workers", "1", "--views_per_vehicle", "2",
                                 "--corpus_minutes", "1e-4"])  # fmt: skip
    assert gpu_prior.corpus_vehicles(args, tmp_path) == 64  # the floor: any rate fits fewer in 6 ms
    assert not (tmp_path / "corpus_pilot").exists()  # the pilot leaves nothing behind
    (tmp_path / "corpus").mkdir()
    (tmp_path / "corpus" / "corpus.json").write_text(json.dumps({"num_vehicles": 1234}))
    assert gpu_prior.corpus_vehicles(args, tmp_path) == 1234


def test_arms_name_a_condition_input_and_optionally_a_size() -> None:
    assert gpu_prior.parse_arm("global", "medium") == (None, "medium")
    assert gpu_prior.parse_arm("rotated_input@micro", "medium") == ("rotated_input", "micro")
    assert gpu_prior.arm_label("rotated_input@micro") == "rotated_input-micro"  # a name $OUT returns
    for arm in ("rays", "rotated_input@huge"):
        with pytest.raises(ValueError, match=rf"arms: '{arm}' is not <input>\[@<size>\]"):
            gpu_prior.parse_arm(arm, "medium")


def test_packed_parts_restore_the_pipeline_with_a_float16_unet_loading_as_float32(tmp_path):
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    pipe.save_pretrained(tmp_path / "arm" / "pipeline")
    out = tmp_path / "out"
    out.mkdir()
    parts = gpu_prior.pack(tmp_path / "arm" / "pipeline", out, "rotated_input")
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
    args = gpu_prior.parse_args(["--out", "o", "--work", str(tmp_path / "work"), "--evaluators", "e",
                                 "--init", str(start), "--train_batch_size", "2", "--max_train_steps", "1",
                                 "--learning_rate", "1e-30", "--lr_warmup_steps", "0", "--mixed_precision",
                                 "no", "--no-cache_on_device", "--num_workers", "0", "--lr_scheduler",
                                 "cosine"])  # fmt: skip
    pipeline = gpu_prior.train_arm(args, "rotated_input@tiny", corpus, start / "vae", minutes=5.0)
    config = json.loads((pipeline.parent / "config.json").read_text())
    settings = (config["lr_scheduler"], config["max_train_steps"], config["max_train_minutes"])
    assert settings == ("cosine", 1, 5.0)
    trained = SARZero123Pipeline.from_pretrained(pipeline)
    initial = SARZero123Pipeline.from_pretrained(start)
    # a step at a vanishing learning rate leaves the init's weights: the arm started from them, at their size
    before = initial.unet.state_dict()
    for name, value in trained.unet.state_dict().items():
        torch.testing.assert_close(value, before[name], msg=name)
    assert trained.pose_projection.config.spatial_pose == "rotated_input"
    with pytest.raises(ValueError, match=r"takes the condition input 'rotated_input', arm 'global@tiny'"):
        gpu_prior.train_arm(args, "global@tiny", corpus, start / "vae", minutes=5.0)
    assert gpu_prior.init_pipeline("none", None, "global") is None
