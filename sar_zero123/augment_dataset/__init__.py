"""Turn a folder of labelled chips into a larger training set with novel views from a pipeline.

Example::

    python -m sar_zero123.augment_dataset --data ../shared/data/mstar --out runs/mstar_aug \\
        --d_az -30 30 --d_el 0 --classes T72 --include_real

For every selected chip and every request (an azimuth change ``--d_az`` or an absolute
``--target_azimuths_deg``, each combined with every ``--d_el``), the pipeline generates one view. The
output folder is a dataset every script reads (:func:`sar_zero123.data.load_index`):

* ``views/<CLASS>/<stem>_r<row>_v<request>.npy``: float32 magnitude ``scaling.denormalize(view)`` (in
  [0, 1] for the unit-magnitude scaling of the simulator and the 8-bit chips), ``row`` being the chip's
  position in the source index (0 = first chip) and ``request`` the request's position;
* ``index.csv`` with the standard columns (:data:`sar_zero123.domain.INDEX_COLUMNS`), written last;
* ``provenance.csv``: the same rows and columns plus :data:`PROVENANCE_COLUMNS`. They live in a file of
  their own because ``load_index`` refuses columns it does not know;
* ``views.json``: what the generated arrays hold (magnitude) and the dB scaling they were mapped back with;
* ``augment.json``: the options and the SHA-256 of the pipeline's files. A folder made with other options
  or other weights is refused, so that a re-run after a kill resumes (views already on disk are kept) and
  never mixes two augmentations or two models.

Each view has its own random stream (:func:`~sar_zero123.augment_dataset.plan.view_generator`), so its
noise does not depend on which other views share its batch. Its bytes still do, by float rounding:
PyTorch's CPU convolutions and matrix products choose their kernels by batch size. So the batches are
fixed (consecutive views of the plan, ``--batch_size`` of them), a resumed run regenerates each batch that
misses a view and writes only the missing files, and ``batch_size`` is one of the options a resumed run
must keep: a view is then the same bytes whether it was written before or after a kill (same machine and
threads).
"""

from __future__ import annotations

import csv
import functools
import io
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sar_zero123.augment_dataset.plan import (
    ViewRequest,
    check_trained_ranges,
    plan_views,
    select_records,
    view_generator,
)
from sar_zero123.config import RemovedField, check_minimum, check_output_dir, parse_config
from sar_zero123.config.json_io import config_to_dict, read_json, write_json_atomic
from sar_zero123.data import ChipRecord, DecibelScaling, load_index, load_magnitude
from sar_zero123.domain import INDEX_COLUMNS, naming_write_errors
from sar_zero123.generate import GenerateConfig, _resolve_scaling, load_input_chip
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.proxy import DATASET_SHORTLIST, fit_scores, with_shortlist
from sar_zero123.model.sampler import SamplerSettings, scheduler_name
from sar_zero123.model.view_request import check_delta_bounds
from sar_zero123.pretrained import SIM_PRIOR_ROTATED, is_bundled_name, resolve_pretrained
from sar_zero123.progress import progress_bar
from sar_zero123.runs.folder import (
    check_options_folder,
    content_identity,
    field_defaults,
)
from sar_zero123.runs.launch import check_device
from sar_zero123.runs.lock import is_lock_file, lock_output_folder, release_output_folder
from sar_zero123.runs.restart import check_restart_target, move_aside
from sar_zero123.sim.dataset import write_index_atomic

logger = logging.getLogger(__name__)

__all__ = [
    "AUGMENT_FILE",
    "MAX_AUGMENT_VIEWS",
    "MAX_BATCH_SIZE",
    "MAX_REQUESTS_PER_CHIP",
    "PROVENANCE_COLUMNS",
    "PROVENANCE_FILE",
    "AugmentConfig",
    "augment_dataset",
    "main",
]

