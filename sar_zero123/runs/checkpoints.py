"""Crash-safe training checkpoints on top of ``accelerate``'s ``save_state`` / ``load_state``.

``Accelerator.save_state`` writes model, optimizer, LR scheduler, sampler, gradient scaler,
registered objects (e.g. an EMA model) and every process's RNG states into one folder, but it
writes in place: a kill in the middle leaves a folder that looks like a checkpoint and is not.
Here every checkpoint is written to ``checkpoint-<step>.tmp`` and renamed to ``checkpoint-<step>``
only when all processes have finished writing (a directory rename is atomic on POSIX file
systems), so ``--resume_from_checkpoint latest`` never picks up a half-written one. The folder holds
``run_state.json`` with the step, the run's config and any script state (epoch, samples seen, ...), and
``manifest.json``, written last, with the size and SHA-256 of every other file: a checkpoint damaged
after it was sealed (a partial copy, a disk that lost unsynced data) is found by :func:`verify_checkpoint`,
and ``latest`` falls back to the newest checkpoint that verifies, logging the ones it skipped.

Divergence guards: :func:`check_finite_step` stops a run on a non-finite loss or gradient norm, and
:func:`save_checkpoint` refuses to write non-finite weights (:func:`check_finite_state`).
Resume guards: :func:`check_resume_config` refuses to resume with settings that change the run,
:func:`check_resume_state` with a setting that changes which modules a checkpoint holds.
Resumed data order: :func:`resumable_batches` draws the micro-batches an uninterrupted run would draw.

Multi-node runs need ``output_dir`` on a file system shared by all nodes, as accelerate does.
:func:`end_run` ends a run without the process-group teardown deadlock described there.
"""

from __future__ import annotations

import gc
import json
import logging
import math
import os
import re
import shutil
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

from sar_zero123.config import drop_removed_fields
from sar_zero123.config.json_io import config_to_dict, write_json_atomic
from sar_zero123.domain import naming_write_errors
from sar_zero123.runs.folder import field_defaults
from sar_zero123.runs.manifest import manifest_problem, write_manifest

logger = logging.getLogger(__name__)

CHECKPOINT_PREFIX = "checkpoint-"
STATE_FILE = "run_state.json"
#: Config fields that may change between a checkpoint and its resumed run: they do not change what is
#: computed (where and how often things are written or logged, the validation samples, the loaders' workers).
RESUME_MAY_DIFFER = (
    "output_dir",
    "resume_from_checkpoint",
    "report_to",
    "checkpointing_steps",
    "checkpoints_total_limit",
    "logging_steps",
    "validation_steps",
    "num_validation_images",
    "validation_inference_steps",
    "num_workers",
    "dataloader_num_workers",  # finetune_pfm's older name for num_workers, in older checkpoints
    "work_dir",
    "save_pipeline",
    "evaluators",  # finetune_pfm: validation-only pose-following check
    "num_eval_images",
    "max_train_minutes",  # finetune_pfm: where this session stops, not what a step computes
)
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
    config: Any | None = None,
) -> Path:
    """Save the full training state atomically as ``output_dir/checkpoint-<step>``.

    Must be called on every process (``save_state`` gathers per-process RNG states). Nothing is written
    when a prepared model or registered object holds a NaN or infinite value.

    Args:
        accelerator: the run's accelerator (models, optimizers, schedulers already prepared).
        output_dir: the run folder.
        step: global optimisation step; names the checkpoint.
        total_limit: keep at most this many checkpoints (oldest removed after a successful save).
        extra_state: JSON-serialisable script state stored in ``run_state.json``.
        config: the run's config dataclass, stored in ``run_state.json`` for :func:`check_resume_config`.

    Returns:
        The path of the finished checkpoint folder.

    Raises:
        ValueError: if ``step`` is negative or ``total_limit`` is below 1.
        FloatingPointError: if the training state holds non-finite values (the run diverged).
    """
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    if total_limit is not None and total_limit < 1:
        raise ValueError(f"total_limit must be >= 1 or None, got {total_limit}")
    check_finite_state(
        {f"model {i}": model for i, model in enumerate(accelerator._models)}
        | {f"registered object {i}": obj for i, obj in enumerate(accelerator._custom_objects)},
        what=f"checkpoint-{step}",
    )
    state = {"step": int(step), **(extra_state or {})}
    if config is not None:
        state.update(config=config_to_dict(config), config_class=type(config).__name__)
    output_dir = Path(output_dir)
    final = output_dir / f"{CHECKPOINT_PREFIX}{step}"
    tmp = output_dir / f"{CHECKPOINT_PREFIX}{step}.tmp"
    # 1. a stale temporary folder from an earlier killed save is garbage
    if accelerator.is_main_process:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    accelerator.wait_for_everyone()
    # 2. every process writes its part; 3. the main process seals the folder (state, then the manifest
    #    of every file, synced to disk) and renames it in one step. A failed write (disk full, a file-size
    #    limit) removes the partial folder and names it; the earlier checkpoints are untouched.
    earlier = [path.name for path in list_checkpoints(output_dir)]
    kept = (
        f"the partial checkpoint was removed and {', '.join(earlier)} kept; free space and resume with "
        "--resume_from_checkpoint latest"
        if earlier
        else "the partial checkpoint was removed (no earlier checkpoint exists)"
    )
    try:
        with naming_write_errors(tmp, kept):
            accelerator.save_state(str(tmp))
            accelerator.wait_for_everyone()
            if accelerator.is_main_process:
                write_json_atomic(state, tmp / STATE_FILE)
                write_manifest(tmp)
                if final.exists():
                    shutil.rmtree(final)
                os.replace(tmp, final)
    except OSError:
        if accelerator.is_main_process:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    if accelerator.is_main_process:
        if total_limit is not None:
            for old in list_checkpoints(output_dir)[:-total_limit]:
                shutil.rmtree(old, ignore_errors=True)
    accelerator.wait_for_everyone()
    return final


