"""The one restart rule: ``--restart`` moves a folder aside (never deleted) only when it holds none of the
run's inputs and lies inside none of them nor inside the package, for run and options folders alike."""
from __future__ import annotations

import logging
import shutil
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["check_restart_target", "move_aside"]


#: Config fields that name where a stage writes, never what it reads.
_OUTPUT_FIELDS = ("output_dir", "work_dir", "out")


def _named_inputs(identity: Mapping[str, Any], config: Mapping[str, Any]) -> list[tuple[str, Any]]:
    """``(name, value)`` of every input a run may read: the data paths of ``identity`` and every config field
    but the outputs."""
    named: list[tuple[str, Any]] = [
        (key, value.get("path")) for key, value in identity.items() if isinstance(value, Mapping)
    ]
    if "path" in identity:
        named.append(("data", identity["path"]))
    for key, value in config.items():
        if key not in _OUTPUT_FIELDS:
            named += [(key, item) for item in (value if isinstance(value, list | tuple) else [value])]
    return named


def _inputs_inside(folder: Path, identity: Mapping[str, Any], config: Mapping[str, Any]) -> list[str]:
    """The inputs (data paths of ``identity``, config fields naming existing paths) inside ``folder``."""
    root = folder.resolve()
    inside, seen = [], set()
    for name, value in _named_inputs(identity, config):
        if isinstance(value, str) and value and Path(value).exists():
            resolved = Path(value).resolve()
            if resolved.is_relative_to(root) and resolved not in seen:  # each input once, by its path
                seen.add(resolved)
                inside.append(f"{name}: {value}")
    return inside


def _inputs_holding(folder: Path, identity: Mapping[str, Any], config: Mapping[str, Any]) -> list[str]:
    """The inputs that are ``folder`` or hold it, and the package's own folder where it holds ``folder``."""
    import sar_zero123

    root = folder.resolve()
    package = ("the sar_zero123 package", str(Path(sar_zero123.__file__).resolve().parent))
    holding, seen = [], set()
    for name, value in [*_named_inputs(identity, config), package]:
        if isinstance(value, str) and value and Path(value).is_dir():
            resolved = Path(value).resolve()
            if root.is_relative_to(resolved) and (name, resolved) not in seen:  # each input once
                seen.add((name, resolved))
                holding.append(f"{name}: {value}")
    return holding


def check_restart_target(
    path: Path, identity: Mapping[str, Any], config: Mapping[str, Any], flag_hint: str = "output_dir"
) -> None:
    """Refuse to move ``path`` aside when it holds one of the run's inputs, or lies inside one of them or
    inside the package (its bundled pipelines).

    Raises:
        ValueError: Naming ``flag_hint``, the folder and the inputs.
    """
    inside = _inputs_inside(path, identity, config)
    if inside:
        raise ValueError(
            f"restart: {flag_hint} {str(path)!r} holds this run's inputs ({', '.join(inside)}); moving "
            "it aside would move them too. Name another output folder, or move the inputs out first"
        )
    holding = _inputs_holding(path, identity, config)
    if holding:
        raise ValueError(
            f"restart: {flag_hint} {str(path)!r} lies inside this run's inputs ({', '.join(holding)}); "
            "moving it aside would move part of them. Name an output folder outside them"
        )


def move_aside(path: Path) -> Path:
    """Move the folder ``path`` aside to ``<name>.replaced-<UTC time>`` (never deleted); returns the new path.

    Raises:
        ValueError: If ``path`` is the working directory or holds it.
    """
    if Path.cwd().resolve().is_relative_to(path.resolve()):  # `--output_dir .` or a parent of the cwd
        raise ValueError(
            f"restart: output_dir {str(path)!r} is the working directory or holds it, and cannot be moved "
            "aside while a command works in it; run from another folder, or name another output_dir"
        )
    path = path.resolve()  # `run/..`-style paths get a real name for the moved-aside folder
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    target = path.with_name(f"{path.name}.replaced-{stamp}")
    suffix = 1
    while target.exists():
        target = path.with_name(f"{path.name}.replaced-{stamp}-{suffix}")
        suffix += 1
    shutil.move(str(path), str(target))
    logger.warning("restart: moved the old run %s aside to %s", path, target)
    return target
