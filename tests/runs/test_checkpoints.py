"""Tests for atomic accelerate checkpoints."""

from __future__ import annotations

import dataclasses
import errno
import json
import re
from pathlib import Path

import pytest
import torch
from accelerate import Accelerator
from accelerate.state import AcceleratorState
from accelerate.utils import DataLoaderConfiguration, set_seed

from sar_zero123.runs.checkpoints import (
    check_finite_step,
    check_resume_config,
    check_resume_state,
    check_resume_steps,
    end_run,
    list_checkpoints,
    load_checkpoint,
    read_run_state,
    resolve_resume_checkpoint,
    resumable_batches,
    resume_step,
    save_checkpoint,
    verify_checkpoint,
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


# ------------------------------------------------------------------------- manifest and latest fallback
def _three_checkpoints(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    for step in (1, 2, 3):
        _step(model, optimizer)
        save_checkpoint(accelerator, tmp_path, step)
    return accelerator


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-1])


def _flip_last_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (_truncate, r"model.safetensors' has \d+ bytes, manifest.json records \d+"),
        (Path.unlink, r"model.safetensors', listed in manifest.json, is missing"),
        (_flip_last_byte, r"model.safetensors' does not match its SHA-256"),
    ],
    ids=["truncated", "deleted", "corrupt"],
)
def test_latest_skips_a_damaged_newest_checkpoint_and_says_why(tmp_path: Path, caplog, damage, reason):
    _three_checkpoints(tmp_path)
    assert verify_checkpoint(tmp_path / "checkpoint-3") is None
    damage(tmp_path / "checkpoint-3" / "model.safetensors")
    with caplog.at_level("WARNING", logger="sar_zero123.runs.checkpoints"):
        assert resolve_resume_checkpoint(tmp_path, "latest").name == "checkpoint-2"
    assert re.search(rf"skipping .*checkpoint-3: .*{reason}", caplog.text)
    with pytest.raises(ValueError, match=reason):  # an explicit path is refused, not skipped
        resolve_resume_checkpoint(tmp_path, str(tmp_path / "checkpoint-3"))


def test_latest_with_no_intact_checkpoint_is_an_error(tmp_path: Path):
    _three_checkpoints(tmp_path)
    for step in (1, 2, 3):
        _truncate(tmp_path / f"checkpoint-{step}" / "optimizer.bin")
    with pytest.raises(FileNotFoundError, match=r"no intact checkpoint .*checkpoint-3: .*optimizer.bin"):
        resolve_resume_checkpoint(tmp_path, "latest")


def test_load_checkpoint_of_another_model_names_the_folder(tmp_path: Path):
    _three_checkpoints(tmp_path)
    AcceleratorState._reset_state(True)
    accelerator = Accelerator(cpu=True)
    model = accelerator.prepare(torch.nn.Linear(5, 2))
    with pytest.raises(RuntimeError, match=r"cannot load .*checkpoint-3.*model.safetensors"):
        load_checkpoint(accelerator, tmp_path / "checkpoint-3")
    del model


# ------------------------------------------------------------------------------------ divergence guards
@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"loss": float("nan")}, "loss=nan"),
        ({"loss": torch.tensor(float("inf"))}, "loss=inf"),
        ({"loss": 1.0, "grad_norm": float("nan")}, "grad_norm=nan"),
    ],
)
def test_check_finite_step_names_the_value_and_step(values, named):
    with pytest.raises(FloatingPointError, match=rf"diverged at step 7: {named}"):
        check_finite_step(7, **values)


def test_check_finite_step_passes_finite_values():
    check_finite_step(1, loss=torch.tensor(0.5), grad_norm=3.0)


def test_save_checkpoint_refuses_nan_weights(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    with torch.no_grad():
        model.weight[0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match=r"refusing to write checkpoint-4: .*model 0.weight"):
        save_checkpoint(accelerator, tmp_path, 4)
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------------- resume settings
@dataclasses.dataclass
class _Config:
    learning_rate: float = 1e-4
    image_size: int | None = None
    output_dir: str = "a"
    max_train_steps: int = 10


@dataclasses.dataclass
class _OtherConfig:
    learning_rate: float = 1e-4


@pytest.mark.parametrize(
    ("changed", "match"),
    [
        ({"learning_rate": 1.0}, r"learning_rate: checkpoint 0.0001, this run 1.0"),
        ({"image_size": 64}, r"image_size: checkpoint None, this run 64"),
        ({"learning_rate": 1.0, "max_train_steps": 5}, r"learning_rate: .*; max_train_steps: .* 5"),
    ],
)
def test_resume_with_changed_settings_is_refused_listing_them(tmp_path: Path, changed, match):
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 1, config=_Config())
    with pytest.raises(ValueError, match=rf"other settings that change the run.*{match}"):
        check_resume_config(path, _Config(**changed))