def verify_checkpoint(path: str | os.PathLike, check_hashes: bool = True) -> str | None:
    """Why a checkpoint folder cannot be resumed, or ``None`` when it is complete and intact.

    A checkpoint written before manifests existed (no ``manifest.json``) passes when it has its
    ``run_state.json``.

    Args:
        path: the checkpoint folder.
        check_hashes: also compare SHA-256 digests (reads every byte), not only the sizes.

    Returns:
        ``None``, or a sentence naming the file and what is wrong with it.
    """
    path = Path(path)
    if not path.is_dir():
        return f"{str(path)!r} is not a folder"
    if not (path / STATE_FILE).is_file():
        return f"{str(path / STATE_FILE)!r} is missing (the checkpoint is incomplete)"
    return manifest_problem(path, check_hashes=check_hashes)


def resolve_resume_checkpoint(output_dir: str | os.PathLike, value: str | None) -> Path | None:
    """Turn ``--resume_from_checkpoint`` into a checkpoint folder.

    Args:
        output_dir: the run folder searched by ``"latest"``.
        value: ``None`` (start fresh), ``"latest"`` (the newest complete checkpoint in
            ``output_dir`` that passes :func:`verify_checkpoint`, skipping damaged newer ones with a
            logged warning; ``None`` when there is no checkpoint yet, so a first run and a restarted
            run can share one command line), or a path to a checkpoint folder.

    Returns:
        The checkpoint folder, or ``None`` to start from scratch.

    Raises:
        FileNotFoundError: if an explicit path is not a complete checkpoint, or ``latest`` finds
            checkpoints but none that verifies (starting over would silently discard them).
        ValueError: if an explicit checkpoint fails :func:`verify_checkpoint`.
    """
    if value is None or value == "":
        return None
    if value == "latest":
        checkpoints = list_checkpoints(output_dir)
        skipped = []
        for checkpoint in reversed(checkpoints):
            problem = verify_checkpoint(checkpoint)
            if problem is None:
                return checkpoint
            logger.warning("resume_from_checkpoint latest: skipping %s: %s", checkpoint, problem)
            skipped.append(f"{checkpoint.name}: {problem}")
        if skipped:
            raise FileNotFoundError(
                f"resume_from_checkpoint latest: no intact checkpoint in {str(output_dir)!r}; "
                + "; ".join(skipped)
            )
        return None
    path = Path(value)
    if not (path / STATE_FILE).is_file():
        raise FileNotFoundError(
            f"resume_from_checkpoint: {str(path)!r} is not a complete checkpoint folder "
            f"(expected {STATE_FILE} inside, written by save_checkpoint)"
        )
    problem = verify_checkpoint(path)
    if problem is not None:
        raise ValueError(f"resume_from_checkpoint: {problem}")
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


