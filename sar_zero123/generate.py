"""Generate novel views of one SAR chip from the command line.

Example::

    python -m sar_zero123.generate --image chip.png --d-az 30 --d-el 10   # the bundled prior
    python -m sar_zero123.generate --pipeline runs/pfm/pipeline --image chip.png \\
        --d-az 30 60 90 --d-el 0 --output_dir views/

writes, for each view ``i``, ``view_{i}_daz{d_az}_del{d_el}.png`` (8-bit) and ``.npy`` (float32 (H, W)),
both normalised dB, plus ``input.png``, ``contact_sheet.png``, ``config.json`` and ``views.json`` (the
requests and what the arrays hold). The folder follows :mod:`sar_zero123.runs.folder`; a bad chip is
refused before anything is written. The chip is mapped to normalised dB with the pipeline's
``decibel_scaling.json``, else ``--scaling_file`` or the unit-magnitude default. ``--pipeline`` defaults
to the bundled prior for the chip: the proxy one when its absolute azimuth is known, else the rotated one.
A pipeline whose pose carries the input's absolute depression takes ``--input_depression``, else the
chip file's, else :data:`DEFAULT_INPUT_DEPRESSION_DEG` with a printed note.
"""

from __future__ import annotations

import numbers
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import PIL.Image
import torch
from matplotlib.figure import Figure

from sar_zero123.config import parse_config
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import (
    SCALING_FILE,
    DecibelScaling,
    center_crop_resize,
    check_magnitude,
    load_magnitude,
    parse_sample_name,
    read_mstar_raw,
)
from sar_zero123.data.mstar_raw import is_mstar_raw
from sar_zero123.data.splits import TRAIN_DEPRESSION_DEG
from sar_zero123.domain import MAX_IMAGE_SIZE, naming_write_errors
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import SamplerSettings
from sar_zero123.model.view_request import check_delta_bounds, check_target_depression
from sar_zero123.pretrained import SIM_PRIOR_IDENTITY, SIM_PRIOR_ROTATED, resolve_pretrained
from sar_zero123.progress import progress_bar
from sar_zero123.runs.folder import RunFolder, StageTimer, data_identity, finish_run
from sar_zero123.runs.launch import check_device
from sar_zero123.runs.stage import open_stage_folder

__all__ = [
    "DEFAULT_INPUT_DEPRESSION_DEG",
    "GENERATE_MAY_DIFFER",
    "MAX_VIEWS",
    "GenerateConfig",
    "chip_azimuth_deg",
    "chip_depression_deg",
    "generate_views",
    "main",
    "resolve_input_depression",
]

#: Name of the decibel-scaling file a training run may save next to its pipeline.
#: Refuse a chip when more than this fraction of its pixels leaves the scaling's dB range (it is on
#: another scale: raw magnitudes with unit bounds, or dB values read as magnitude); warn below it.
MAX_CLIPPED_FRACTION = 0.5
#: Input depression assumed for a chip that records none: MSTAR's training depression.
DEFAULT_INPUT_DEPRESSION_DEG = TRAIN_DEPRESSION_DEG
#: Most views one call generates: they are sampled as one batch and shown as one contact-sheet row.
MAX_VIEWS = 64
#: What each view's ``.npy`` (and ``.png``) holds, as ``views.json`` says beside them.
VIEWS_DOMAIN = (
    "normalised dB in [0, 1] (float32 .npy; the .png is the same at 8 bits): dB = min_db + value * (max_db - "
    "min_db), magnitude = sar_zero123.data.DecibelScaling(**scaling).denormalize(value)"
)
VIEWS_FILE = "views.json"
#: Settings that never change the views a folder holds: where it is and how it is reused.
GENERATE_MAY_DIFFER = ("output_dir", "resume", "restart")