def test_resume_config_allows_output_settings_and_names_another_script(tmp_path: Path, caplog):
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 1, config=_Config())
    check_resume_config(path, _Config(output_dir="b"))
    check_resume_config(path, _Config(max_train_steps=20), may_differ=("max_train_steps",))
    check_resume_config(None, _Config(learning_rate=5.0))
    with pytest.raises(ValueError, match="written by a _Config run, not a _OtherConfig run"):
        check_resume_config(path, _OtherConfig())
    old = save_checkpoint(accelerator, tmp_path, 2)  # no stored config: accepted with a warning
    with caplog.at_level("WARNING", logger="sar_zero123.runs.checkpoints"):
        check_resume_config(old, _Config(learning_rate=5.0))
    assert "stores no config" in caplog.text


def test_resume_config_compares_a_renamed_field_under_its_new_name(tmp_path: Path):
    @dataclasses.dataclass
    class _Renamed:  # _Config with learning_rate renamed to peak_learning_rate
        peak_learning_rate: float = 1e-4
        image_size: int | None = None
        output_dir: str = "a"
        max_train_steps: int = 10

    _Renamed.__name__ = "_Config"  # the same script, a later version
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 1, config=_Config())
    check_resume_config(path, _Renamed(), renamed={"learning_rate": "peak_learning_rate"})
    with pytest.raises(ValueError, match=r"peak_learning_rate: checkpoint 0.0001, this run 1.0"):
        check_resume_config(path, _Renamed(1.0), renamed={"learning_rate": "peak_learning_rate"})
    with pytest.raises(ValueError, match=r"learning_rate: checkpoint 0.0001, this run '<absent>'"):
        check_resume_config(path, _Renamed())


def test_resume_config_takes_a_bundled_folder_from_another_install(tmp_path: Path):
    @dataclasses.dataclass
    class _Config:  # noqa: N801 (the same script's config, with a bundled component)
        pretrained: str = "/old/site-packages/sar_zero123/pretrained/sim_prior_proxy"

    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 1, config=_Config())
    check_resume_config(path, _Config("/work/checkout/sar_zero123/pretrained/sim_prior_proxy"))
    with pytest.raises(ValueError, match=r"pretrained: checkpoint 'sar_zero123/pretrained/sim_prior_proxy', "
                       r"this run 'sar_zero123/pretrained/sim_prior_rotated'"):
        check_resume_config(path, _Config("/work/checkout/sar_zero123/pretrained/sim_prior_rotated"))
    with pytest.raises(ValueError, match=r"this run '/home/me/sim_prior_proxy'"):
        check_resume_config(path, _Config("/home/me/sim_prior_proxy"))  # a folder of the user's own


def test_check_resume_state_refuses_another_module_setting(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 1, extra_state={"tower": True})
    check_resume_state(path, "tower", True)
    check_resume_state(None, "tower", False)
    with pytest.raises(ValueError, match=r"resume_from_checkpoint: .*-1' was written with tower=True"):
        check_resume_state(path, "tower", False)
    old = save_checkpoint(accelerator, tmp_path, 2)  # written before `tower` was stored
    check_resume_state(old, "tower", False, default=False)
    with pytest.raises(ValueError, match="written with tower=False"):
        check_resume_state(old, "tower", True, default=False)


class _EpochDataset(torch.utils.data.Dataset):
    """Item i of epoch e is 100 * e + i, so a batch shows which epoch's content it came from."""

    def __init__(self, size: int) -> None:
        self.size, self.epoch = size, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, index: int) -> int:
        return 100 * self.epoch + index


def _batches(start: int, stop: int) -> list[tuple[int, int, list[int]]]:
    """Micro-batches start..stop-1 of a fresh run (as start_run builds it: seedable sampler, seeded)."""
    accelerator = Accelerator(cpu=True, dataloader_config=DataLoaderConfiguration(use_seedable_sampler=True))
    set_seed(0)
    dataset = _EpochDataset(7)
    loader = torch.utils.data.DataLoader(dataset, batch_size=2, shuffle=True, drop_last=True)
    loader = accelerator.prepare(loader)  # 3 batches per epoch, order a function of (seed, epoch)
    batches = resumable_batches(accelerator, loader, start, stop, datasets=[dataset])
    return [(index, epoch, batch.tolist()) for index, epoch, batch in batches]