def check_resume_steps(path: str | os.PathLike | None, max_train_steps: int, field: str = "max_train_steps"):
    """Refuse to resume a checkpoint already past the run's last step, before the folder's record changes.

    A resume with ``max_train_steps`` below the checkpoint's step would train nothing, export the later
    checkpoint's weights and record the lower value, misdescribing the run.

    Args:
        path: The checkpoint to resume (:func:`resolve_resume_checkpoint`), or ``None`` (a fresh run).
        max_train_steps: The run's last optimisation step.
        field: The flag's name, for the message.

    Raises:
        ValueError: If the checkpoint's step exceeds ``max_train_steps`` (naming both).
    """
    if path is None:
        return
    step = int(read_run_state(path)["step"])
    if max_train_steps < step:
        raise ValueError(
            f"{field}: {max_train_steps} is below the step of the checkpoint to resume ({str(path)!r}, step "
            f"{step}); nothing would be trained and the record would understate the run. Resume with "
            f"{field} >= {step}, or start a new run in another folder (or --restart) for a shorter one"
        )


def load_checkpoint(accelerator: Accelerator, path: str | os.PathLike) -> dict[str, Any]:
    """Restore a checkpoint written by :func:`save_checkpoint`; returns its ``run_state.json``.

    Raises:
        FileNotFoundError: If the checkpoint has no ``run_state.json``.
        ValueError: If a pickled file of the checkpoint (a registered object's state, the optimiser's, the
            random states) holds more than tensors and plain values (a pickle that could run code, or one
            accelerate would skip unsaid; :func:`_refuse_code_in_pickles`).
        RuntimeError: If accelerate cannot load it (the message names the folder and the files present).
    """
    state = read_run_state(path)
    _refuse_code_in_pickles(path)
    try:
        accelerator.load_state(str(path))
    except (RuntimeError, ValueError, KeyError, OSError, EOFError) as error:
        present = sorted(p.name for p in Path(path).iterdir())
        detail = str(error)
        detail = detail if len(detail) <= 400 else detail[:400] + " ..."
        raise RuntimeError(
            f"resume_from_checkpoint: cannot load {str(path)!r} (files: {present}) into this run's models: "
            f"{type(error).__name__}: {detail}; was it written by another script or model configuration?"
        ) from error
    return state


#: The pickled files accelerate's ``load_state`` reads from a checkpoint folder (weights are safetensors).
_PICKLED_STATE = ("custom_checkpoint_*.pkl", "random_states_*.pkl", "optimizer*.bin", "scheduler*.bin",
                  "sampler*.bin", "dl_state_dict*.bin", "scaler*.pt")  # fmt: skip


def _refuse_code_in_pickles(path: str | os.PathLike) -> None:
    """Refuse a checkpoint whose pickled files (:data:`_PICKLED_STATE`: registered objects' states such as an
    EMA's, the optimiser's and scheduler's, the random states) hold more than tensors and plain values.

    accelerate unpickles registered objects' states with ``weights_only=False``, so a crafted one would run
    code on resume; it reads the others with ``weights_only=True`` but skips random states it cannot read
    with no more than a log line (a resume that is silently not the same run), and an unreadable optimiser
    state surfaces as a raw unpickling error. Each file is read here first with ``weights_only=True``
    (accelerate's own loader, numpy arrays allowed), which refuses any other object before calling it. A
    checkpoint is data.

    Raises:
        ValueError: Naming the file.
    """
    from accelerate.utils import load

    for pattern in _PICKLED_STATE:
        for pickled in sorted(Path(path).glob(pattern)):
            try:
                load(pickled, map_location="cpu")
            except Exception as error:  # noqa: BLE001 (any failure is a refusal; the type is named)
                raise ValueError(
                    f"resume_from_checkpoint: {str(pickled)!r} holds more than tensors and plain values "
                    f"({type(error).__name__}); its pickle could run code, so it is not loaded"
                ) from None


