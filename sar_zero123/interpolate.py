"""A fine-tuned pipeline's weights interpolated with those of the pipeline it started from (WiSE-FT).

Example::

    python -m sar_zero123.interpolate --start sar-zero123/sim-prior-rotated \\
        --finetuned runs/mstar/finetune_lambda0/pipeline --alpha 0.85 --output_dir runs/mstar/wise0.85

writes ``output_dir/pipeline``, whose trained weights are ``(1 - alpha) * start + alpha * finetuned``,
tensor by tensor, and whose other files are the fine-tune's. Wortsman et al. (CVPR 2022) show such a mix
keeps most of the fine-tune's accuracy and much of the start's robustness to distribution shift; here
the start is the multi-view prior, which turns vehicles it has never seen.

The two must have one architecture (same components, configs, tensor names, shapes and dtypes); anything
else is refused by name and leaves nothing behind. Integer tensors are the fine-tune's. The pipeline is
written under a temporary name and renamed into place. Hand-written because no library mixes two
diffusers pipeline folders file by file.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from sar_zero123.config import parse_config
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.domain import naming_write_errors
from sar_zero123.pretrained import resolve_pretrained
from sar_zero123.runs.folder import StageTimer, content_identity, finish_run, weights_identity
from sar_zero123.runs.manifest import manifest_problem, write_manifest
from sar_zero123.runs.stage import open_stage_folder

__all__ = [
    "InterpolateConfig", "check_lineage", "check_readable", "interpolate_pipelines", "interpolate_state",
    "main", "mix_plan", "run_interpolate",
]  # fmt: skip

_WEIGHTS_SUFFIX = ".safetensors"


@dataclass
class InterpolateConfig:
    """Mix a fine-tuned pipeline with the pipeline it was fine-tuned from."""

    start: str = ""  # the pipeline the fine-tune started from (a folder or a bundled name)
    finetuned: str = ""  # the fine-tuned pipeline folder (its model_index.json beside its components)
    alpha: float = 0.5  # weight of the fine-tune: 1 is the fine-tune, 0 the start's weights
    output_dir: str = ""  # run folder: its record and pipeline/, the mixed pipeline
    resume: bool = False  # return a finished folder with these settings as it is (finish an unfinished one)
    restart: bool = False  # move an existing folder at output_dir aside (never deleted) and mix anew

    def __post_init__(self) -> None:
        for name in ("start", "finetuned", "output_dir"):
            if not getattr(self, name):
                raise ValueError(f"{name}: expected a path, got an empty value")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must lie in [0, 1] (1: the fine-tune), got {self.alpha}")


def interpolate_state(
    start: dict[str, torch.Tensor], finetuned: dict[str, torch.Tensor], alpha: float, name: str = "weights"
) -> dict[str, torch.Tensor]:
    """``(1 - alpha) * start + alpha * finetuned`` for every floating tensor (in float32, stored in the
    fine-tune's dtype); other tensors are the fine-tune's.

    Raises:
        ValueError: Naming ``name`` and the first tensor missing from one or differing in shape or dtype.
    """
    missing = sorted(set(start) ^ set(finetuned))
    if missing:
        raise ValueError(f"{name}: the two pipelines do not hold the same tensors (e.g. {missing[0]!r})")
    mixed = {}
    for key, tuned in finetuned.items():
        base = start[key]
        if base.shape != tuned.shape or base.dtype != tuned.dtype:
            raise ValueError(
                f"{name}: tensor {key!r} is {tuple(base.shape)} {base.dtype} in the start and "
                f"{tuple(tuned.shape)} {tuned.dtype} in the fine-tune"
            )
        if tuned.is_floating_point():
            value = torch.lerp(base.float(), tuned.float(), float(alpha)).to(tuned.dtype)
        else:
            value = tuned.clone()
        mixed[key] = value.contiguous()
    return mixed


#: Config entries that record what a component was trained beside, not its architecture.
_RECORD_KEYS = ("trained_estimator",)


def _architecture(config_file: Path) -> dict | None:
    """A component's config without diffusers' and transformers' ``_`` bookkeeping keys and
    :data:`_RECORD_KEYS`; ``None`` where it has no ``config.json``."""
    if not config_file.is_file():
        return None
    config = json.loads(config_file.read_text())
    return {k: v for k, v in config.items() if not k.startswith("_") and k not in _RECORD_KEYS}


def check_readable(folder: Path, field_name: str) -> None:
    """Refuse a pipeline folder whose files differ from its manifest, or whose weights do not read.

    Raises:
        ValueError: Naming ``field_name`` and the file.
    """
    problem = manifest_problem(folder)
    if problem is not None:
        raise ValueError(f"{field_name}: {problem}")
    for weights in sorted(folder.rglob(f"*{_WEIGHTS_SUFFIX}")):
        try:
            with safe_open(str(weights), framework="pt") as handle:
                handle.keys()
        except Exception as error:  # safetensors raises its own error type, not an OSError
            raise ValueError(
                f"{field_name}: {str(weights)!r} is not a readable safetensors file ({error})"
            ) from None


def check_lineage(start: str | os.PathLike, start_dir: Path, tuned_dir: Path) -> None:
    """Refuse a ``start`` other than the pipeline the fine-tune started from, where its ``model_index.json``
    records the start's weights' SHA-256 (``lineage``)."""
    index = json.loads((tuned_dir / "model_index.json").read_text())
    lineage = index.get("lineage") if isinstance(index, dict) else None
    started = lineage.get("start_weights") if isinstance(lineage, dict) else None
    if started is None:  # a fine-tune exported before lineage was recorded, or of unknown origin
        return
    current = weights_identity(start_dir)
    if current != started:
        raise ValueError(
            f"start: the fine-tune {str(tuned_dir)!r} started from {lineage.get('start')!r} (weights SHA-256 "
            f"{str(started)[:12]}...), not from {str(start)!r} ({current[:12]}...): the mix would not lie "
            "between the fine-tune and the model it came from; pass the pipeline it started from"
        )


def _pipeline_dirs(start: str | os.PathLike, finetuned: str | os.PathLike) -> tuple[Path, Path]:
    """The two pipeline folders, refused unless each holds a ``model_index.json``."""
    start_dir, tuned_dir = resolve_pretrained(start), Path(finetuned)
    for field_name, folder in (("start", start_dir), ("finetuned", tuned_dir)):
        if not (folder / "model_index.json").is_file():
            raise FileNotFoundError(
                f"{field_name}: expected a pipeline folder with model_index.json, got {folder}"
            )
    return start_dir, tuned_dir


def interpolate_pipelines(
    start: str | os.PathLike, finetuned: str | os.PathLike, alpha: float, output_dir: str | os.PathLike
) -> Path:
    """Write the pipeline ``(1 - alpha) * start + alpha * finetuned`` into ``output_dir``; returns it.

    Raises:
        FileNotFoundError: If either pipeline folder lacks ``model_index.json``.
        ValueError: For an ``alpha`` outside [0, 1], an existing ``output_dir``, a start the fine-tune did
            not start from, or two pipelines of different architectures.
    """
    (start_dir, tuned_dir), out = _pipeline_dirs(start, finetuned), Path(output_dir)
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must lie in [0, 1] (1: the fine-tune), got {alpha}")
    if out.exists():
        raise ValueError(f"output_dir: {str(out)!r} exists; give a new folder")
    return _write_mix(mix_plan(start, start_dir, tuned_dir), tuned_dir, alpha, out)


def mix_plan(start: str | os.PathLike, start_dir: Path, tuned_dir: Path) -> list[tuple[Path, Path]]:
    """``(relative path, start's file)`` of every weight file of the fine-tune, after checking its lineage and
    that each component's config matches (tensors are checked as they are mixed).

    Raises:
        ValueError: Naming the component, for a wrong start, a weight file the start lacks, configs of
            another architecture, or a fine-tune without weights.
    """
    check_lineage(start, start_dir, tuned_dir)
    plan: list[tuple[Path, Path]] = []
    for weights in sorted(tuned_dir.rglob(f"*{_WEIGHTS_SUFFIX}")):
        relative = weights.relative_to(tuned_dir)
        component = relative.parts[0] if len(relative.parts) > 1 else "the pipeline folder"
        other = start_dir / relative
        if not other.is_file():
            raise ValueError(
                f"{component}: the start has no {relative} (not the pipeline the fine-tune began from?)"
            )
        name = relative.parent / "config.json"
        first, second = _architecture(start_dir / name), _architecture(tuned_dir / name)
        if first is not None and second is not None and first != second:
            changed = sorted(k for k in first.keys() | second.keys() if first.get(k) != second.get(k))
            raise ValueError(f"{component}: the two pipelines' configs differ in {changed}")
        plan.append((relative, other))
    if not plan:
        raise ValueError(f"finetuned: {tuned_dir} holds no {_WEIGHTS_SUFFIX} weights")
    return plan


def _write_mix(plan: list[tuple[Path, Path]], tuned_dir: Path, alpha: float, out: Path) -> Path:
    """The fine-tune's folder copied under a temporary name, each planned weight file mixed, the folder
    sealed, then renamed into place whole; returns ``out``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    kept = "nothing was written to it (the scratch copy is removed); free space and run the command again"
    try:
        with naming_write_errors(out, kept):
            staged = scratch / "pipeline"
            shutil.copytree(tuned_dir, staged)
            for relative, other in plan:
                component = relative.parts[0] if len(relative.parts) > 1 else "the pipeline folder"
                mixed = interpolate_state(load_file(other), load_file(tuned_dir / relative), alpha, component)
                save_file(mixed, staged / relative, metadata={"format": "pt"})
            _forget_trained_estimator(staged)
            write_manifest(staged)  # sealed last: the loader refuses a file changed since
            os.replace(staged, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return out


def _forget_trained_estimator(folder: Path) -> None:
    """The mix's azimuth estimator is neither run's: clear its ``trained_estimator`` record, so the mix loads
    as a pipeline of unknown estimator origin."""
    config_file = folder / "pose_projection" / "config.json"
    if config_file.is_file():
        config = json.loads(config_file.read_text())
        if config.get("trained_estimator") is not None:
            write_json_atomic({**config, "trained_estimator": None}, config_file)


def run_interpolate(config: InterpolateConfig) -> Path:
    """Mix the two pipelines into ``config.output_dir``/pipeline under the run-folder rule; returns it.

    Raises:
        FileNotFoundError: If either pipeline folder lacks ``model_index.json``.
        ValueError: For a folder holding other work, or two pipelines of different architectures.
    """
    timer = StageTimer()
    start_dir, tuned_dir = _pipeline_dirs(config.start, config.finetuned)
    for field_name, folder in (("start", start_dir), ("finetuned", tuned_dir)):
        check_readable(folder, field_name)  # before the folder is opened: a refusal leaves nothing behind
    plan = mix_plan(config.start, start_dir, tuned_dir)
    data = {"start": content_identity(start_dir), "finetuned": content_identity(tuned_dir)}
    folder = open_stage_folder(
        config.output_dir, "interpolate", config, data=data, resume=config.resume, restart=config.restart,
        may_differ=("resume", "restart"), resume_hint="--resume",
    )  # fmt: skip
    pipeline = folder.path / "pipeline"
    if folder.finished:
        return pipeline
    if not (pipeline / "model_index.json").is_file():  # renamed into place whole, or absent
        for stale in folder.path.glob(f".{pipeline.name}.*"):  # the scratch folder of a run killed before
            if stale.is_dir():
                shutil.rmtree(stale)
        _write_mix(plan, tuned_dir, config.alpha, pipeline)
    finish_run(folder, ["pipeline/model_index.json"], seconds=timer.seconds, results={"alpha": config.alpha})
    return pipeline


def main(argv: Sequence[str] | None = None) -> Path:
    """``python -m sar_zero123.interpolate``: the flags are :class:`InterpolateConfig`'s fields."""
    config = parse_config(InterpolateConfig, argv, prog="python -m sar_zero123.interpolate")
    out = run_interpolate(config)
    print(f"{out}: alpha = {config.alpha:g} of {config.finetuned}, {1 - config.alpha:g} of {config.start}")
    return out


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    from sar_zero123.runs.refusals import run_command

    raise SystemExit(run_command(main, "sar-zero123-interpolate"))