@dataclass
class GenerateConfig(SamplerSettings):
    """Generate novel views of one SAR chip with a saved SARZero123Pipeline.

    Sampler fields left unset take the pipeline's recorded values, else the library's.
    """

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "input_domain", "scaling_file", "device", "image_size",
    )  # fmt: skip

    # SARZero123Pipeline.save_pretrained folder, or a bundled one's name; None: the best measured for this
    # chip, sim-prior-identity when its azimuth is known (--input_azimuth, a raw MSTAR header), else
    # sim-prior-rotated (docs/results/identity.md)
    pipeline: str | None = None
    image: str = ""  # input chip (PNG/JPEG/TIFF, .npy, .mat or raw MSTAR file)
    d_az: list[float] = field(default_factory=lambda: [30.0, 60.0, 90.0])  # azimuth deltas in degrees
    d_el: list[float] = field(default_factory=lambda: [0.0])  # depression deltas in degrees (1 or 1 per d_az)
    output_dir: str = "generated_views"  # output folder
    input_azimuth: float | None = None  # chip's absolute azimuth (deg); None: the file's (raw MSTAR), if any
    seed: int = 0  # view i uses torch.Generator().manual_seed(seed + i)
    input_domain: Literal["magnitude", "normalized_db"] = "magnitude"  # what the chip file holds
    scaling_file: str | None = None  # DecibelScaling JSON (default: <pipeline>/decibel_scaling.json or unit)
    image_size: int | None = None  # chip size fed to the model; default: the pipeline's own
    input_depression: float | None = None  # chip's depression (deg); None: the file's, else 17 (MSTAR's)
    device: str = "cpu"  # torch device
    resume: bool = False  # return a finished folder with these settings as it is; redo an unfinished one
    restart: bool = False  # move an existing folder at output_dir aside (never deleted) and generate anew

    def __post_init__(self) -> None:
        super().__post_init__()  # the sampler's fields, validated where they are declared
        if not self.image:
            raise ValueError("image: an input chip file is required")
        if self.pipeline is None:  # resolved here, so that the run's record names the pipeline it used
            known = self.input_azimuth is not None or chip_azimuth_deg(self.image) is not None
            self.pipeline = SIM_PRIOR_IDENTITY if known else SIM_PRIOR_ROTATED
        if not self.pipeline:
            raise ValueError("pipeline: a pipeline folder is required")
        if not self.d_az:
            raise ValueError("d_az: give at least one azimuth delta")
        if len(self.d_az) > MAX_VIEWS:
            raise ValueError(
                f"d_az: at most {MAX_VIEWS} views per call (one batch, one contact-sheet column each), got "
                f"{len(self.d_az)}; split the request into several calls"
            )
        if not all(np.isfinite(self.d_az)) or not all(np.isfinite(self.d_el)):
            raise ValueError(f"d_az/d_el must be finite, got {self.d_az} and {self.d_el}")
        check_delta_bounds(self.d_az, self.d_el)
        if len(self.d_el) not in (1, len(self.d_az)):
            raise ValueError(f"d_el: give 1 value or one per d_az ({len(self.d_az)}), got {len(self.d_el)}")
        if self.input_azimuth is not None and not np.isfinite(self.input_azimuth):
            raise ValueError(f"input_azimuth must be a finite angle in degrees, got {self.input_azimuth}")
        if self.image_size is not None and not 1 <= self.image_size <= MAX_IMAGE_SIZE:
            raise ValueError(f"image_size must lie in [1, {MAX_IMAGE_SIZE}] pixels, got {self.image_size}")
        if self.input_depression is not None and not 0.0 < self.input_depression < 90.0:
            raise ValueError(f"input_depression must lie in (0, 90) degrees, got {self.input_depression}")
        if self.resume and self.restart:
            raise ValueError("resume and restart: choose one (keep this folder's views, or move it aside)")
        check_device(self.device)


def _resolve_scaling(scaling_file: str | None, pipeline: str) -> DecibelScaling:
    path = Path(scaling_file) if scaling_file is not None else resolve_pretrained(pipeline) / SCALING_FILE
    if scaling_file is None and not path.exists():
        return DecibelScaling()
    return DecibelScaling.from_file(path)