def resume_step(accelerator: Accelerator, path: str | os.PathLike | None) -> int:
    """The optimisation step a run starts at: 0 for a fresh run (``path`` is ``None``), else the step of
    the checkpoint it restores (:func:`load_checkpoint`, logged).

    Raises:
        FileNotFoundError, RuntimeError: From :func:`load_checkpoint`.
    """
    if path is None:
        return 0
    step = int(load_checkpoint(accelerator, path)["step"])
    logger.info("resumed from %s at step %d", path, step)
    return step


def check_resume_config(
    path: str | os.PathLike | None,
    config: Any,
    may_differ: Iterable[str] = (),
    renamed: Mapping[str, str] | None = None,
) -> None:
    """Refuse to resume a checkpoint with settings that change the run.

    Compares ``config`` with the config stored in the checkpoint's ``run_state.json`` by
    :func:`save_checkpoint`. Fields in :data:`RESUME_MAY_DIFFER` and ``may_differ`` may change (e.g.
    where checkpoints go); any other difference would leave the restored optimiser, model or data
    order disagreeing with the ``config.json`` the run writes. Call it before writing ``config.json``.
    A checkpoint without a stored config (older runs) is accepted with a warning. A field the checkpoint's
    config lacks (added to the code since it was written) counts as its default: a new field's default keeps
    the behaviour of the code before it, so only a run that sets it otherwise is refused.

    Args:
        path: the checkpoint folder (``None``: a fresh run, nothing to check).
        config: this run's config dataclass.
        may_differ: further field names that may change for this script.
        renamed: old field name -> this config's name, for fields renamed since checkpoints were written
            (a checkpoint's value under the old name is compared under the new one).

    Raises:
        ValueError: listing every differing field with the checkpoint's and this run's value, or
            naming the other script whose checkpoint this is.
    """
    if path is None:
        return
    state = read_run_state(path)
    if "config" not in state:
        logger.warning("%s stores no config (written by an older version); settings not compared", path)
        return
    written_class = state.get("config_class")
    if written_class is not None and written_class != type(config).__name__:
        raise ValueError(
            f"resume_from_checkpoint: {str(path)!r} was written by a {written_class} run, not a "
            f"{type(config).__name__} run (another script's checkpoint)"
        )
    allowed = set(RESUME_MAY_DIFFER) | set(may_differ)
    current = config_to_dict(config)
    written = {(renamed or {}).get(name, name): value for name, value in state["config"].items()}
    # a field removed since, at the default its removal keeps, changes nothing; another value is refused
    written = drop_removed_fields(config, written, f"resume_from_checkpoint: {str(path)!r}")
    defaults = field_defaults(config)
    written.update({name: defaults[name] for name in set(current) - set(written) if name in defaults})
    differences = [
        f"{name}: checkpoint {written.get(name, '<absent>')!r}, this run {current.get(name, '<absent>')!r}"
        for name in sorted(set(current) | set(written))
        if name not in allowed and current.get(name, "<absent>") != written.get(name, "<absent>")
    ]
    if differences:
        raise ValueError(
            f"resume_from_checkpoint: {str(path)!r} was written with other settings that change the run; "
            f"resume with the checkpoint's values or start a new output_dir. Differences: "
            + "; ".join(differences)
        )


def check_resume_state(path: str | os.PathLike | None, name: str, value: Any, default: Any = None) -> None:
    """Refuse a checkpoint whose ``run_state.json`` records another ``name`` than this run's ``value``.

    For a setting that decides which modules a checkpoint holds (and so which files ``load_state``
    expects); checked from the run state, so also for checkpoints that store no config.

    Args:
        path: The checkpoint folder (``None``: a fresh run, nothing to check).
        name: The key in ``extra_state`` that :func:`save_checkpoint` stored.
        value: This run's value.
        default: The value of a checkpoint that stores no ``name`` (written before it was stored).

    Raises:
        ValueError: Naming the checkpoint and the value it was written with.
    """
    if path is None:
        return
    written = read_run_state(path).get(name, default)
    if written != value:
        raise ValueError(
            f"resume_from_checkpoint: {str(path)!r} was written with {name}={written}; "
            "resume it with the same setting"
        )