#: The options of an augmentation, in its output folder.
AUGMENT_FILE = "augment.json"
#: What every generated view's ``.npy`` holds, as ``views.json`` says in the output folder.
VIEWS_DOMAIN = (
    "magnitude (float32 .npy, as the source chips): each generated view in normalised dB mapped back by "
    "sar_zero123.data.DecibelScaling(**scaling).denormalize, clipped to [0, the scaling's peak]"
)
VIEWS_FILE = "views.json"
#: Key of ``augment.json`` holding the SHA-256 of the pipeline's files (:func:`content_identity`).
PIPELINE_DIGEST = "pipeline_sha256"
#: The index rows with their provenance (``load_index`` refuses unknown columns in ``index.csv``).
PROVENANCE_FILE = "provenance.csv"
#: Columns ``provenance.csv`` adds to :data:`~sar_zero123.domain.INDEX_COLUMNS`.
PROVENANCE_COLUMNS = ("source_path", "d_az_deg", "d_el_deg", "pipeline", "seed", "generated")
#: Most views per pipeline call (``batch_size``): the batch's latents and activations are allocated at once.
MAX_BATCH_SIZE = 256
#: Most requests per chip (azimuth requests x ``d_el``): a 1 deg azimuth grid at 11 depression changes fits.
MAX_REQUESTS_PER_CHIP = 4096
#: Most views one augmentation writes (about 64 GiB of 128 px float32 chips).
MAX_AUGMENT_VIEWS = 1_000_000
_SPECKLE = "speckle re-added to the generated views made a classifier trained on them less accurate"


@dataclass
class AugmentConfig(SamplerSettings):
    """Add novel views from a SARZero123Pipeline to a dataset of labelled chips.

    The sampler's fields (:class:`~sar_zero123.model.sampler.SamplerSettings`) are inherited: each left unset
    takes the value the pipeline records as measured best for it (its model card), else the library's; with
    the index's azimuths, a pipeline that records a start from the proxy starts each view from a simulator
    vehicle fitted to the chip.
    """

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "batch_size", "scaling_file", "device", "include_real",
    )  # fmt: skip
    REMOVED_FIELDS = {
        "speckle": RemovedField(False, _SPECKLE),
        "speckle_sigma": RemovedField(10.0, _SPECKLE),
        "speckle_looks": RemovedField(None, _SPECKLE),
    }

    data: str = ""  # dataset folder: index.csv, or a tree of original MSTAR files
    pipeline: str = SIM_PRIOR_ROTATED  # SARZero123Pipeline.save_pretrained folder, or a bundled one's name
    out: str = ""  # output dataset folder (a re-run with the same options resumes it)
    d_az: list[float] = field(default_factory=list)  # azimuth changes in degrees (or target_azimuths_deg)
    target_azimuths_deg: list[float] = field(default_factory=list)  # absolute azimuths (deg), instead of d_az
    d_el: list[float] = field(default_factory=lambda: [0.0])  # depression changes (deg), each with every d_az
    classes: list[str] = field(default_factory=list)  # only these target classes (empty: all)
    depressions_deg: list[float] = field(default_factory=list)  # only chips at these depressions (empty: all)
    max_chips_per_class: int | None = None  # at most this many chips per class, evenly spaced in index order
    include_real: bool = False  # also list the selected real chips (generated 0, absolute paths)
    batch_size: int = 8  # views per pipeline call (a view changes with it by float rounding only)
    seed: int = 0  # view (row, request) is sampled with view_generator(seed, row, request)
    scaling_file: str | None = None  # DecibelScaling JSON (default: <pipeline>/decibel_scaling.json or unit)
    device: str = "cpu"  # torch device
    resume: bool = True  # continue an out folder holding this augmentation (the default); --no-resume refuses
    restart: bool = False  # move an existing out folder aside (never deleted) and start anew

    def __post_init__(self) -> None:
        super().__post_init__()  # the sampler's fields, validated where they are declared
        check_device(self.device)
        if not self.data:
            raise ValueError("data: a dataset folder is required")
        if not self.out:
            raise ValueError("out: an output folder is required")
        if not self.pipeline:
            raise ValueError("pipeline: a pipeline folder or a bundled pipeline's name is required")
        if bool(self.d_az) == bool(self.target_azimuths_deg):
            raise ValueError(
                f"d_az/target_azimuths_deg: give exactly one of them, got d_az={self.d_az} and "
                f"target_azimuths_deg={self.target_azimuths_deg}"
            )
        if not self.d_el:
            raise ValueError("d_el: give at least one depression change (0 keeps the depression)")
        for name in ("d_az", "target_azimuths_deg", "d_el", "depressions_deg"):
            if not all(np.isfinite(getattr(self, name))):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")
        if not all(0.0 <= a < 360.0 for a in self.target_azimuths_deg):
            raise ValueError(f"target_azimuths_deg must lie in [0, 360), got {self.target_azimuths_deg}")
        check_delta_bounds(self.d_az, self.d_el)
        check_minimum(self, "batch_size", minimum=1)
        if self.batch_size > MAX_BATCH_SIZE:
            raise ValueError(f"batch_size must be <= {MAX_BATCH_SIZE} views per call, got {self.batch_size}")
        requests = len(self.d_az or self.target_azimuths_deg) * len(self.d_el)
        if requests > MAX_REQUESTS_PER_CHIP:
            raise ValueError(
                f"d_az/target_azimuths_deg x d_el: at most {MAX_REQUESTS_PER_CHIP} requests per chip, got "
                f"{len(self.d_az or self.target_azimuths_deg)} x {len(self.d_el)} = {requests}"
            )
        check_minimum(self, "max_chips_per_class", minimum=1, optional=True)
        check_minimum(self, "seed", minimum=0)
        if not Path(self.data).is_dir():
            raise FileNotFoundError(f"data: dataset folder not found: {self.data!r}")
        if not resolve_pretrained(self.pipeline).is_dir():
            raise FileNotFoundError(f"pipeline: pipeline folder not found: {self.pipeline!r}")
        if self.scaling_file is not None and not Path(self.scaling_file).is_file():
            raise FileNotFoundError(f"scaling_file: no such file {self.scaling_file!r}")


