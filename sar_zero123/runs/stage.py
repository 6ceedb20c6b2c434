"""The run-folder rule as every stage and command applies it, on one process or under ``accelerate launch``,
and the withdrawal of a run whose setup failed."""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from accelerate import PartialState
from accelerate.utils import parse_flag_from_env

from sar_zero123.runs.folder import RunFolder, open_run_folder

logger = logging.getLogger(__name__)

__all__ = ["launch_state", "open_stage_folder", "withdrawn_if_setup_fails"]


def launch_state() -> PartialState:
    """The launch's process state, made as ``Accelerator`` makes it: without ``ACCELERATE_USE_CPU`` (set by
    ``accelerate launch --multi_gpu`` on CPU) a bare ``PartialState()`` would set up a one-process run."""
    return PartialState(cpu=parse_flag_from_env("ACCELERATE_USE_CPU"))


def open_stage_folder(
    path: str | os.PathLike,
    stage: str,
    config: Any,
    *,
    data: str | os.PathLike | None | Mapping[str, Any],
    resume: bool,
    restart: bool,
    may_differ: Iterable[str] = (),
    may_extend: Iterable[str] = (),
    resume_hint: str = "--resume_from_checkpoint latest",
    flag_hint: str = "output_dir",
    write: bool = True,
) -> RunFolder:
    """The prologue of every stage and command: :func:`~sar_zero123.runs.folder.open_run_folder` on every
    process of a launch; the main process writes.

    With several processes each first checks the folder as it is on disk, so a refusal stops every process
    before any waits in a collective; then the main process opens it for real while the others wait.

    Args:
        data: The identity of each data input (``{"data": data_identity(config.data)}``), or the data folder
            itself (``None``: the built-in simulator).
        write: ``False`` checks the folder on every process and writes nothing.

    Returns:
        The opened folder (on non-main processes, the check's view).

    Raises:
        ValueError: From ``open_run_folder``, naming the folder and each difference.
    """
    options = dict(data=data, resume=resume, restart=restart, may_differ=tuple(may_differ),
                   may_extend=tuple(may_extend), resume_hint=resume_hint, flag_hint=flag_hint)  # fmt: skip
    if not write:
        return open_run_folder(path, stage, config, write=False, **options)
    state = launch_state()
    folder = None
    if state.num_processes > 1:
        folder = open_run_folder(path, stage, config, write=False, **options)
        state.wait_for_everyone()
    if state.is_main_process:
        folder = open_run_folder(path, stage, config, write=True, **options)
    state.wait_for_everyone()
    return folder


@contextmanager
def withdrawn_if_setup_fails(folder: RunFolder) -> Iterator[None]:
    """Around a stage's setup: a new run whose setup raises leaves nothing it wrote, so the corrected command
    starts it instead of being refused for differing from a run that never began.

    Only a folder opened empty is withdrawn (its lock kept other writers out, so all in it is this setup's);
    a continued run keeps everything.
    """
    try:
        yield
    except BaseException:
        if folder.status == "new" and launch_state().is_main_process:
            _withdraw(folder.path)
        raise


def _withdraw(path: Path) -> None:
    """Remove what a failed setup wrote into ``path`` (a folder opened empty), keeping the folder."""
    if not path.is_dir():
        return
    for entry in path.iterdir():
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
    logger.info("%s: the run failed before it began; its record and setup files were withdrawn", path)
