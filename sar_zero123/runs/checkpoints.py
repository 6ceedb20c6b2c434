"""Crash-safe training checkpoints on top of ``accelerate``'s ``save_state`` / ``load_state``.

``save_state`` writes in place, so a kill mid-write leaves a folder that looks like a checkpoint. Here each
checkpoint is written to ``checkpoint-<step>.tmp`` and renamed (atomic on POSIX) once every process has
written; ``manifest.json``, written last, holds every file's size and SHA-256, so a checkpoint damaged
after sealing is found and ``latest`` falls back to the newest one that verifies.

Guards: non-finite losses or weights stop a run before they are saved; a resume with settings that
change the run, or past its last step, is refused; :func:`resumable_batches` replays the data order.
Multi-node runs need ``output_dir`` on a shared file system, as accelerate does.
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
    """Save the full training state atomically as ``output_dir/checkpoint-<step>`` (returned); call it on
    every process.

    Args:
        total_limit: Keep at most this many checkpoints (oldest removed after a successful save).
        extra_state: JSON-serialisable script state stored in ``run_state.json``.
        config: The run's config dataclass, stored for :func:`check_resume_config`.

    Raises:
        ValueError: If ``step`` is negative or ``total_limit`` is below 1.
        FloatingPointError: If the training state holds non-finite values (nothing is written).
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
    # 2. every process writes its part; 3. the main process seals the folder (state, then the synced
    #    manifest) and renames it. A failed write removes the partial folder; earlier ones are untouched.
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
    """Why a checkpoint cannot be resumed (naming the file), or ``None`` when it is complete and intact.

    ``check_hashes`` also compares SHA-256 digests, not only sizes. A checkpoint without ``manifest.json``
    passes when it has its ``run_state.json``.
    """
    path = Path(path)
    if not path.is_dir():
        return f"{str(path)!r} is not a folder"
    if not (path / STATE_FILE).is_file():
        return f"{str(path / STATE_FILE)!r} is missing (the checkpoint is incomplete)"
    return manifest_problem(path, check_hashes=check_hashes)


def resolve_resume_checkpoint(output_dir: str | os.PathLike, value: str | None) -> Path | None:
    """Turn ``--resume_from_checkpoint`` (``None``, ``"latest"`` or a folder) into a checkpoint folder.

    ``"latest"`` is the newest checkpoint that verifies, skipping damaged newer ones with a warning, and
    ``None`` when there is none yet, so a first and a restarted run share one command line.

    Raises:
        FileNotFoundError: If an explicit path is not a complete checkpoint, or ``latest`` finds checkpoints
            but none that verifies (starting over would silently discard them).
        ValueError: If an explicit checkpoint fails :func:`verify_checkpoint`.
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
    """Refuse to resume a checkpoint already past the run's last step, before the folder's record changes:
    such a run would train nothing and misrecord ``max_train_steps``.

    Raises:
        ValueError: Naming both steps.
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
        ValueError: If a pickled file holds more than tensors and plain values.
        RuntimeError: If accelerate cannot load it (naming the folder and the files present).
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
    """Refuse a checkpoint whose pickled files hold more than tensors and plain values.

    accelerate unpickles registered objects' states with ``weights_only=False`` (a crafted one runs code) and
    skips unreadable random states with a log line (a resume that is silently not the same run); reading each
    file first with ``weights_only=True`` refuses both. A checkpoint is data.

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
    """The step a run starts at: 0 for a fresh run (``path`` is ``None``), else the restored checkpoint's."""
    if path is None:
        return 0
    step = int(load_checkpoint(accelerator, path)["step"])
    logger.info("resumed from %s at step %d", path, step)
    return step


def _portable(value: Any) -> Any:
    """A bundled component's resolved folder as its place inside the package, so that a run started in one
    install or checkout resumes in another; any other value unchanged."""
    if isinstance(value, str):
        _, marker, tail = value.replace(os.sep, "/").rpartition(_BUNDLED_MARKER)
        if marker:
            return _BUNDLED_MARKER.lstrip("/") + tail
    return value


#: Where the bundled pipelines lie inside the installed package.
_BUNDLED_MARKER = "/sar_zero123/pretrained/"


def check_resume_config(
    path: str | os.PathLike | None,
    config: Any,
    may_differ: Iterable[str] = (),
    renamed: Mapping[str, str] | None = None,
) -> None:
    """Refuse to resume a checkpoint with settings that change the run; call it before writing
    ``config.json``.

    Fields in :data:`RESUME_MAY_DIFFER` and ``may_differ`` may change. A checkpoint without a stored config is
    accepted with a warning; a field its config lacks counts as its default. ``renamed`` maps an old field
    name to this config's.

    Raises:
        ValueError: Listing every differing field with both values, or naming the other script whose
            checkpoint this is.
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
    current = {name: _portable(value) for name, value in config_to_dict(config).items()}
    written = {(renamed or {}).get(name, name): value for name, value in state["config"].items()}
    # a field removed since, at the default its removal keeps, changes nothing; another value is refused
    written = drop_removed_fields(config, written, f"resume_from_checkpoint: {str(path)!r}")
    written = {name: _portable(value) for name, value in written.items()}
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

    For a setting that decides which modules a checkpoint holds; read from the run state, so it also covers
    checkpoints without a config. ``default`` is the value of one that stores no ``name``.

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

    Micro-batch ``i`` is batch ``i % len(loader)`` of epoch ``i // len(loader)``; each epoch calls
    ``set_epoch`` on ``datasets`` and ``loader``, and a resume mid-epoch skips that epoch's first batches, so
    a resumed run sees the batches of an uninterrupted one.

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
    """Stop a diverging run: raise when a named value of a training step (loss, gradient norm) is not finite.

    Pass values equal on every process, so all raise together and none waits in a collective.

    Raises:
        FloatingPointError: Naming the step and each non-finite value.
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
    """Refuse to write weights (modules, ``state_dict`` holders or tensors) that hold NaN or infinite values.

    Raises:
        FloatingPointError: Naming ``what`` and up to five non-finite entries.
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
    """End a run on every process, after the script dropped its own references to prepared models.

    Plain ``end_training`` can deadlock: a DDP wrapper outliving ``destroy_process_group`` lets gloo's
    destructor join its threads while holding the GIL (pytorch/pytorch#56297). Dropping accelerate's
    references first lets the group be freed through a binding that releases the GIL.

    Returns:
        How many ``DistributedDataParallel`` wrappers were still referenced (0 unless the caller kept one;
        a warning is logged otherwise).
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