def _recorded_options(config: AugmentConfig) -> dict[str, Any]:
    """The options that decide the output, with local paths made absolute."""
    options = config_to_dict(config)
    options["data"] = str(Path(config.data).resolve())
    if not is_bundled_name(config.pipeline):
        options["pipeline"] = str(Path(config.pipeline).resolve())
    if config.scaling_file is not None:
        options["scaling_file"] = str(Path(config.scaling_file).resolve())
    for name in ("out", "resume", "restart"):  # where and how it is written, not what
        options.pop(name)
    # the weights, not the folder name: a resume onto a replaced pipeline would mix two models' views
    folder = resolve_pretrained(config.pipeline)  # refuses an unknown bundled name or a missing folder
    if not folder.is_dir():
        raise FileNotFoundError(f"pipeline: {config.pipeline!r} is neither a bundled name nor a folder")
    options[PIPELINE_DIGEST] = content_identity(folder)
    # the pipeline's own scheduler by name, and how a proxy pipeline fits (the loader refuses bad folders)
    index = _json_or_empty(folder / "model_index.json")
    if config.scheduler is None:
        scheduler = _json_or_empty(folder / "scheduler" / "scheduler_config.json")
        name = str(scheduler.get("_class_name", "unknown"))
        options["scheduler"] = scheduler_name(name, scheduler) or name
    if index.get("proxy") is not None:
        options["proxy_shortlist"] = DATASET_SHORTLIST  # how a proxy pipeline's fits are made (two stages)
    return options


def _json_or_empty(path: Path) -> dict[str, Any]:
    """A JSON object file, or ``{}`` where it is missing or holds no object."""
    data = read_json(path, str(path.name)) if path.is_file() else {}
    return data if isinstance(data, dict) else {}


def _check_out_folder(out: Path, options: dict[str, Any]) -> bool:
    """Whether ``out`` holds this augmentation already (resume); refuses any other non-empty folder
    (:func:`~sar_zero123.runs.folder.check_options_folder`, the rule for folders whose record is an options
    file), and a resume onto a pipeline whose weights changed.

    Raises:
        ValueError: naming ``out``, for a non-empty folder without :data:`AUGMENT_FILE`, one made with
            other options (the differences listed), or with other pipeline weights (both digests named).
    """

    def other_weights(recorded: Any, current: Any) -> str:
        return (
            f"pipeline: {options['pipeline']!r} holds other weights than the ones the views in {str(out)!r} "
            f"were made with (SHA-256 {str(recorded)[:12]}... there, {str(current)[:12]}... now); resuming "
            "would mix two models' views. Use another out folder, or the pipeline the folder was made with"
        )

    return check_options_folder(
        out, options, record=AUGMENT_FILE, what="augmentation", defaults=field_defaults(AugmentConfig),
        removed_from=AugmentConfig,
        identity_field=PIPELINE_DIGEST, identity_message=other_weights,
    )  # fmt: skip


