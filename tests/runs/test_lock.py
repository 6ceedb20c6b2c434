"""One writer per output folder: a second process is refused, naming the first (issue 39 item 3)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from sar_zero123.runs.folder import finish_run, open_run_folder
from sar_zero123.runs.lock import (
    is_lock_file,
    lock_output_folder,
    lock_path,
    release_output_folder,
)

HOLD = textwrap.dedent(
    """
    import sys, time
    from sar_zero123.runs.folder import open_run_folder
    open_run_folder(sys.argv[1], "demo", {"seed": 0})
    print("held", flush=True)
    time.sleep(60)
    """
)


@pytest.fixture
def holder(tmp_path):
    """A second process that opened ``tmp_path / "run"`` and holds it until killed."""
    process = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(tmp_path / "run")], stdout=subprocess.PIPE, text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    try:
        assert process.stdout.readline().strip() == "held"
        yield process
    finally:
        process.kill()
        process.wait()


def test_a_second_process_is_refused_naming_the_holder_until_it_exits(tmp_path, holder):
    run = tmp_path / "run"
    message = rf"output_dir: '.*run' is being written by process {holder.pid} on .*command: -c .*run\)"
    with pytest.raises(ValueError, match=message):
        open_run_folder(run, "demo", {"seed": 0}, resume=True)
    with pytest.raises(ValueError, match="is being written by"):  # restart must not move it aside either
        open_run_folder(run, "demo", {"seed": 0}, restart=True)
    assert sorted(p.name for p in run.iterdir()) == ["run.json"]  # nothing moved, nothing written
    holder.kill()  # a kill releases the lock: the next writer resumes the folder
    holder.wait()
    folder = open_run_folder(run, "demo", {"seed": 0}, resume=True)
    assert folder.status == "continued"
    finish_run(folder)  # finishing releases the lock and removes its file
    assert not lock_path(run).exists()


def test_the_lock_is_reentrant_lives_beside_the_folder_and_is_skipped_by_emptiness_checks(tmp_path):
    run = tmp_path / "out" / "run"
    lock_output_folder(run)
    lock_output_folder(run)  # the same process again: no refusal
    assert lock_path(run) == tmp_path / "out" / ".run.lock" and lock_path(run).is_file()
    assert not run.exists()  # the folder itself is not created
    assert is_lock_file(lock_path(run)) and not is_lock_file(tmp_path / "run.json")
    folder = open_run_folder(tmp_path / "out", "parent", {"seed": 0})  # a sibling's lock file: still empty
    assert folder.status == "new"
    release_output_folder(run)
    release_output_folder(run)  # not held: a no-op
    assert not lock_path(run).exists()
    release_output_folder(tmp_path / "out")


def test_augment_dataset_refuses_a_second_writer(tmp_path, holder):
    from sar_zero123.augment_dataset import AugmentConfig, augment_dataset
    from sar_zero123.sim import simulate_dataset

    data = simulate_dataset(tmp_path / "data", classes=("TANK",), instances=1, azimuth_step_deg=180,
                            depressions_deg=(17.0,), size=32)  # fmt: skip
    config = AugmentConfig(data=str(data), pipeline="sar-zero123/sim-prior-rotated",
                           out=str(tmp_path / "run"), d_az=[10.0], num_inference_steps=1)  # fmt: skip
    with pytest.raises(ValueError, match=rf"^out: '.*run' is being written by process {holder.pid}"):
        augment_dataset(config)
