"""Crash-safe training checkpoints on top of ``accelerate``'s ``save_state`` / ``load_state``.

``Accelerator.save_state`` writes model, optimizer, LR scheduler, sampler, gradient scaler,
registered objects (e.g. an EMA model) and every process's RNG states into one folder, but it
writes in place: a kill in the middle leaves a folder that looks like a checkpoint and is not.
Here every checkpoint is written to ``checkpoint-<step>.tmp`` and renamed to ``checkpoint-<step>``
only when all processes have finished writing (a directory rename is atomic on POSIX file
systems), so ``--resume_from_checkpoint latest`` never picks up a broken one. The folder holds
``run_state.json`` with the step and any script state (epoch, samples seen, ...).

Multi-node runs need ``output_dir`` on a file system shared by all nodes, as accelerate does.
:func:`end_run` ends a run without the process-group teardown deadlock described there.
"""

from __future__ import annotations

import gc
import json
import logging
import os
import re
import shutil
from pathlib import Path
from typing import Any

from accelerate import Accelerator
from torch.nn.parallel import DistributedDataParallel

from sar_zero123.config import write_json_atomic

logger = logging.getLogger(__name__)

CHECKPOINT_PREFIX = "checkpoint-"
STATE_FILE = "run_state.json"
_CHECKPOINT_RE = re.compile(rf"^{CHECKPOINT_PREFIX}(\d+)$")


def list_checkpoints(output_dir: str | os.PathLike) -> list[Path]:
    """Complete checkpoints under ``output_dir``, oldest step first (temporary folders excluded)."""
    output_dir = Path(output_dir)
    if not output_dir.is_dir():
        return []
    found = []
    for child in output_dir.iterdir():
        match = _CHECKPOINT_RE.match(child.name)
        if match and child.is_dir() and (child / STATE_FILE).is_file():
            found.append((int(match.group(1)), child))
    return [path for _, path in sorted(found)]


def save_checkpoint(
    accelerator: Accelerator,
    output_dir: str | os.PathLike,
    step: int,
    total_limit: int | None = None,
    extra_state: dict[str, Any] | None = None,
) -> Path:
    """Save the full training state atomically as ``output_dir/checkpoint-<step>``.

    Must be called on every process (``save_state`` gathers per-process RNG states).

    Args:
        accelerator: the run's accelerator (models, optimizers, schedulers already prepared).
        output_dir: the run folder.
        step: global optimisation step; names the checkpoint.
        total_limit: keep at most this many checkpoints (oldest removed after a successful save).
        extra_state: JSON-serialisable script state stored in ``run_state.json``.

    Returns:
        The path of the finished checkpoint folder.

    Raises:
        ValueError: if ``step`` is negative or ``total_limit`` is below 1.
    """
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    if total_limit is not None and total_limit < 1:
        raise ValueError(f"total_limit must be >= 1 or None, got {total_limit}")
    output_dir = Path(output_dir)
    final = output_dir / f"{CHECKPOINT_PREFIX}{step}"
    tmp = output_dir / f"{CHECKPOINT_PREFIX}{step}.tmp"
    # 1. a stale temporary folder from an earlier killed save is garbage
    if accelerator.is_main_process:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    accelerator.wait_for_everyone()
    # 2. every process writes its part
    accelerator.save_state(str(tmp))
    accelerator.wait_for_everyone()
    # 3. the main process seals the folder and renames it in one step
    if accelerator.is_main_process:
        write_json_atomic({"step": int(step), **(extra_state or {})}, tmp / STATE_FILE)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        if total_limit is not None:
            for old in list_checkpoints(output_dir)[:-total_limit]:
                shutil.rmtree(old, ignore_errors=True)
    accelerator.wait_for_everyone()
    return final


def resolve_resume_checkpoint(output_dir: str | os.PathLike, value: str | None) -> Path | None:
    """Turn ``--resume_from_checkpoint`` into a checkpoint folder.

    Args:
        output_dir: the run folder searched by ``"latest"``.
        value: ``None`` (start fresh), ``"latest"`` (the newest complete checkpoint in
            ``output_dir``, or ``None`` when there is none yet, so a first run and a restarted
            run can share one command line), or a path to a checkpoint folder.

    Returns:
        The checkpoint folder, or ``None`` to start from scratch.

    Raises:
        FileNotFoundError: if an explicit path is not a complete checkpoint.
    """
    if value is None or value == "":
        return None
    if value == "latest":
        checkpoints = list_checkpoints(output_dir)
        return checkpoints[-1] if checkpoints else None
    path = Path(value)
    if not (path / STATE_FILE).is_file():
        raise FileNotFoundError(
            f"resume_from_checkpoint: {str(path)!r} is not a complete checkpoint folder "
            f"(expected {STATE_FILE} inside, written by save_checkpoint)"
        )
    return path


def read_run_state(path: str | os.PathLike) -> dict[str, Any]:
    """The ``run_state.json`` of a checkpoint written by :func:`save_checkpoint`, without loading it.

    Raises:
        FileNotFoundError: If the checkpoint has no ``run_state.json`` (it is incomplete).
    """
    state_file = Path(path) / STATE_FILE
    if not state_file.is_file():
        raise FileNotFoundError(f"checkpoint {str(path)!r} has no {STATE_FILE}; it is incomplete")
    with state_file.open() as handle:
        return json.load(handle)


def load_checkpoint(accelerator: Accelerator, path: str | os.PathLike) -> dict[str, Any]:
    """Restore a checkpoint written by :func:`save_checkpoint`; returns its ``run_state.json``."""
    state = read_run_state(path)
    accelerator.load_state(str(path))
    return state


def end_run(accelerator: Accelerator) -> int:
    """End a run: drop accelerate's references to the prepared objects, then end the trackers and
    destroy the process group (``Accelerator.end_training``). Call it on every process, after deleting
    the script's own references to prepared (data-parallel wrapped) models.

    Why not just ``end_training``: a DDP wrapper's Reducer holds the process group. If the wrapper
    outlives ``destroy_process_group``, the Reducer later drops the last reference, and gloo's
    destructor joins its worker threads while holding the GIL; a worker that is still freeing a
    finished collective's tensors needs the GIL, so both wait forever (pytorch/pytorch#56297). It hung
    about 1 run in 10 of two-process CPU runs here, after all work was done. Released while the group is
    still registered, the wrappers only decrement its count, and ``destroy_process_group`` frees it
    through a binding that releases the GIL.

    Returns:
        How many ``DistributedDataParallel`` wrappers were still referenced after accelerate's were
        dropped (0 when the caller released its own; a warning is logged otherwise).
    """
    accelerator.free_memory()  # clears accelerate's lists of prepared objects and runs gc.collect()
    survivors = sum(issubclass(type(item), DistributedDataParallel) for item in gc.get_objects())
    if survivors:
        logger.warning(
            "%d DistributedDataParallel wrapper(s) still referenced when the process group is destroyed; "
            "a gloo run may hang at exit (see sar_zero123.run_state.end_run)",
            survivors,
        )
    accelerator.end_training()
    return survivors