def load_input_chip(config: GenerateConfig, size: int) -> np.ndarray:
    """The input chip as float32 ``(size, size)`` normalised dB in [0, 1].

    Raises:
        ValueError: If a ``normalized_db`` chip lies outside [0, 1], a magnitude is negative or not finite,
            or more than :data:`MAX_CLIPPED_FRACTION` of the pixels leave the dB range (fewer: a warning).
    """
    chip = center_crop_resize(load_magnitude(config.image), size=size, name=f"image {config.image!r}")
    if config.input_domain == "magnitude":
        scaling = _resolve_scaling(config.scaling_file, config.pipeline)
        check_magnitude(chip, name=f"image {config.image!r}")
        unclipped = scaling.normalize(chip, clip=False)
        tolerance = 1e-4  # a magnitude of exactly 1 normalises to 1 + float32 rounding
        clipped = float(np.mean((unclipped < -tolerance) | (unclipped > 1.0 + tolerance)))
        message = (
            f"image {config.image!r}: {clipped:.1%} of the pixels lie outside the scaling's dB range "
            f"[{scaling.min_db:g}, {scaling.max_db:g}] dB (magnitudes {chip.min():.4g}..{chip.max():.4g}) "
            "and are clipped"
        )
        if clipped > MAX_CLIPPED_FRACTION:
            raise ValueError(f"{message}; give the pipeline's --scaling_file or the right --input_domain")
        if clipped > 0:
            warnings.warn(message, stacklevel=2)
        chip = np.clip(unclipped, 0.0, 1.0).astype(np.float32)
    elif chip.min() < 0.0 or chip.max() > 1.0:
        raise ValueError(f"image: a normalized_db chip must lie in [0, 1], got [{chip.min()}, {chip.max()}]")
    return chip


def chip_depression_deg(path: str | Path) -> float | None:
    """The depression a chip file records: a raw MSTAR file's ``DesiredDepression``, the elevation in a SAMPLE
    file name, or ``None`` (images, ``.npy``)."""
    path = Path(path)
    if path.is_file() and is_mstar_raw(path):
        return read_mstar_raw(path).depression_deg
    try:
        return parse_sample_name(path)[1].depression_deg
    except ValueError:
        return None


def chip_azimuth_deg(path: str | Path) -> float | None:
    """The absolute azimuth a raw MSTAR file records (``TargetAz``), else ``None`` (a SAMPLE name's azimuth is
    a bin centre)."""
    path = Path(path)
    if path.is_file() and is_mstar_raw(path):
        return read_mstar_raw(path).azimuth_deg
    return None


def resolve_input_depression(image: str | Path, input_depression: float | None) -> tuple[float, str]:
    """``(depression_deg, source)`` of the input chip: ``input_depression`` (``"given"``), else the file's
    (``"file"``), else :data:`DEFAULT_INPUT_DEPRESSION_DEG` (``"default"``)."""
    if input_depression is not None:
        return float(input_depression), "given"
    recorded = chip_depression_deg(image)
    if recorded is not None:
        return recorded, "file"
    return DEFAULT_INPUT_DEPRESSION_DEG, "default"


