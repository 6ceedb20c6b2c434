"""Figures of the co-domain augmentations, like the paper's Fig. 3 (sampled maps) and Fig. 4 (examples).

``fig3_monotonic_maps.png``: 50 random monotonic maps (Algorithm 1) for each of gamma in {0, 1} and
Q in {16, 256}. ``fig4_augmentations.png``: every preset of ``sar_zero123.augment.PRESETS`` on a few
chips from an image folder with ``index.csv`` (e.g. ``../shared/data/mstar``), one chip per class,
shown in normalised dB.

    python train/plot_augmentations.py --data ../shared/data/mstar --out_dir docs/figures
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from sar_zero123.augment import PRESETS, augment_batch, sample_monotonic_map  # noqa: E402
from sar_zero123.config import parse_config  # noqa: E402
from sar_zero123.config.json_io import save_config  # noqa: E402
from sar_zero123.data import DecibelScaling, center_crop_resize, load_index, load_magnitude  # noqa: E402


@dataclass
class PlotConfig:
    data: str = ""  # folder with index.csv and chips for Fig. 4; empty = skip Fig. 4
    out_dir: str = "docs/figures"  # where the PNGs (and config.json) go
    num_maps: int = 50  # monotonic maps drawn per panel of Fig. 3
    num_chips: int = 4  # chips in Fig. 4 (one per class, classes in sorted order)
    depression_deg: float = 17.0  # take Fig. 4 chips at this depression
    size: int = 128  # Fig. 4 chips are centre-cropped/resized to size x size
    seed: int = 0  # seed of the single generator behind every random draw
    dpi: int = 100  # resolution of the PNGs

    def __post_init__(self) -> None:
        if self.num_maps < 1:
            raise ValueError(f"num_maps must be >= 1, got {self.num_maps}")
        if self.num_chips < 1:
            raise ValueError(f"num_chips must be >= 1, got {self.num_chips}")
        if self.size < 8:
            raise ValueError(f"size must be >= 8, got {self.size}")
        if self.dpi < 10:
            raise ValueError(f"dpi must be >= 10, got {self.dpi}")
        if self.data and not (Path(self.data) / "index.csv").is_file():
            raise ValueError(f"data must be a folder with index.csv, got {self.data!r}")


def plot_monotonic_maps(num_maps: int, generator: torch.Generator, path: Path, dpi: int) -> Path:
    """Fig. 3: ``num_maps`` sampled maps for gamma in {0, 1} (rows) and Q in {16, 256} (columns)."""
    levels_plot = torch.linspace(0.0, 1.0, 513, dtype=torch.float64)
    fig, axes = plt.subplots(2, 2, figsize=(7.0, 7.0), sharex=True, sharey=True)
    for row, gamma in enumerate((0.0, 1.0)):
        for col, q in enumerate((16, 256)):
            table = sample_monotonic_map(num_maps, q=q, gamma=gamma, generator=generator, dtype=torch.float64)
            levels = np.linspace(0.0, 1.0, q)
            ax = axes[row, col]
            for curve in table.numpy():
                ax.plot(levels_plot.numpy(), np.interp(levels_plot.numpy(), levels, curve), lw=0.6, alpha=0.6)
            ax.plot([0, 1], [0, 1], "k--", lw=1.0)
            ax.set_title(f"$\\gamma$ = {gamma:g}, Q = {q}")
            ax.set_aspect("equal")
            if row == 1:
                ax.set_xlabel("input magnitude")
            if col == 0:
                ax.set_ylabel("mapped magnitude")
    fig.suptitle(f"{num_maps} random monotonic maps (Algorithm 1)")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def load_example_chips(
    data: Path, num_chips: int, depression_deg: float, size: int
) -> tuple[torch.Tensor, list]:
    """The first chip (by path) of each of the first ``num_chips`` classes, as (N, 1, S, S) magnitudes."""
    records = sorted(load_index(data), key=lambda r: str(r.path))
    by_class: dict[str, object] = {}
    for record in records:
        if abs(record.depression_deg - depression_deg) < 0.5 and record.target_class not in by_class:
            by_class[record.target_class] = record
    if not by_class:
        raise ValueError(f"data: no chip at depression {depression_deg} deg in {data}")
    chosen = [by_class[name] for name in sorted(by_class)[:num_chips]]
    chips = [center_crop_resize(load_magnitude(record.path), size) for record in chosen]
    return torch.from_numpy(np.stack(chips)[:, None]).clamp(0.0, 1.0), chosen


def plot_preset_examples(
    magnitude: torch.Tensor, labels: list[str], generator: torch.Generator, path: Path, dpi: int
) -> Path:
    """Fig. 4: the input and one view per preset (columns) for every chip (rows), in normalised dB."""
    scaling = DecibelScaling()
    columns = {"input": scaling.normalize(magnitude)}
    for name in PRESETS:
        columns[name] = augment_batch(magnitude, name, scaling, generator=generator)
    rows = magnitude.shape[0]
    fig, axes = plt.subplots(rows, len(columns), figsize=(1.6 * len(columns), 1.7 * rows), squeeze=False)
    for col, (name, images) in enumerate(columns.items()):
        for row in range(rows):
            ax = axes[row, col]
            ax.imshow(images[row, 0].numpy(), cmap="gray", vmin=0.0, vmax=1.0)
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(name, fontsize=8)
            if col == 0:
                ax.set_ylabel(labels[row], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> dict[str, Path]:
    config = parse_config(PlotConfig, argv)
    out_dir = Path(config.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, out_dir, name="plot_augmentations_config.json")
    generator = torch.Generator().manual_seed(config.seed)
    written = {
        "fig3": plot_monotonic_maps(
            config.num_maps, generator, out_dir / "fig3_monotonic_maps.png", config.dpi
        )
    }
    if config.data:
        magnitude, records = load_example_chips(
            Path(config.data), config.num_chips, config.depression_deg, config.size
        )
        labels = [f"{r.target_class} {r.azimuth_deg:.0f}°" for r in records]
        written["fig4"] = plot_preset_examples(
            magnitude, labels, generator, out_dir / "fig4_augmentations.png", config.dpi
        )
    for path in written.values():
        print(f"wrote {path}")
    return written


if __name__ == "__main__":
    main(sys.argv[1:])
