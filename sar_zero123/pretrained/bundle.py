"""Make a bundled pipeline folder from a trained one: float16 weights, the measured sampler recorded.

    python -m sar_zero123.pretrained.bundle PIPELINE NAME --sampler '{"strength": 0.5, "start_from": "proxy"}'

copies ``PIPELINE`` to ``sar_zero123/pretrained/NAME`` with floating ``*.safetensors`` tensors cast to
float16 (a pipeline loads them as float32, so measure the bundled folder, not the run's), no
``_name_or_path`` in any ``config.json``, a lineage's start named rather than given by its path, and
``model_index.json``'s ``sampler`` merged with the given fields. It is written beside its final name and
renamed into place; an existing ``NAME`` is refused.
Registering the name and its model card are left to the developer.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from safetensors.torch import load_file, save_file

from sar_zero123.pretrained import BUNDLED_PIPELINES, RETIRED_PIPELINES
from sar_zero123.runs.manifest import write_manifest

__all__ = ["bundle_pipeline"]


def bundle_pipeline(
    pipeline: str | os.PathLike, destination: str | os.PathLike, sampler: dict[str, Any] | None = None
) -> Path:
    """Copy ``pipeline`` to ``destination`` with float16 weights and ``sampler`` recorded; returns it.

    Raises:
        FileNotFoundError: If ``pipeline`` has no ``model_index.json``.
        ValueError: If ``destination`` exists, or ``sampler`` is not a mapping.
    """
    source, target = Path(pipeline), Path(destination)
    if not (source / "model_index.json").is_file():
        raise FileNotFoundError(
            f"pipeline: expected a save_pretrained folder with model_index.json, got {source}"
        )
    if target.exists():
        raise ValueError(f"destination: {target} exists; bundle into a new folder")
    if sampler is not None and not isinstance(sampler, dict):
        raise ValueError(f"sampler: expected a mapping of sampler fields, got {type(sampler).__name__}")
    scratch = target.with_name(f".{target.name}.tmp")
    shutil.rmtree(scratch, ignore_errors=True)
    try:
        shutil.copytree(source, scratch)
        for weights in sorted(scratch.rglob("*.safetensors")):
            tensors = load_file(weights)
            half = {k: v.half() if v.is_floating_point() else v for k, v in tensors.items()}
            save_file(half, weights, metadata={"format": "pt"})
        for config_path in sorted(scratch.rglob("config.json")):  # no path of the machine it was trained on
            config = json.loads(config_path.read_text())
            if config.pop("_name_or_path", None) is not None:
                config_path.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
        index_path = scratch / "model_index.json"
        index = json.loads(index_path.read_text())
        if isinstance(index.get("lineage"), dict):  # the start by name, not by this machine's path
            index["lineage"]["start"] = _start_name(index["lineage"].get("start"))
        if sampler is not None:
            index["sampler"] = {**(index.get("sampler") or {}), **sampler}
        index_path.write_text(json.dumps(index, indent=2, sort_keys=True) + "\n")
        write_manifest(scratch)  # sealed last: the loader refuses a file changed since
        os.replace(scratch, target)
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    return target


def _start_name(start: Any) -> Any:
    """A lineage's start as a bundled (or retired) name where it is one's folder, else its folder's name
    where it is an absolute path; anything else as it is."""
    if not isinstance(start, str) or not Path(start).is_absolute():
        return start
    folder = Path(start).name
    known = (*BUNDLED_PIPELINES, *RETIRED_PIPELINES)
    names = {name.split("/", 1)[1].replace("-", "_"): name for name in known}
    return names.get(folder, folder)


def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pipeline", help="the trained pipeline folder (model_index.json)")
    parser.add_argument("name", help="the bundled folder's name under sar_zero123/pretrained/")
    parser.add_argument("--sampler", default=None, help="JSON object of sampler fields to record")
    args = parser.parse_args(argv)
    if Path(args.name).name != args.name or args.name in ("", ".", ".."):
        raise ValueError(f"name: expected one folder name, got {args.name!r}")
    sampler = None if args.sampler is None else json.loads(args.sampler)
    out = bundle_pipeline(args.pipeline, Path(__file__).resolve().parent / args.name, sampler)
    print(out)
    return out


if __name__ == "__main__":
    main()