def generate_views(
    pipe: SARZero123Pipeline,
    chip: np.ndarray,
    d_az: Sequence[float],
    d_el: Sequence[float],
    sampler: SamplerSettings,
    seed: int,
    *,
    input_depression_deg: float | None = None,
    input_azimuth_deg: float | None = None,
    return_fit_score: bool = False,
) -> np.ndarray | tuple[np.ndarray, float | None]:
    """All requested views of one chip in a single batched pipeline call.

    Args:
        chip: Normalised dB input ``(H, W)``.
        d_el: Depression deltas in degrees, 1 or one per ``d_az``.
        sampler: A field left ``None`` is the pipeline's recorded value.
        seed: View ``i`` is sampled with ``torch.Generator().manual_seed(seed + i)``.
        input_depression_deg: The chip's absolute depression, for a pipeline whose pose carries it.
        input_azimuth_deg: The chip's absolute azimuth (the simulator proxy's fit).
        return_fit_score: Also return the proxy's fit score (``None`` where none was fitted).

    Returns:
        Views in normalised dB, float32 ``(V, H, W)``; with ``return_fit_score``, ``(views, score)``.

    Raises:
        ValueError: Naming ``seed``, for a seed that is not an integer or whose views' seeds leave int64.
    """
    num_views = len(d_az)
    if isinstance(seed, bool | np.bool_) or not isinstance(seed, numbers.Integral):
        kind = type(seed).__name__
        raise ValueError(f"`seed` must be an integer (view i uses seed + i), got {kind} {seed!r}")
    if not -(2**63) <= seed <= 2**63 - num_views:  # torch.Generator.manual_seed takes 64-bit seeds
        raise ValueError(f"`seed` + view index must lie within int64 for {num_views} view(s), got {seed}")
    d_el = list(d_el) * num_views if len(d_el) == 1 else list(d_el)
    images = torch.from_numpy(chip)[None, None].expand(num_views, -1, -1, -1)  # (V, 1, H, W)
    generators = [torch.Generator(pipe.device).manual_seed(seed + i) for i in range(num_views)]
    out = pipe(
        images,
        d_az=list(d_az),
        d_el=d_el,
        input_depression_deg=input_depression_deg,
        input_azimuth_deg=input_azimuth_deg,
        generator=generators,
        output_type="np",
        **sampler.sampler_arguments(),
    )
    views = out.images[..., 0]
    if not return_fit_score:
        return views
    scores = out.proxy_fit_scores
    return views, None if scores is None else float(scores[0])  # one chip: every view shares its fit


def _save_png(array: np.ndarray, path: Path) -> None:
    PIL.Image.fromarray((np.clip(array, 0.0, 1.0) * 255.0).round().astype(np.uint8), mode="L").save(path)


def _contact_sheet(chip: np.ndarray, views: np.ndarray, titles: list[str], path: Path) -> None:
    columns = len(views) + 1
    # A bare Figure renders through Agg without pyplot's global state or a display.
    figure = Figure(figsize=(2.2 * columns, 2.5))
    axes = figure.subplots(1, columns, squeeze=False)
    for axis, image, title in zip(axes[0], [chip, *views], ["input", *titles]):
        axis.imshow(image, cmap="gray", vmin=0.0, vmax=1.0)
        axis.set_title(title, fontsize=8)
        axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def _open_output_dir(config: GenerateConfig, write: bool) -> RunFolder:
    """The run-folder rule on ``output_dir``; the input chip file is identified by its SHA-256."""
    if not Path(config.image).is_file():
        raise FileNotFoundError(f"image: {config.image!r} is not a file")
    return open_stage_folder(
        config.output_dir, "generate", config, data={"image": data_identity(config.image)},
        resume=config.resume, restart=config.restart, may_differ=GENERATE_MAY_DIFFER, write=write,
        resume_hint="--resume",
    )  # fmt: skip