def _check_chip_sizes(records: Sequence[ChipRecord], size: int) -> None:
    """Refuse chips smaller than the pipeline's size (they would be upsampled, changing the pixel spacing),
    read from the files themselves: an index's ``height``/``width`` columns are checked against them, never
    trusted."""
    small = []
    for record in records:
        shape = tuple(load_magnitude(record.path).shape)
        listed = (record.height, record.width)
        if None not in listed and tuple(listed) != shape:
            raise ValueError(
                f"data: index.csv lists {record.path} as {listed[0]}x{listed[1]} (height, width), but the "
                f"file is {shape[0]}x{shape[1]}; correct the index's height and width columns"
            )
        if min(shape) < size:
            small.append(f"{record.path} ({shape[0]}x{shape[1]})")
    if small:
        raise ValueError(
            f"data: {len(small)} chip(s) are smaller than the pipeline's {size} px, e.g. {small[0]}; "
            "use a pipeline of their size"
        )


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` through a temporary file and ``os.replace``: a kill never leaves a partial file."""
    tmp = path.with_name(f".{path.name}.tmp")
    kept = "the views written so far are kept (--resume continues); the index is written last"
    with naming_write_errors(path, kept):
        try:
            tmp.write_bytes(data)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def _index_row(
    path: str, record: ChipRecord, depression_deg: float, azimuth_deg: float, size: int | None
) -> list[str]:
    """One ``index.csv`` row (:data:`~sar_zero123.domain.INDEX_COLUMNS`); ``size`` for a view."""
    height, width = (size, size) if size is not None else (record.height, record.width)
    return [
        path,
        record.target_class,
        record.target_type or "",
        record.serial,
        repr(depression_deg),
        repr(azimuth_deg),
        "" if height is None else str(height),
        "" if width is None else str(width),
    ]


def augment_dataset(config: AugmentConfig) -> Path:
    """Generate the requested views of the selected chips and write them as a dataset.

    Args:
        config: The options (:class:`AugmentConfig`).

    Returns:
        The output folder (pass it to :func:`~sar_zero123.data.load_index`).

    Raises:
        ValueError: naming the field, for an output folder that holds something else, a selection that is
            empty or would write more than :data:`MAX_AUGMENT_VIEWS` views, chips smaller than the
            pipeline's size or that the decibel scaling does not fit (more than half the pixels clipped),
            or requests outside the pipeline's trained ranges; all but the scaling are checked before any
            generation.
    """
    # 1. the source chips, the views they get, and the output folder's state
    out = Path(config.out)
    options = _recorded_options(config)
    check_output_dir(out, "out")
    restart = config.restart and out.is_dir() and any(not is_lock_file(p) for p in out.iterdir())
    if restart:  # before the lock file is made beside out: a refusal leaves the inputs as they were
        inputs = {name: options.get(name) for name in ("data", "pipeline", "scaling_file")}
        check_restart_target(out, {}, inputs, "out")  # either way round: out inside an input refused too
        if not (out / AUGMENT_FILE).is_file():
            raise ValueError(
                f"restart: out {str(out)!r} holds no {AUGMENT_FILE}: it is not an augmentation of this "
                "project, and --restart moves only those; name another out folder"
            )
    lock_output_folder(out, "out")  # one writer: a second augmentation into this folder is refused now
    if restart:
        move_aside(out)
    resuming = _check_out_folder(out, options)
    if resuming and not config.resume:
        raise ValueError(
            f"out: {str(out)!r} already holds this augmentation; continue it (--resume, the default) or pass "
            "--restart to move it aside"
        )
    records = load_index(config.data)
    selected = select_records(records, config.classes, config.depressions_deg, config.max_chips_per_class)
    requests = len(config.d_az or config.target_azimuths_deg) * len(config.d_el)
    if len(selected) * requests > MAX_AUGMENT_VIEWS:
        raise ValueError(
            f"data: {len(selected)} chips x {requests} requests = {len(selected) * requests} views, more "
            f"than {MAX_AUGMENT_VIEWS}; select fewer chips (classes, depressions_deg, max_chips_per_class) "
            "or fewer requests"
        )
    views = plan_views(selected, config.d_az, config.target_azimuths_deg, config.d_el)

    # 2. the pipeline, and every check that can fail before generating
    pipe = SARZero123Pipeline.from_pretrained(config.pipeline).to(config.device)
    pipe.set_progress_bar_config(disable=True)
    if getattr(pipe.config, "proxy", None) is not None:  # a dataset's fits share pose buckets: shortlisted
        pipe.register_to_config(proxy=with_shortlist(pipe.config.proxy))
    config.apply_scheduler(pipe)
    size = pipe.default_image_size
    _check_chip_sizes([record for _, record in selected], size)
    prepared_chip = _chip_loader(config.pipeline, config.scaling_file, size)
    if getattr(pipe.config, "proxy", None) is not None:  # chips no simulator vehicle fits: skipped, counted
        kept = _fitted_chips(pipe, selected, prepared_chip)
        if len(kept) < len(selected):
            kept_ids = {id(item) for item in kept}
            skipped = [str(item[1].path) for item in selected if id(item) not in kept_ids]
            logger.warning(
                "skipped %d of %d chips: no simulator vehicle fits them (fit score below %s): %s",
                len(skipped), len(selected), pipe.config.proxy["min_fit_score"], ", ".join(skipped[:5]),
            )  # fmt: skip
            if not kept:
                raise ValueError(
                    f"data: no selected chip holds a vehicle the simulator proxy fits ({skipped[0]})"
                )
            selected = kept
            views = plan_views(selected, config.d_az, config.target_azimuths_deg, config.d_el)
    check_trained_ranges(pipe.pose_projection.config, config.d_el, [r.depression_deg for _, r in selected])
    out.mkdir(parents=True, exist_ok=True)
    if not resuming:
        write_json_atomic(options, out / AUGMENT_FILE)
    scaling = _resolve_scaling(config.scaling_file, config.pipeline)
    write_json_atomic({"domain": VIEWS_DOMAIN, "scaling": scaling.to_dict()}, out / VIEWS_FILE)

    # 3. generate the batches that miss a view; each view has its own generators
    batches = [views[start : start + config.batch_size] for start in range(0, len(views), config.batch_size)]
    pending = [batch for batch in batches if not all((out / view.path).is_file() for view in batch)]
    for folder in sorted({(out / view.path).parent for batch in pending for view in batch}):
        folder.mkdir(parents=True, exist_ok=True)
    with progress_bar(total=sum(len(batch) for batch in pending), desc="augmenting", unit="view") as progress:
        for batch in pending:
            chips = np.stack([prepared_chip(view.record.path) for view in batch])  # (B, S, S)
            images = _generate(pipe, chips, batch, sampler=config.sampler_settings(), seed=config.seed)
            for view, image in zip(batch, images):
                if (out / view.path).is_file():  # written before a kill, from this same batch
                    continue
                magnitude = _view_magnitude(image, scaling)
                buffer = io.BytesIO()
                np.save(buffer, magnitude)
                _write_atomic(out / view.path, buffer.getvalue())
            progress.update(len(batch))

    # 4. the provenance, then the index, last
    real = selected if config.include_real else []
    rows = _index_rows(real, views, size, pipeline=config.pipeline, seed=config.seed, data_root=config.data)
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows([[*INDEX_COLUMNS, *PROVENANCE_COLUMNS], *rows])
    _write_atomic(out / PROVENANCE_FILE, text.getvalue().encode())
    write_index_atomic(out, [row[: len(INDEX_COLUMNS)] for row in rows])
    release_output_folder(out)
    return out


def _fitted_chips(
    pipe: SARZero123Pipeline, selected: list, prepared_chip: Callable[[Path], np.ndarray]
) -> list:
    """The selected chips whose simulator proxy fit scores at least the pipeline's ``proxy.min_fit_score``
    (the fits are remembered: generation does not run them again)."""
    proxy = pipe.config.proxy
    kept = []
    for start in range(0, len(selected), 64):
        chunk = selected[start : start + 64]
        chips = torch.from_numpy(np.stack([prepared_chip(record.path) for _, record in chunk]))[:, None]
        azimuth = torch.tensor([record.azimuth_deg for _, record in chunk])
        depression = torch.tensor([record.depression_deg for _, record in chunk])
        scores = fit_scores(chips, azimuth, depression, proxy)
        kept += [item for item, score in zip(chunk, scores) if score >= proxy["min_fit_score"]]
    return kept


def _chip_loader(pipeline: str, scaling_file: str | None, size: int) -> Callable[[Path], np.ndarray]:
    """``path -> normalised dB chip`` (``generate.py``'s :func:`~sar_zero123.generate.load_input_chip`),
    remembering the last chips: a chip's requests follow one another."""

    @functools.lru_cache(maxsize=64)
    def prepared_chip(path: Path) -> np.ndarray:
        try:
            chip_config = GenerateConfig(pipeline=pipeline, image=str(path), scaling_file=scaling_file)
            return load_input_chip(chip_config, size)
        except ValueError as error:
            raise ValueError(f"data: chip {path}: {error}") from None

    return prepared_chip


def _generate(
    pipe: SARZero123Pipeline,
    chips: np.ndarray,
    batch: Sequence[ViewRequest],
    *,
    sampler: SamplerSettings,
    seed: int,
) -> np.ndarray:
    """One pipeline call for a batch of views: ``(B, S, S)`` normalised dB from ``(B, S, S)`` chips; a
    ``sampler`` field left ``None`` is the pipeline's recorded value. Each chip's index pose (azimuth,
    depression) fits the simulator proxy of a pipeline that records one."""
    has_proxy = getattr(pipe.config, "proxy", None) is not None
    takes_depression = getattr(pipe.pose_projection.config, "input_depression", False) or has_proxy
    return pipe(
        torch.from_numpy(chips)[:, None],  # (B, 1, S, S)
        d_az=[view.d_az_deg for view in batch],
        d_el=[view.d_el_deg for view in batch],
        input_depression_deg=[view.record.depression_deg for view in batch] if takes_depression else None,
        generator=[view_generator(seed, view.row_index, view.request_index) for view in batch],
        output_type="np",
        input_azimuth_deg=[view.record.azimuth_deg for view in batch] if has_proxy else None,
        **sampler.sampler_arguments(),
    ).images[..., 0]


def _view_magnitude(image: np.ndarray, scaling: DecibelScaling) -> np.ndarray:
    """A generated view (normalised dB) as the float32 magnitude written to disk."""
    peak = float(scaling.denormalize(np.float64(1.0)))  # the largest magnitude the scaling represents
    return np.clip(scaling.denormalize(image.astype(np.float64)), 0.0, peak).astype(np.float32)


def _index_rows(
    real: Sequence[tuple[int, ChipRecord]],
    views: Sequence[ViewRequest],
    size: int,
    *,
    pipeline: str,
    seed: int,
    data_root: str | Path,
) -> list[list[str]]:
    """Rows of ``provenance.csv``: the index columns, then :data:`PROVENANCE_COLUMNS`."""
    data_root = Path(data_root).resolve()
    rows = []
    for _, record in real:
        row = _index_row(str(record.path), record, record.depression_deg, record.azimuth_deg, None)
        rows.append([*row, _source_path(record, data_root), "0.0", "0.0", "", "", "0"])
    for view in views:
        row = _index_row(view.path.as_posix(), view.record, view.depression_deg, view.azimuth_deg, size)
        source = _source_path(view.record, data_root)
        d_angles = [repr(view.d_az_deg), repr(view.d_el_deg)]
        rows.append([*row, source, *d_angles, pipeline, str(seed), "1"])
    return rows


def _source_path(record: ChipRecord, data_root: Path) -> str:
    """The chip's path as the source index gives it: relative to the data folder when inside it."""
    try:
        return record.path.relative_to(data_root).as_posix()
    except ValueError:
        return str(record.path)


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> Path:
    """Command-line entry point (``python -m sar_zero123.augment_dataset``, ``sar-zero123-augment``).

    Args:
        argv: Arguments without the program name; ``None`` reads ``sys.argv``.
        prog: The command's name in usage lines (``None``: the script's file name).

    Returns:
        The output folder.
    """
    return augment_dataset(parse_config(AugmentConfig, argv, prog=prog))

