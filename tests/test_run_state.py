"""Tests for atomic accelerate checkpoints."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from accelerate import Accelerator

from sar_zero123.run_state import (
    end_run,
    list_checkpoints,
    load_checkpoint,
    read_run_state,
    resolve_resume_checkpoint,
    save_checkpoint,
)


def _setup():
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    optimizer = torch.optim.AdamW(model.parameters(), lr=0.1)
    accelerator = Accelerator(cpu=True)
    model, optimizer = accelerator.prepare(model, optimizer)
    return accelerator, model, optimizer


def _step(model, optimizer):
    loss = model(torch.ones(4, 3)).pow(2).sum()
    loss.backward()
    optimizer.step()
    optimizer.zero_grad()


def test_save_resume_restores_weights_and_rng(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    _step(model, optimizer)
    path = save_checkpoint(accelerator, tmp_path, step=1, extra_state={"epoch": 3})
    assert path.name == "checkpoint-1" and not (tmp_path / "checkpoint-1.tmp").exists()
    expected_weight = model.weight.detach().clone()
    expected_draw = torch.rand(3)
    _step(model, optimizer)
    state = load_checkpoint(accelerator, path)
    assert state == {"step": 1, "epoch": 3}
    torch.testing.assert_close(model.weight, expected_weight, rtol=0, atol=0)
    torch.testing.assert_close(torch.rand(3), expected_draw, rtol=0, atol=0)


def test_total_limit_and_latest_ignore_partial(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    for step in (2, 4, 6):
        save_checkpoint(accelerator, tmp_path, step=step, total_limit=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["checkpoint-4", "checkpoint-6"]
    # a killed save leaves a .tmp folder, and a folder without run_state.json is incomplete
    (tmp_path / "checkpoint-8.tmp").mkdir()
    (tmp_path / "checkpoint-9").mkdir()
    assert resolve_resume_checkpoint(tmp_path, "latest").name == "checkpoint-6"
    assert resolve_resume_checkpoint(tmp_path / "empty", "latest") is None
    assert resolve_resume_checkpoint(tmp_path, None) is None
    with pytest.raises(FileNotFoundError, match="checkpoint-9"):
        resolve_resume_checkpoint(tmp_path, str(tmp_path / "checkpoint-9"))
    with pytest.raises(ValueError, match="total_limit"):
        save_checkpoint(accelerator, tmp_path, step=10, total_limit=0)


def test_read_run_state_and_end_run(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    _step(model, optimizer)
    path = save_checkpoint(accelerator, tmp_path, 3, extra_state={"epoch": 1})
    assert read_run_state(path) == {"step": 3, "epoch": 1}
    with pytest.raises(FileNotFoundError, match="run_state.json"):
        read_run_state(tmp_path)
    # a single process has no data-parallel wrapper; accelerate's references are dropped
    assert end_run(accelerator) == 0
    assert accelerator._models == [] and accelerator._optimizers == []
