"""Contact sheets: simulated chips of each class at several azimuths, optionally beside real chips."""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from sar_zero123.domain import center_crop, to_decibels
from sar_zero123.sim.render import render_chip
from sar_zero123.sim.targets import TARGET_CLASSES, make_target

__all__ = ["DISPLAY_RANGE_DB", "MAX_SHEET_CELLS", "MAX_SHEET_COLUMNS", "contact_sheet"]

DISPLAY_RANGE_DB = (-40.0, 0.0)
#: Most columns of a contact sheet (one chip each): wider sheets are unreadable and slow to render.
MAX_SHEET_COLUMNS = 64
#: Most chips on one sheet (each is rendered, then drawn by matplotlib).
MAX_SHEET_CELLS = 1024
# Real classes shown by default, chosen to mirror the simulated shapes (tank, carrier, truck,
# bulldozer, self-propelled gun, anti-aircraft gun).
_REAL_CLASSES = ("T62", "BMP2", "ZIL131", "D7", "2S1", "ZSU234")


def _real_chips(
    root: Path, classes: Sequence[str], azimuths_deg: Sequence[float], depression_deg: float, size: int
) -> list[tuple[str, list[tuple[float, np.ndarray]]]]:
    """The chip nearest each azimuth for each class of an MSTAR-style image folder (8-bit files)."""
    with open(root / "index.csv", newline="") as f:
        records = [r for r in csv.DictReader(f) if abs(float(r["depression_deg"]) - depression_deg) < 0.5]
    out = []
    for class_name in classes:
        recs = [r for r in records if r["target_class"] == class_name]
        if not recs:
            continue
        row = []
        for az in azimuths_deg:
            r = min(recs, key=lambda r: abs((float(r["azimuth_deg"]) - az + 180.0) % 360.0 - 180.0))
            pixels = np.asarray(Image.open(root / r["path"]).convert("L"), dtype=np.float32) / 255.0
            row.append((float(r["azimuth_deg"]), center_crop(pixels, min(size, *pixels.shape))))
        out.append((class_name, row))
    return out


def contact_sheet(
    path: str | os.PathLike[str],
    classes: Sequence[str] | None = None,
    azimuths_deg: Sequence[float] = (0.0, 30.0, 60.0, 90.0, 135.0, 180.0, 270.0),
    depression_deg: float = 17.0,
    size: int = 128,
    seed: int = 0,
    instance: int = 0,
    real_root: str | os.PathLike[str] | None = None,
    real_classes: Sequence[str] = _REAL_CLASSES,
    dpi: int = 100,
) -> Path:
    """Write a PNG grid of simulated chips (one row per class, one column per azimuth), shown in dB.

    ``real_root`` (an MSTAR-style image folder) adds rows of its ``real_classes`` chips nearest each azimuth,
    centre-cropped to ``size``. Returns the PNG path.

    Raises:
        ValueError: For more than :data:`MAX_SHEET_COLUMNS` azimuths (or none) or :data:`MAX_SHEET_CELLS`
            chips, before any chip is rendered.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not 1 <= len(azimuths_deg) <= MAX_SHEET_COLUMNS:
        raise ValueError(
            f"azimuths_deg: expected 1 to {MAX_SHEET_COLUMNS} azimuths (one sheet column each), "
            f"got {len(azimuths_deg)}"
        )
    classes = list(TARGET_CLASSES) if classes is None else [str(c).upper() for c in classes]
    planned_rows = len(classes) + (len(real_classes) if real_root is not None else 0)
    if planned_rows * len(azimuths_deg) > MAX_SHEET_CELLS:
        raise ValueError(
            f"classes x azimuths_deg: at most {MAX_SHEET_CELLS} chips per sheet, got {planned_rows} rows x "
            f"{len(azimuths_deg)} azimuths"
        )
    rows: list[tuple[str, list[tuple[float, np.ndarray]]]] = []
    for i, class_name in enumerate(classes):
        target = make_target(class_name, instance)
        chips = []
        for j, az in enumerate(azimuths_deg):
            rng = np.random.default_rng([int(seed), i, j])
            chips.append((float(az), render_chip(target, az, depression_deg, size, rng)))
        rows.append((f"sim {class_name}", chips))
    if real_root is not None:
        real = _real_chips(Path(real_root), real_classes, azimuths_deg, depression_deg, size)
        rows += [(f"MSTAR {name}", chips) for name, chips in real]

    n_rows, n_cols = len(rows), len(azimuths_deg)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(1.6 * n_cols, 1.7 * n_rows), squeeze=False)
    for r, (label, chips) in enumerate(rows):
        for c, (az, chip) in enumerate(chips):
            ax = axes[r, c]
            ax.imshow(to_decibels(chip), cmap="gray", vmin=DISPLAY_RANGE_DB[0], vmax=DISPLAY_RANGE_DB[1])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{az:.0f} deg", fontsize=7, pad=2)
            if c == 0:
                ax.set_ylabel(label, fontsize=7)
    fig.suptitle(
        f"depression {depression_deg:g} deg, radar at the bottom, {DISPLAY_RANGE_DB[0]:.0f}..0 dB", fontsize=8
    )
    return _save_grey_png(fig, path, dpi)


def _save_grey_png(fig, path: str | os.PathLike[str], dpi: int) -> Path:
    """Save a grey figure as a one-channel 8-bit PNG (about 4x smaller than RGBA) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.3 / fig.get_figheight()))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format="png")
    plt.close(fig)
    Image.open(buffer).convert("L").save(out, optimize=True)
    return out