def main(argv: Sequence[str] | None = None) -> Path:
    """Command-line entry point; returns the output folder (with ``--resume``, a finished one as it is).

    Raises:
        ValueError: Before anything is written, for a folder holding other work or a bad input chip.
        FileNotFoundError: Before anything is written, for a missing chip or pipeline.
    """
    config = parse_config(GenerateConfig, argv)
    timer = StageTimer()
    # 1. the folder checked (nothing written), then the pipeline and the chip, then the views in memory:
    # a folder holding other work, a bad chip and a failed sampling all leave the disk as it was
    if _open_output_dir(config, write=False).finished:
        return Path(config.output_dir)
    pipe = SARZero123Pipeline.from_pretrained(config.pipeline).to(config.device)
    config.apply_scheduler(pipe)
    size = config.image_size or pipe.default_image_size
    if size > 2 * pipe.default_image_size:  # the cost grows with its square; the model never saw such sizes
        raise ValueError(
            f"image_size: at most twice the pipeline's trained size {pipe.default_image_size} px "
            f"({2 * pipe.default_image_size}), got {size}; leave it out to use the trained size"
        )
    if size % pipe.size_multiple:  # the VAE and the UNet halve it: named here, not as the pipeline's `image`
        raise ValueError(
            f"image_size: a multiple of {pipe.size_multiple} px for this pipeline (its VAE and UNet "
            f"downsampling), got {size}; leave it out to use the trained size {pipe.default_image_size}"
        )
    chip = load_input_chip(config, size)
    input_depression_deg = None
    if getattr(pipe.pose_projection.config, "input_depression", False):
        input_depression_deg, source = resolve_input_depression(config.image, config.input_depression)
        if source == "default":
            print(
                f"note: {config.image!r} records no depression angle; assuming the input chip was taken at "
                f"{input_depression_deg:g} deg (MSTAR's training depression); give --input_depression"
            )
        elif source == "file":
            print(f"note: input depression {input_depression_deg:g} deg, read from {config.image!r}")
    else:  # a depression given or recorded bounds the target depression only (the pose does not take it)
        depression, source = resolve_input_depression(config.image, config.input_depression)
        if source != "default":
            d_el = torch.tensor(config.d_el, dtype=torch.float64)
            check_target_depression(torch.full_like(d_el, depression), d_el)
        if config.input_depression is not None:
            print("note: this pipeline's pose does not take the input's depression; --input_depression only "
                  "bounds the target depression (input + d_el) to (0, 90) deg")  # fmt: skip
    input_azimuth_deg = config.input_azimuth
    if input_azimuth_deg is None:
        input_azimuth_deg = chip_azimuth_deg(config.image)
        if input_azimuth_deg is not None:  # a pipeline recording a proxy start fits its proxy with it
            print(f"note: input azimuth {input_azimuth_deg:g} deg, read from {config.image!r}")
    if input_azimuth_deg is not None and input_depression_deg is None:  # the proxy's fit needs the depression
        input_depression_deg, _ = resolve_input_depression(config.image, config.input_depression)
    views = generate_views(
        pipe,
        chip,
        config.d_az,
        config.d_el,
        config.sampler_settings(),
        config.seed,
        input_depression_deg=input_depression_deg,
        input_azimuth_deg=input_azimuth_deg,
        return_fit_score=True,
    )
    views, fit_score = views

    # 2. the folder opened for real (an old one moved aside with --restart), the views written, the record
    folder = _open_output_dir(config, write=True)
    out = folder.path
    save_config(config, out)
    d_el = config.d_el * len(config.d_az) if len(config.d_el) == 1 else config.d_el
    titles, outputs, listed = [], ["config.json", "input.png"], []
    _save_png(chip, out / "input.png")
    for index, (view, d_az_deg, d_el_deg) in enumerate(
        progress_bar(list(zip(views, config.d_az, d_el)), desc="writing views", unit="view")
    ):
        stem = f"view_{index:02d}_daz{d_az_deg:+07.2f}_del{d_el_deg:+06.2f}"
        with naming_write_errors(out / stem, "the run is not marked finished (--resume redoes it)"):
            _save_png(view, out / f"{stem}.png")
            np.save(out / f"{stem}.npy", view.astype(np.float32))
        titles.append(f"d_az {d_az_deg:g}, d_el {d_el_deg:g}")
        listed.append({"png": f"{stem}.png", "npy": f"{stem}.npy", "d_az_deg": float(d_az_deg),
                       "d_el_deg": float(d_el_deg)})  # fmt: skip
        outputs += [f"{stem}.png", f"{stem}.npy"]
    _contact_sheet(chip, views, titles, out / "contact_sheet.png")
    scaling = _resolve_scaling(config.scaling_file, config.pipeline).to_dict()
    record = {"domain": VIEWS_DOMAIN, "scaling": scaling, "views": listed, "proxy_fit_score": fit_score}
    write_json_atomic(record, out / VIEWS_FILE)
    finish_run(folder, [*outputs, "contact_sheet.png", VIEWS_FILE], seconds=timer.seconds)
    return out


if __name__ == "__main__":  # exit 0 on success; a refusal in one line (--traceback: in full)
    from sar_zero123.runs.refusals import run_command

    raise SystemExit(run_command(main, "sar-zero123-generate"))