def resumable_batches(
    accelerator: Accelerator,
    loader: DataLoader,
    start: int,
    stop: int,
    datasets: Sequence[Any] = (),
) -> Iterator[tuple[int, int, Any]]:
    """Micro-batches ``start`` to ``stop - 1`` of a run that repeats ``loader`` epoch after epoch.

    Micro-batch ``i`` is batch ``i % len(loader)`` of epoch ``i // len(loader)``. Each epoch first calls
    ``set_epoch(epoch)`` on ``datasets`` (e.g. ``ViewPairDataset``'s pairs) and on ``loader`` (accelerate's
    seedable sampler: the order is a function of the seed and the epoch), and a run resumed in the middle of
    an epoch skips that epoch's first batches with ``accelerator.skip_first_batches``. A run resumed at
    ``start`` therefore sees the same batches as an uninterrupted one.

    Args:
        accelerator: The run's accelerator.
        loader: The prepared training data loader.
        start: Index of the first micro-batch (``0``, or the resumed step times the accumulation steps).
        stop: One past the last micro-batch index.
        datasets: Datasets whose content depends on the epoch.

    Yields:
        ``(index, epoch, batch)``.
    """
    index = start
    while index < stop:
        epoch, offset = divmod(index, len(loader))
        for dataset in datasets:
            dataset.set_epoch(epoch)
        loader.set_epoch(epoch)
        for batch in accelerator.skip_first_batches(loader, offset) if offset else loader:
            yield index, epoch, batch
            index += 1
            if index == stop:
                return


# --------------------------------------------------------------------------------------- divergence
def check_finite_step(step: int, **values: float | torch.Tensor) -> None:
    """Stop a diverging run: raise when a value of a training step (loss, gradient norm) is not finite.

    Call it with values that are equal on every process (gathered or reduced), so that every process
    raises together and none waits in a collective. Raising before the next checkpoint means no NaN
    weights are saved or exported.

    Args:
        step: the optimisation step, for the message.
        **values: named scalars (Python numbers or one-element tensors).

    Raises:
        FloatingPointError: naming the step and each non-finite value.
    """
    bad = {name: float(value) for name, value in values.items() if not math.isfinite(float(value))}
    if bad:
        listed = ", ".join(f"{name}={value}" for name, value in bad.items())
        raise FloatingPointError(
            f"training diverged at step {step}: {listed} is not finite; stopped before saving anything from "
            "this step. Lower the learning rate (or clip gradients harder), resume from the last checkpoint"
        )


def _nonfinite_entries(value: Any, prefix: str) -> Iterable[str]:
    if isinstance(value, torch.Tensor):
        if (value.is_floating_point() or value.is_complex()) and not torch.isfinite(value).all():
            yield prefix
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _nonfinite_entries(item, f"{prefix}.{key}")
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            yield from _nonfinite_entries(item, f"{prefix}.{index}")


def check_finite_state(objects: dict[str, Any], what: str) -> None:
    """Refuse to write weights that hold NaN or infinite values.

    Args:
        objects: named modules or objects with a ``state_dict()`` (EMA models), or tensors.
        what: what was about to be written, for the message (``"checkpoint-40"``, ``"pipeline"``).

    Raises:
        FloatingPointError: naming up to five non-finite entries.
    """
    bad: list[str] = []
    for name, obj in objects.items():
        if obj is None:
            continue
        state = obj.state_dict() if hasattr(obj, "state_dict") else obj
        bad.extend(_nonfinite_entries(state, name))
    if bad:
        shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        raise FloatingPointError(
            f"refusing to write {what}: non-finite (NaN or inf) values in {shown}; the run diverged"
        )


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
            "a gloo run may hang at exit (see sar_zero123.runs.checkpoints.end_run)",
            survivors,
        )
    accelerator.end_training()
    return survivors