def procedural_contact_sheet(
    path: str | os.PathLike[str],
    seeds: Sequence[int] = tuple(range(24)),
    depressions_deg: Sequence[float] = (17.0, 45.0),
    azimuth_deg: float = 30.0,
    size: int = 64,
    seed: int = 0,
    columns: int = 8,
    dpi: int = 100,
) -> Path:
    """Write a PNG grid of procedural vehicles, each at one azimuth and each of ``depressions_deg`` side by
    side, so that silhouettes and shadows compare; returns the PNG path.

    Raises:
        ValueError: For a sheet wider than :data:`MAX_SHEET_COLUMNS` cells or with more than
            :data:`MAX_SHEET_CELLS` chips, or an empty one, before any chip is rendered.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sar_zero123.sim.procedural import make_procedural_target

    seeds = [int(s) for s in seeds]
    per_row = int(columns) * len(depressions_deg)
    if not seeds or int(columns) < 1 or not 1 <= per_row <= MAX_SHEET_COLUMNS:
        raise ValueError(
            f"columns x depressions_deg: expected 1 to {MAX_SHEET_COLUMNS} cells per row and at least one "
            f"seed, got {int(columns)} x {len(depressions_deg)} and {len(seeds)} seeds"
        )
    if len(seeds) * len(depressions_deg) > MAX_SHEET_CELLS:
        raise ValueError(
            f"seeds: at most {MAX_SHEET_CELLS} chips per sheet, got {len(seeds)} vehicles x "
            f"{len(depressions_deg)} depressions"
        )
    n_rows = -(-len(seeds) // int(columns))
    fig, axes = plt.subplots(n_rows, per_row, figsize=(1.1 * per_row, 1.25 * n_rows), squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for i, vehicle in enumerate(seeds):
        target = make_procedural_target(vehicle)
        for j, depression in enumerate(depressions_deg):
            rng = np.random.default_rng([int(seed), i, j])
            chip = render_chip(target, azimuth_deg, depression, size, rng)
            ax = axes[i // int(columns), (i % int(columns)) * len(depressions_deg) + j]
            ax.imshow(to_decibels(chip), cmap="gray", vmin=DISPLAY_RANGE_DB[0], vmax=DISPLAY_RANGE_DB[1])
            ax.set_title(f"#{vehicle} {depression:g} deg", fontsize=6, pad=1)
    fig.suptitle(
        f"procedural vehicles at azimuth {azimuth_deg:g} deg, depressions {list(depressions_deg)} deg, "
        f"radar at the bottom, {DISPLAY_RANGE_DB[0]:.0f}..0 dB",
        fontsize=8,
    )
    return _save_grey_png(fig, path, dpi)