def test_resumable_batches_continue_an_uninterrupted_run():
    full = _batches(0, 8)
    assert [(index, epoch) for index, epoch, _ in full] == [(i, i // 3) for i in range(8)]
    assert all(value // 100 == epoch for _, epoch, batch in full for value in batch)  # datasets' set_epoch
    orders = [[value % 100 for _, _, batch in full[3 * e : 3 * e + 3] for value in batch] for e in (0, 1)]
    assert orders[0] != orders[1]  # the loader's set_epoch: a new order per epoch
    AcceleratorState._reset_state(True)
    assert _batches(4, 8) == full[4:]  # resumed in the middle of epoch 1
    AcceleratorState._reset_state(True)
    assert _batches(8, 8) == []


def test_resume_step_is_zero_for_a_fresh_run_and_the_checkpoint_step_otherwise(tmp_path: Path, caplog):
    accelerator, model, optimizer = _setup()
    assert resume_step(accelerator, None) == 0
    path = save_checkpoint(accelerator, tmp_path, 3)
    with caplog.at_level("INFO", logger="sar_zero123.runs.checkpoints"):
        assert resume_step(accelerator, path) == 3
    assert "resumed from" in caplog.text and "at step 3" in caplog.text


def test_resuming_a_checkpoint_past_max_train_steps_is_refused_naming_both(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 3)
    check_resume_steps(None, 1)  # a fresh run
    check_resume_steps(path, 3)  # finished at the checkpoint (e.g. killed during the export): allowed
    check_resume_steps(path, 5)
    with pytest.raises(ValueError, match=r"^max_train_steps: 2 is below the step of the checkpoint to resume "
                                         r"\('.*checkpoint-3', step 3\); nothing would be trained .*"
                                         r"Resume with max_train_steps >= 3"):  # fmt: skip
        check_resume_steps(path, 2)


def test_a_checkpoint_that_cannot_be_written_is_removed_and_named_keeping_the_earlier(tmp_path, monkeypatch):
    accelerator, model, optimizer = _setup()
    save_checkpoint(accelerator, tmp_path, 1)

    def full_disk(folder: str) -> None:
        (Path(folder) / "model.safetensors").write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(accelerator, "save_state", full_disk)
    named = (r"^\[Errno 28\] could not write '.*checkpoint-2.tmp': No space left on device; the partial "
             r"checkpoint was removed and checkpoint-1 kept; free space and resume with "
             r"--resume_from_checkpoint latest$")
    with pytest.raises(OSError, match=named) as caught:
        save_checkpoint(accelerator, tmp_path, 2)
    assert caught.value.errno == errno.ENOSPC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint-1"]
    assert verify_checkpoint(tmp_path / "checkpoint-1") is None


def test_a_field_added_since_the_checkpoint_counts_as_its_default(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, 1, config=_OtherConfig())  # before the other fields existed
    state_file = Path(path) / "run_state.json"
    state = json.loads(state_file.read_text())
    state["config_class"] = "_Config"  # the same script, an older version of its config
    state_file.write_text(json.dumps(state))
    check_resume_config(path, _Config())  # every new field at its default: the old run's behaviour
    with pytest.raises(ValueError, match=r"image_size: checkpoint None, this run 64"):
        check_resume_config(path, _Config(image_size=64))


class _Counter:
    """A registered object whose state is plain values (as an EMA's is tensors and numbers)."""

    def __init__(self) -> None:
        self.count = 0

    def state_dict(self) -> dict:
        return {"count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.count = state["count"]


class _Payload:
    """A pickle that runs code when it is loaded (writes a marker file)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_checkpoint_whose_custom_state_could_run_code_is_refused_unrun(tmp_path: Path):
    accelerator, model, optimizer = _setup()
    counter = _Counter()
    accelerator.register_for_checkpointing(counter)
    counter.count = 7
    path = save_checkpoint(accelerator, tmp_path, step=1)
    counter.count = 0
    load_checkpoint(accelerator, path)
    assert counter.count == 7  # plain state still resumes
    marker = tmp_path / "ran"
    torch.save(_Payload(marker), path / "custom_checkpoint_0.pkl")
    with pytest.raises(ValueError, match=r"custom_checkpoint_0.pkl' holds more than tensors .*not loaded"):
        load_checkpoint(accelerator, path)
    assert not marker.exists()


@pytest.mark.parametrize("name", ["random_states_0.pkl", "optimizer.bin"])
def test_a_checkpoint_whose_random_or_optimiser_state_is_a_crafted_pickle_is_refused_unrun(tmp_path, name):
    """accelerate reads these with weights_only=True, but skips random states it cannot read with a log line
    only (a resume that is silently another run) and lets an optimiser's unpickling error out raw: both are
    refused by name, before accelerate reads anything."""
    accelerator, model, optimizer = _setup()
    path = save_checkpoint(accelerator, tmp_path, step=1)
    load_checkpoint(accelerator, path)  # the genuine files read under weights_only
    marker = tmp_path / "ran"
    torch.save(_Payload(marker), path / name)
    with pytest.raises(ValueError, match=rf"{re.escape(name)}' holds more than tensors .*not loaded"):
        load_checkpoint(accelerator, path)
    assert not marker.exists()
