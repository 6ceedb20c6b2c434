"""One rule for run folders, shared by every stage: nothing is overwritten, nothing is misdescribed.

A folder holds ``run.json``, the record of what made it: the stage, its resolved config, its data's
identity, the code version, and whether it finished. :func:`open_run_folder` applies the rule first:

* an absent or empty folder starts a new run;
* a record of another stage, config or data is refused, naming each difference;
* the same record is continued only when asked (``resume=True``); ``may_extend`` fields may then change;
* starting over is explicit (``restart=True``): the old folder is moved aside, never deleted;
* a non-empty folder without a record is refused: it is not a run of this stage;
* one writer at a time: the folder's lock (:mod:`sar_zero123.runs.lock`) is taken before anything else.

:func:`finish_run` marks the run finished once its outputs exist; reports read those records. Every write
is atomic, so a kill leaves the previous record intact.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from sar_zero123.config import drop_removed_fields, removed_fields
from sar_zero123.config.json_io import config_to_dict, read_json, write_json_atomic
from sar_zero123.runs.lock import is_lock_file, lock_output_folder, release_output_folder
from sar_zero123.runs.restart import check_restart_target, move_aside

logger = logging.getLogger(__name__)

__all__ = [
    "RUN_RECORD",
    "RunFolder",
    "StageTimer",
    "check_options_folder",
    "code_version",
    "data_identity",
    "field_defaults",
    "finish_run",
    "open_run_folder",
    "read_run_record",
    "run_differences",
    "WEIGHT_SUFFIXES",
    "weights_identity",
]

#: The record of a run folder.
RUN_RECORD = "run.json"
_FORMAT = 1


@dataclass(frozen=True)
class RunFolder:
    """An opened run folder.

    Attributes:
        status: ``"new"``, ``"continued"`` (same record, resumed) or ``"finished"`` (same record, resumed,
            already finished: a stage may skip its work).
        record: The record as written in ``run.json``.
    """

    path: Path
    status: Literal["new", "continued", "finished"]
    record: dict[str, Any]

    @property
    def finished(self) -> bool:
        return self.status == "finished"


def code_version() -> str:
    """The package version, and the git commit of its checkout where there is one (read, not run); recorded,
    never compared."""
    from sar_zero123 import __version__

    version = __version__
    git = Path(__file__).resolve().parents[2] / ".git"  # the checkout holding sar_zero123/
    try:
        head = (git / "HEAD").read_text().strip()
        if head.startswith("ref: "):
            ref = head[5:]
            ref_file = git / ref
            if ref_file.is_file():
                head = ref_file.read_text().strip()
            else:
                packed = (git / "packed-refs").read_text().splitlines()
                head = next((line.split()[0] for line in packed if line.endswith(" " + ref)), "")
        if head:
            version += f"+g{head[:12]}"
    except OSError:
        pass
    return version


def data_identity(data: str | os.PathLike | None) -> dict[str, Any]:
    """What a run read, so that the same folder name with other contents is not taken for the same data.

    A folder with ``index.csv``: the index's SHA-256. Any other folder (raw MSTAR): the SHA-256 of its sorted
    relative file names and sizes. ``None``: the built-in simulator, identified by the config.

    Raises:
        FileNotFoundError: If ``data`` is given and does not exist.
    """
    if data is None:
        return {"source": "built-in simulator"}
    root = Path(data)
    if not root.exists():
        raise FileNotFoundError(f"data: {str(root)!r} does not exist")
    index = root / "index.csv" if root.is_dir() else root
    digest = hashlib.sha256()
    if index.is_file():
        with open(index, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        return {"path": str(root.resolve()), "index_sha256": digest.hexdigest()}
    count = 0
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(f"{path.relative_to(root).as_posix()}\0{path.stat().st_size}\n".encode())
        count += 1
    return {"path": str(root.resolve()), "files": count, "files_sha256": digest.hexdigest()}


def content_identity(path: str | os.PathLike) -> str:
    """SHA-256 over a folder's (or file's) relative file names and bytes, so a model replaced in place is told
    apart."""
    return _files_digest(Path(path))


def _files_digest(root: Path, suffixes: tuple[str, ...] | None = None) -> str:
    """SHA-256 over the relative names and bytes of the files under ``root`` (ending in ``suffixes``, when
    given), or of ``root`` itself when it is a file."""
    if not root.exists():
        raise FileNotFoundError(f"{str(root)!r} does not exist")
    files = [root] if not root.is_dir() else sorted(
        p for p in root.rglob("*") if p.is_file() and (suffixes is None or p.suffix in suffixes)
    )  # fmt: skip
    digest = hashlib.sha256()
    for file in files:
        digest.update((file.relative_to(root).as_posix() if root.is_dir() else file.name).encode() + b"\0")
        with open(file, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()


#: The files that hold a model's weights (what :func:`weights_identity` hashes).
WEIGHT_SUFFIXES = (".safetensors", ".bin", ".ckpt", ".pt", ".pth")


def weights_identity(path: str | os.PathLike) -> str:
    """SHA-256 over a model folder's weight files (:data:`WEIGHT_SUFFIXES`) or a checkpoint file: what a
    fine-tune started from, whatever text changes beside it."""
    return _files_digest(Path(path), WEIGHT_SUFFIXES)


def read_run_record(folder: str | os.PathLike) -> dict[str, Any] | None:
    """The ``run.json`` of a folder, or ``None`` when it has none.

    Raises:
        ValueError: If the record is not valid JSON (naming the file).
    """
    path = Path(folder) / RUN_RECORD
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not a valid run record ({error})") from error


def _as_dict(config: Any) -> dict[str, Any]:
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return config_to_dict(config)
    # a JSON round trip gives the same types a record read back has (tuples become lists)
    return json.loads(json.dumps(dict(config)))


def field_defaults(config: Any) -> dict[str, Any]:
    """The defaults of a dataclass config's fields as a record holds them (JSON types); ``{}`` for anything
    else."""
    if not dataclasses.is_dataclass(config):
        return {}
    defaults = {}
    for item in dataclasses.fields(config):
        if item.default is not dataclasses.MISSING:
            value = item.default
        elif item.default_factory is not dataclasses.MISSING:
            value = item.default_factory()
        else:
            continue
        try:
            defaults[item.name] = json.loads(json.dumps(value))
        except (TypeError, ValueError):
            continue
    return defaults


def run_differences(
    record: Mapping[str, Any],
    stage: str,
    config: Mapping[str, Any],
    data: Mapping[str, Any],
    ignore: Iterable[str] = (),
    defaults: Mapping[str, Any] | None = None,
) -> list[str]:
    """Every difference between a folder's record and a new run, as ``"field: folder X, this run Y"``.

    A field the record lacks counts as its value in ``defaults`` (the folder predates the field).
    """
    if record.get("stage") != stage:
        return [f"stage: folder {record.get('stage')!r}, this run {stage!r}"]
    ignored = set(ignore)
    written = record.get("config", {})
    written = {**{k: v for k, v in (defaults or {}).items() if k not in written}, **written}
    differences = [
        f"{name}: folder {written.get(name, '<absent>')!r}, this run {config.get(name, '<absent>')!r}"
        for name in sorted(set(written) | set(config))
        if name not in ignored and written.get(name, "<absent>") != config.get(name, "<absent>")
    ]
    if record.get("data") != dict(data):
        differences.append(f"data: folder {record.get('data')!r}, this run {dict(data)!r}")
    return differences


def open_run_folder(
    path: str | os.PathLike,
    stage: str,
    config: Any,
    *,
    data: str | os.PathLike | None | Mapping[str, Any] = None,
    resume: bool = False,
    restart: bool = False,
    may_differ: Iterable[str] = (),
    may_extend: Iterable[str] = (),
    write: bool = True,
    flag_hint: str = "output_dir",
    resume_hint: str = "--resume_from_checkpoint latest",
) -> RunFolder:
    """Apply the run-folder rule to ``path`` before a stage does any work (see the module docstring).

    Args:
        stage: The stage's name: a folder of another stage is refused.
        config: The stage's resolved config (a dataclass or a mapping).
        data: The data folder the stage reads (``None``: the built-in simulator), or a :func:`data_identity`.
        may_differ: Fields that never change what a folder holds (where logs go, how often to print).
        may_extend: Fields that may change when continuing, e.g. ``max_train_steps``.
        write: Write the record (``False`` on non-main processes: they check only).
        flag_hint: The user's name for ``path``, for messages.
        resume_hint: How the user continues a run of this stage, for messages.

    Raises:
        ValueError: If ``resume`` and ``restart`` are both set; if the folder is not empty and has no record;
            if its record differs; if it has the same record and neither is set.
    """
    if resume and restart:
        raise ValueError(
            "resume and restart: choose one (continue this run, or move it aside and start anew)"
        )
    path = Path(path)
    identity = dict(data) if isinstance(data, Mapping) else data_identity(data)
    values = _as_dict(config)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag_hint}: {str(path)!r} is a file, not a folder")
    if write:  # one writer: a second process opening the folder now is refused, naming this one
        lock_output_folder(path, flag_hint)
    occupied = path.is_dir() and any(not is_lock_file(p) for p in path.iterdir())
    if occupied and restart:
        check_restart_target(path, identity, values, flag_hint)
        existing = read_run_record(path)
        if existing is None:  # moving aside is for this project's runs, never a folder of yours
            raise ValueError(
                f"restart: {flag_hint} {str(path)!r} holds no {RUN_RECORD}: it is not a run folder of this "
                f"project, and --restart moves only those; name another {flag_hint}"
            )
        if existing.get("stage") != stage:  # nor another command's work (a dataset, a prior, a fine-tune)
            raise ValueError(
                f"restart: {flag_hint} {str(path)!r} holds a {existing.get('stage')} run, not a {stage} run; "
                f"--restart moves aside only this command's own runs; name another {flag_hint}"
            )
        if write:
            move_aside(path)
        occupied = False
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    if not occupied:
        record = {
            "format": _FORMAT,
            "stage": stage,
            "config": values,
            "data": identity,
            "code_version": code_version(),
            "created": now,
            "finished": False,
        }
        if write:
            path.mkdir(parents=True, exist_ok=True)
            write_json_atomic(record, path / RUN_RECORD)
        return RunFolder(path, "new", record)
    record = read_run_record(path)
    if record is None:
        raise ValueError(
            f"{flag_hint}: {str(path)!r} is not empty and holds no {RUN_RECORD} (not a {stage} run of this "
            "version): choose an empty or new folder"
        )
    extendable = set(may_extend) if resume else set()
    # a field since removed counts as absent where the folder holds its old default, and is refused otherwise
    drop_removed_fields(config, record.get("config", {}), f"{flag_hint}: {str(path)!r}")
    differences = run_differences(
        record,
        stage,
        values,
        identity,
        ignore=set(may_differ) | extendable | set(removed_fields(config)),
        defaults=field_defaults(config),
    )
    if differences:
        raise ValueError(
            f"{flag_hint}: {str(path)!r} holds a {record.get('stage')} run made with other settings; reusing "
            "it would replace or misdescribe that work. Differences: "
            + "; ".join(differences)
            + ". Choose another folder, or pass --restart to move this run aside."
        )
    finished = bool(record.get("finished"))
    missing = [name for name in record.get("outputs", []) if not (path / name).exists()]
    if finished and missing:
        # a finished record whose outputs are gone (deleted by hand, a partial copy) is not finished
        logger.warning("%s: recorded as finished but %s are missing; the run is unfinished", path, missing)
        finished = False
        record = {**record, "finished": False}
        if write and resume:
            write_json_atomic(record, path / RUN_RECORD)
    if not resume:
        state = "finished" if finished else "unfinished"
        raise ValueError(
            f"{flag_hint}: {str(path)!r} already holds {'an' if state == 'unfinished' else 'a'} {state} "
            f"{stage} run with these settings; "
            f"continue it explicitly ({resume_hint}) or pass --restart to move it aside"
        )
    changed = {
        name: {"from": record["config"].get(name), "to": values.get(name)}
        for name in sorted(extendable)
        if record["config"].get(name) != values.get(name)
    }
    if changed:
        # a longer run is a new run of the same folder: not finished until it finishes again
        record = {**record, "config": values, "finished": False,
                  "continued": [*record.get("continued", []), {"at": now, "changed": changed,
                                                              "code_version": code_version()}]}  # fmt: skip
        finished = False
        if write:
            write_json_atomic(record, path / RUN_RECORD)
    if finished and write:
        release_output_folder(path)  # nothing is left to write: the stage returns what the folder holds
    return RunFolder(path, "finished" if finished else "continued", record)


def check_options_folder(
    out: Path,
    options: Mapping[str, Any],
    *,
    record: str,
    what: str,
    defaults: Mapping[str, Any],
    identity_field: str | None = None,
    identity_message: Callable[[Any, Any], str] | None = None,
    flag_hint: str = "out",
    removed_from: Any = None,
) -> bool:
    """Whether ``out`` holds this run already, for a folder whose record is the options file ``record``
    (``augment.json``) rather than ``run.json``; any other non-empty folder is refused.

    Args:
        defaults: Field defaults, for a record that predates an option.
        removed_from: The config class whose removed fields (``REMOVED_FIELDS``) the record may hold: at
            their old default they read as absent, another value is refused.
        identity_field: An option identifying an input's content, compared first (a record without it
            matches); ``identity_message(recorded, current)`` words its refusal.

    Raises:
        ValueError: For a non-empty folder without ``record``, a record that is not a JSON object, a
            differing ``identity_field``, or other options (each difference named).
    """
    if not out.is_dir() or not any(not is_lock_file(p) for p in out.iterdir()):
        return False
    if not (out / record).is_file():
        raise ValueError(
            f"{flag_hint}: {str(out)!r} is not empty and has no {record}; choose an empty folder"
        )
    recorded = read_json(out / record, what=f"the options the {what} was made with")
    if not isinstance(recorded, dict):
        raise ValueError(f"{out / record}: expected a JSON object of the {what}'s options")
    recorded = drop_removed_fields(removed_from, recorded, f"{flag_hint}: {str(out)!r}")
    recorded = {**{name: defaults[name] for name in options if name in defaults}, **recorded}
    if identity_field is not None:
        if identity_field not in recorded:
            recorded[identity_field] = options[identity_field]
        elif recorded[identity_field] != options[identity_field]:
            raise ValueError(
                identity_message(recorded[identity_field], options[identity_field])
                if identity_message is not None
                else f"{identity_field}: {recorded[identity_field]!r} there, {options[identity_field]!r} now"
            )
    differences = [
        f"{name}: {recorded.get(name)!r} there, {options.get(name)!r} now"
        for name in sorted(set(recorded) | set(options))
        if recorded.get(name) != options.get(name)
    ]
    if differences:
        article = "an" if what[:1] in "aeiou" else "a"
        raise ValueError(
            f"{flag_hint}: {str(out)!r} holds {article} {what} made with other options "
            f"({'; '.join(differences)}); use another folder or the same options"
        )
    return True


def finish_run(
    folder: RunFolder | str | os.PathLike,
    outputs: Iterable[str | os.PathLike] = (),
    *,
    seconds: float | None = None,
    results: Mapping[str, Any] | None = None,
    write: bool = True,
) -> dict[str, Any]:
    """Mark a run finished, after checking that its outputs exist; returns the updated record.

    Args:
        outputs: Files or folders the stage must have written, relative to the folder or absolute.
        seconds: Wall time of the stage; added to earlier sessions' time.
        results: Small JSON-able facts a report may quote.
        write: ``False`` on non-main processes.

    Raises:
        FileNotFoundError: If an output is missing (the run is not marked finished).
        ValueError: If the folder holds no record.
    """
    path = folder.path if isinstance(folder, RunFolder) else Path(folder)
    record = read_run_record(path)
    if record is None:
        raise ValueError(f"{path}: no {RUN_RECORD}; open the folder with open_run_folder first")
    missing = [str(p) for p in outputs if not (path / p).exists()]
    if missing:
        raise FileNotFoundError(f"{path}: the run is not finished, missing outputs: {missing}")
    record = dict(record)
    record["finished"] = True
    record["finished_at"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    record["outputs"] = [str(p) for p in outputs]
    if seconds is not None:
        record["seconds"] = float(record.get("seconds", 0.0)) + float(seconds)
    if results is not None:
        record["results"] = {**record.get("results", {}), **dict(results)}
    if write:
        write_json_atomic(record, path / RUN_RECORD)
        release_output_folder(path)  # the run is done: the next writer may open the folder
    return record


class StageTimer:
    """Wall time of a stage session (``time.perf_counter``), for :func:`finish_run`'s ``seconds``."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.start
