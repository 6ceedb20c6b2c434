"""The Table I stage: one SimCLR encoder per augmentation preset, scored by four frozen-feature probes.

Each preset's encoder is trained (or given, ``encoders``) under ``<output_dir>/<preset>/``; its frozen
features feed the linear, MLP azimuth, 1-NN and 1-NN azimuth probes (:mod:`sar_zero123.training.probes`).
Writes ``table1.json``, ``table1.md`` and, with ``simclr-full`` and ``speckle+monotonic``, ``tsne.png``
(Fig. 6).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sar_zero123.augment import PRESETS
from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import ChipDataset, prepare_splits
from sar_zero123.data.splits import check_protocol
from sar_zero123.domain import MAX_IMAGE_SIZE
from sar_zero123.encoder import SAREncoder, SAREncoderConfig, resolve_encoder_dir
from sar_zero123.evaluation.probes import FeatureSet, extract_features
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.stages.evaluators import model_identity
from sar_zero123.stages.simclr import PretrainSimCLRConfig, run_simclr, select_chips
from sar_zero123.training.probes import run_probes

logger = logging.getLogger(__name__)

__all__ = [
    "COLUMNS",
    "PAPER_TABLE1",
    "TABLE1_MAY_DIFFER",
    "TSNE_PRESETS",
    "Table1Config",
    "format_markdown",
    "plot_tsne",
    "run_table1",
]

# Table I of the paper: (MLP accuracy %, MLP azimuth error deg, 1-NN accuracy %, 1-NN azimuth error deg)
PAPER_TABLE1 = {
    "simclr-full": (98.7, 28.5, 99.6, 12.8),
    "speckle+monotonic": (98.7, 9.8, 99.7, 3.1),
    "speckle+monotonic-as-run": (98.7, 9.8, 99.7, 3.1),  # the setting the paper's encoder was trained with
}
TSNE_PRESETS = ("simclr-full", "speckle+monotonic")
#: The floor row: an untrained encoder of the same architecture, probed the same way.
FLOOR_ROW = "random init (floor)"
COLUMNS = ("linear_accuracy", "mlp_azimuth_error_deg", "knn_accuracy", "knn_azimuth_error_deg")
#: Settings that never change what the folder holds.
TABLE1_MAY_DIFFER = ("resume", "restart", "output_dir", "num_workers")


@dataclass
class Table1Config:
    """Table I: SimCLR encoders per augmentation preset, probed on frozen MSTAR features."""

    ADVANCED_FIELDS = (
        "image_size", "global_batch_size", "cifar_stem", "hidden_sizes", "embedding_size",
        "mixed_precision", "max_train_chips", "probe_epochs", "tsne", "tsne_points", "num_workers",
    )  # fmt: skip
    REMOVED_FIELDS = {
        "channels_last": RemovedField(False, "channels-last memory changed nothing measured; convolutions "
                                      "run in the default memory format"),
        "max_test_chips": RemovedField(None, "the probes are scored on every test chip"),
        "work_dir": RemovedField(None, "the simulated dataset is cached in output_dir"),
    }  # fmt: skip

    output_dir: str = "runs/table1"  # one sub-folder per preset, plus table1.json, table1.md, tsne.png
    data: str | None = None  # data folder with index.csv; None simulates the built-in dataset
    protocol: str = "extended"  # split protocol: encoders and probes train on "train", report on "test"
    presets: tuple[str, ...] = tuple(PRESETS)  # Table I rows to run
    encoders: list[str] = field(default_factory=list)  # existing encoder or run folders, one per preset
    epochs: int = 500  # SimCLR epochs per preset (paper: 500)
    max_train_steps: int | None = None  # cap on SimCLR steps per preset (quick runs)
    image_size: int = 128  # chip side in pixels (paper: 128)
    global_batch_size: int = 256  # SimCLR chips per step over all processes (pretrain_simclr.py)
    learning_rate: float = 0.06  # SimCLR SGD learning rate
    cifar_stem: bool = True  # 3x3 stride-1 stem without max-pool (reference setting)
    hidden_sizes: tuple[int, ...] = (64, 128, 256, 512)  # ResNet-18 stage widths
    embedding_size: int = 64  # stem width
    mixed_precision: str = "no"  # accelerate mixed precision for pretraining: "no", "fp16", "bf16"
    max_train_chips: int | None = None  # seeded random subset of train chips (quick runs); None = all
    probe_epochs: int = 100  # epochs of the linear and MLP probes
    tsne: bool = True  # draw the t-SNE figure when simclr-full and speckle+monotonic are both run
    floor: bool = True  # also probe an untrained encoder of the first row's architecture (the floor)
    tsne_points: int = 1000  # test chips per t-SNE panel
    num_workers: int = 0  # DataLoader workers for reading chips
    seed: int = 0  # seeds splits, pretraining, probes and t-SNE
    resume: bool = False  # continue an unfinished table with these settings; a finished one is returned
    restart: bool = False  # move an existing table in output_dir aside (never deleted) and start over

    def __post_init__(self) -> None:
        unknown = [p for p in self.presets if p not in PRESETS]
        if unknown or not self.presets:
            raise ValueError(
                f"presets must be non-empty names from {sorted(PRESETS)}, got {list(self.presets)}"
            )
        if len(set(self.presets)) != len(self.presets):
            raise ValueError(f"presets must be distinct, got {list(self.presets)}")
        if self.encoders and len(self.encoders) != len(self.presets):
            raise ValueError(
                f"encoders must name one folder per preset ({len(self.presets)}), got {len(self.encoders)}"
            )
        check_minimum(self, "image_size", minimum=1, maximum=MAX_IMAGE_SIZE)
        check_minimum(self, "epochs", "global_batch_size", "probe_epochs", "tsne_points", minimum=1)
        check_minimum(self, "max_train_steps", "max_train_chips", minimum=1, optional=True)
        check_protocol(self.protocol)
        if self.resume and self.restart:
            raise ValueError("resume and restart: choose one (continue this table, or move it aside)")
        if not self.encoders:
            for preset in self.presets:  # the SimCLR settings of every row, checked before any work
                self.simclr_config(preset)

    def simclr_config(self, preset: str) -> PretrainSimCLRConfig:
        """The SimCLR run of one preset, in ``<output_dir>/<preset>`` (continued on resume)."""
        return PretrainSimCLRConfig(
            output_dir=str(Path(self.output_dir) / preset),
            data=self.data,
            protocol=self.protocol,
            work_dir=self.output_dir,  # every preset's run reads the one simulated dataset
            max_train_chips=self.max_train_chips,
            image_size=self.image_size,
            preset=preset,
            cifar_stem=self.cifar_stem,
            hidden_sizes=self.hidden_sizes,
            embedding_size=self.embedding_size,
            global_batch_size=self.global_batch_size,
            epochs=self.epochs,
            max_train_steps=self.max_train_steps,
            learning_rate=self.learning_rate,
            mixed_precision=self.mixed_precision,
            resume_from_checkpoint="latest",
            num_workers=self.num_workers,
            seed=self.seed,
        )


def format_markdown(rows: dict[str, dict[str, Any]], config: Table1Config) -> str:
    """Table I as Markdown: measured numbers next to the paper's."""
    if config.encoders:  # probed as given: the SimCLR settings of this config were not used
        trained = "encoders " + ", ".join(f"`{path}`" for path in config.encoders) + " (trained elsewhere)"
    else:
        trained = f"{config.epochs} SimCLR epochs" + (
            f" capped at {config.max_train_steps} steps" if config.max_train_steps else ""
        )
    lines = [
        f"Table I on `{config.data or 'built-in simulator'}` ({config.protocol} protocol), "
        f"{config.image_size}x{config.image_size} px, {trained}, probes {config.probe_epochs} epochs "
        "(classes: a linear probe; azimuth: an MLP). Paper: 500 epochs, 128x128.",
        "",
        "| preset | linear acc. % | MLP az. err. deg | 1-NN acc. % | 1-NN az. err. deg "
        "| paper MLP acc. / az. | paper 1-NN acc. / az. |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for preset, row in rows.items():
        measured = " | ".join(f"{row[c]:.1f}" for c in COLUMNS)
        paper = PAPER_TABLE1.get(preset)
        paper_cells = f"{paper[0]} / {paper[1]} | {paper[2]} / {paper[3]}" if paper else "- | -"
        lines.append(f"| {preset} | {measured} | {paper_cells} |")
    if {"speckle+monotonic", "speckle+monotonic-as-run"} & set(rows):
        lines += [
            "",
            "Paper row Speckle Rayleigh + Monotonic: `speckle+monotonic` is Eq. (17) as written (per-pixel "
            "speckle, Q 512, always applied); `speckle+monotonic-as-run` is what the authors' encoder was "
            "trained with (speckle on the lookup-table levels, Q 4096, applied with probability 0.95).",
        ]
    return "\n".join(lines) + "\n"


def plot_tsne(features: dict[str, FeatureSet], class_names: list[str], path: Path, points: int, seed: int):
    """Fig. 6-style t-SNE of test features: one row per preset, coloured by class and by azimuth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.manifold import TSNE

    fig, axes = plt.subplots(len(features), 2, figsize=(10, 4.6 * len(features)), squeeze=False)
    for row, (preset, feature_set) in enumerate(features.items()):
        n = feature_set.features.shape[0]
        keep = np.sort(np.random.default_rng(seed).choice(n, size=min(points, n), replace=False))
        perplexity = float(min(30.0, max(2.0, (len(keep) - 1) / 3)))
        embedded = TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(
            feature_set.features[keep].numpy()
        )
        labels = feature_set.labels[keep].numpy()
        by_class = axes[row, 0].scatter(embedded[:, 0], embedded[:, 1], c=labels, cmap="tab10", s=4)
        axes[row, 0].set_title(f"{preset}: class")
        handles = [
            plt.Line2D([], [], marker="o", linestyle="", color=by_class.cmap(by_class.norm(i)), label=name)
            for i, name in enumerate(class_names)
            if (labels == i).any()
        ]
        axes[row, 0].legend(handles=handles, fontsize=7, markerscale=1.5, loc="best")
        by_azimuth = axes[row, 1].scatter(
            embedded[:, 0], embedded[:, 1], c=feature_set.azimuth_deg[keep].numpy(), cmap="twilight", s=4,
            vmin=0, vmax=360,
        )
        axes[row, 1].set_title(f"{preset}: azimuth (deg)")
        fig.colorbar(by_azimuth, ax=axes[row, 1])
        for ax in axes[row]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _given_encoders(config: Table1Config) -> list[Path]:
    """The encoder folders of ``config.encoders``, checked before any work.

    Raises:
        FileNotFoundError: If a folder holds no saved encoder.
        ValueError: If an encoder takes another chip size than ``image_size``.
    """
    folders = [resolve_encoder_dir(path, field="encoders") for path in config.encoders]
    for folder in folders:
        size = SAREncoder.from_pretrained(folder).config.image_size  # also checks the config and weights
        if size != config.image_size:
            raise ValueError(f"encoders: {folder} takes {size} px chips, image_size is {config.image_size}")
    return folders


def _probe_sets(config: Table1Config, work_dir: Path) -> tuple[ChipDataset, ChipDataset]:
    """The probes' train chips (a seeded subset in quick runs) and every test chip, without augmentation."""
    splits = prepare_splits(config.data, config.protocol, work_dir, seed=config.seed)
    train_records = select_chips(splits["train"], config.max_train_chips, config.seed)
    test_records = list(splits["test"])
    train_set = ChipDataset(train_records, size=config.image_size)
    test_set = ChipDataset(test_records, size=config.image_size, class_names=train_set.class_names)
    return train_set, test_set


def _encoder_for(config: Table1Config, preset: str, given: Path | None) -> tuple[Path, dict[str, Any] | None]:
    """The encoder folder of one preset, given or pretrained now, and its SimCLR ``metrics.json``."""
    if given is None:
        logger.info("SimCLR run of %s", preset)
        given = run_simclr(config.simclr_config(preset)) / "encoder"
    metrics_path = given.parent / "metrics.json"
    return given, json.loads(metrics_path.read_text()) if metrics_path.is_file() else None


def _probe_rows(
    config: Table1Config, train_set: ChipDataset, test_set: ChipDataset, encoders: list[Path]
) -> tuple[dict[str, dict[str, Any]], dict[str, FeatureSet]]:
    """Every preset's probe results (a Table I row each) and the test features the t-SNE draws."""
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    rows: dict[str, dict[str, Any]] = {}
    tsne_features: dict[str, FeatureSet] = {}
    for index, preset in enumerate(config.presets):
        encoder_dir, pretrain = _encoder_for(config, preset, encoders[index] if encoders else None)
        encoder = SAREncoder.from_pretrained(encoder_dir, device=device)
        probes, test_features = _probe(config, encoder, train_set, test_set)
        rows[preset] = {**probes, "encoder": str(encoder_dir), "pretrain": pretrain}
        logger.info("%s: %s", preset, {k: round(v, 2) for k, v in probes.items()})
        if preset in TSNE_PRESETS:
            tsne_features[preset] = test_features
        if config.floor and index == 0:
            floor_config = encoder.config
    if config.floor:
        rows[FLOOR_ROW] = _floor_row(config, train_set, test_set, floor_config, device)
    return rows, tsne_features


def _floor_row(
    config: Table1Config,
    train_set: ChipDataset,
    test_set: ChipDataset,
    architecture: SAREncoderConfig,
    device: torch.device,
) -> dict[str, Any]:
    """The probes on an untrained (seeded) encoder of ``architecture``: the floor SimCLR must beat."""
    torch.manual_seed(config.seed)
    encoder = SAREncoder(architecture).to(device).eval()
    probes, _ = _probe(config, encoder, train_set, test_set)
    logger.info("%s: %s", FLOOR_ROW, {k: round(v, 2) for k, v in probes.items()})
    return {**probes, "encoder": "untrained", "architecture": architecture.to_dict(), "pretrain": None}


def _probe(
    config: Table1Config, encoder: SAREncoder, train_set: ChipDataset, test_set: ChipDataset
) -> tuple[dict[str, float], FeatureSet]:
    """The four probes on ``encoder``'s frozen features, and its test features."""
    train_features = extract_features(encoder, train_set, num_workers=config.num_workers)
    test_features = extract_features(encoder, test_set, num_workers=config.num_workers)
    generator = torch.Generator().manual_seed(config.seed)
    classes = len(train_set.class_names)
    return run_probes(train_features, test_features, classes, config.probe_epochs, generator), test_features


def run_table1(config: Table1Config) -> Path:
    """Build Table I in ``config.output_dir``; returns the folder.

    Raises:
        ValueError: Before any work, for a folder holding other work, or if an encoder takes another chip
            size than ``image_size``.
        FileNotFoundError: If ``data`` or an encoder folder does not exist.
    """
    timer = StageTimer()
    # 1. inputs checked, then the run-folder rule, before any work
    encoders = _given_encoders(config)
    inputs: dict[str, Any] = {"data": data_identity(config.data)}
    if encoders:
        inputs["encoders"] = [model_identity(path, f"encoders[{i}]") for i, path in enumerate(encoders)]
    folder = open_stage_folder(
        config.output_dir, "table1", config, data=inputs, resume=config.resume, restart=config.restart,
        may_differ=TABLE1_MAY_DIFFER, resume_hint="--resume",
    )  # fmt: skip
    if folder.finished:
        logger.info("%s already holds this table", folder.path)
        return folder.path
    output_dir = folder.path

    # 2. probe data: train and test splits, no augmentation
    with withdrawn_if_setup_fails(folder):
        train_set, test_set = _probe_sets(config, output_dir)
    save_config(config, output_dir)

    # 3. an encoder per preset (given, or a SimCLR run under the preset's own folder), then the probes
    rows, tsne_features = _probe_rows(config, train_set, test_set, encoders)

    # 4. tables and figure, then the record
    result = {
        "rows": rows,
        "paper": {k: dict(zip(COLUMNS, v)) for k, v in PAPER_TABLE1.items()},
        "train_chips": len(train_set),
        "test_chips": len(test_set),
        "class_names": train_set.class_names,
        "device": "cuda" if torch.cuda.is_available() else "cpu",
    }
    write_json_atomic(result, output_dir / "table1.json")
    (output_dir / "table1.md").write_text(format_markdown(rows, config))
    outputs = ["table1.json", "table1.md"]
    if config.tsne and len(tsne_features) == len(TSNE_PRESETS):
        ordered = {p: tsne_features[p] for p in TSNE_PRESETS}
        plot_tsne(ordered, train_set.class_names, output_dir / "tsne.png", config.tsne_points, config.seed)
        outputs.append("tsne.png")
    finish_run(folder, outputs, seconds=timer.seconds, results={"presets": list(config.presets)})
    return output_dir
