"""The Table II stage: synthetic-to-real transfer on SAMPLE with co-domain augmentations.

``python train/synth_to_real.py`` parses its flags into :class:`SynthToRealConfig` and calls
:func:`run_synth_to_real`. For every augmentation row a ResNet-18 classifier
(:class:`~sar_zero123.evaluation.evaluators.SARClassifier`, trained from scratch) learns the classes from
SAMPLE's *synthetic* chips, augmented on the training device with the row's preset
(:func:`~sar_zero123.augment.augment_batch`; row ``none`` = no augmentation), and is tested on the
*measured* (real) twins. Writes ``table2.json``, ``table2.md`` and one ``<row>/classifier`` folder per row.

The folder follows :mod:`sar_zero123.runs.folder`: a folder holding other work is refused before
any work, naming each difference; an unfinished table with the same settings is continued only with
``resume`` (each row whose classifier was saved is kept) and a finished one is then returned at once;
``restart`` moves an old table aside.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from sar_zero123.augment import PRESETS
from sar_zero123.config import RemovedField, check_minimum
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, load_sample
from sar_zero123.evaluation.evaluators import EVALUATOR_CONFIG_NAME, load_evaluator
from sar_zero123.runs.folder import StageTimer, data_identity, finish_run
from sar_zero123.runs.stage import open_stage_folder, withdrawn_if_setup_fails
from sar_zero123.training.synth_to_real import ADAMW_WEIGHT_DECAY, NO_AUGMENTATION, train_row

logger = logging.getLogger(__name__)

__all__ = [
    "NO_AUGMENTATION",
    "SYNTH_TO_REAL_MAY_DIFFER",
    "SynthToRealConfig",
    "load_chips",
    "run_synth_to_real",
    "train_row",
]

#: Settings that never change what the folder holds: where it is, how the chips are read, how to continue.
SYNTH_TO_REAL_MAY_DIFFER = ("resume", "restart", "output_dir", "num_workers")


@dataclass
class SynthToRealConfig:
    """Table II: classifiers trained on SAMPLE synthetic chips with each augmentation, tested on real."""

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = (
        "image_size", "cifar_stem", "hidden_sizes", "embedding_size", "train_batch_size", "learning_rate",
        "mixed_precision", "num_workers",
    )  # fmt: skip
    #: Settings removed as constants (no recipe, page or measured run set another value): a config or run
    #: folder holding the old default reads as before; another value is refused with the reason.
    REMOVED_FIELDS = {"weight_decay": RemovedField(5e-4, f"AdamW's weight decay is {ADAMW_WEIGHT_DECAY:g}")}

    sample: str | None = None  # SAMPLE folder (png_images/ and/or mat_files/); required
    image_format: str = "qpm"  # SAMPLE variant: "qpm", "decibel" (PNG) or "mat" (complex .mat)
    output_dir: str = "runs/table2"  # table2.json, table2.md and <row>/classifier
    rows: tuple[str, ...] = (NO_AUGMENTATION, *PRESETS)  # augmentation rows ("none" or preset names)
    image_size: int = 128  # chip side in pixels (SAMPLE chips are 128x128)
    cifar_stem: bool = True  # 3x3 stride-1 stem without max-pool
    hidden_sizes: tuple[int, ...] = (64, 128, 256, 512)  # ResNet-18 stage widths
    embedding_size: int = 64  # stem width
    epochs: int = 30  # passes over the synthetic chips per row
    train_batch_size: int = 64  # chips per process per step
    learning_rate: float = 1e-3  # AdamW peak learning rate (cosine decay to 0)
    mixed_precision: str = "no"  # accelerate mixed precision: "no", "fp16" or "bf16"
    num_workers: int = 0  # DataLoader workers for reading the chips once
    seed: int = 0  # seeds initialisation, batch order and augmentations (the same for every row)
    resume: bool = False  # continue an unfinished table with these settings; a finished one is returned
    restart: bool = False  # move an existing table in output_dir aside (never deleted) and start over

    def __post_init__(self) -> None:
        if self.sample is None:
            raise ValueError("sample must name the SAMPLE folder (--sample DIR)")
        if not Path(self.sample).is_dir():
            raise FileNotFoundError(f"sample: {self.sample!r} is not a folder")
        unknown = [r for r in self.rows if r != NO_AUGMENTATION and r not in PRESETS]
        if unknown or not self.rows:
            raise ValueError(
                f"rows must be non-empty names from {[NO_AUGMENTATION, *PRESETS]}, got {list(self.rows)}"
            )
        if len(set(self.rows)) != len(self.rows):
            raise ValueError(f"rows must be distinct (one classifier folder each), got {list(self.rows)}")
        check_minimum(self, "image_size", "epochs", "train_batch_size", minimum=1)
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")
        if self.resume and self.restart:
            raise ValueError("resume and restart: choose one (continue this table, or move it aside)")


def load_chips(
    records: list[ChipRecord], class_names: list[str], image_size: int, num_workers: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Magnitudes and labels of the records, read once. Shape: (N, 1, S, S) and (N,)."""
    dataset = ChipDataset(records, size=image_size, return_magnitude=True, class_names=class_names)
    batches = list(DataLoader(dataset, batch_size=256, num_workers=num_workers))
    return torch.cat([b["magnitude"] for b in batches]), torch.cat([b["label"] for b in batches]).long()


def _format_markdown(rows: dict[str, dict[str, float]], config: SynthToRealConfig, pairs: int) -> str:
    """Table II as Markdown: real-chip accuracy per augmentation row."""
    lines = [
        f"Table II on `{config.sample}` ({config.image_format}, {pairs} synthetic/real pairs): "
        f"train on synthetic, test on real, {config.epochs} epochs, {config.image_size} px.",
        "",
        "| augmentation | real accuracy % |",
        "| --- | ---: |",
        *[f"| {row} | {metrics['real_accuracy']:.1f} |" for row, metrics in rows.items()],
    ]
    return "\n".join(lines) + "\n"


def run_synth_to_real(config: SynthToRealConfig) -> Path:
    """Build Table II in ``config.output_dir``; returns the folder (a finished one, with ``resume``, at once).

    Raises:
        ValueError: Before any work, from :func:`~sar_zero123.data.load_sample` for a folder without
            matching pairs, or from :func:`~sar_zero123.runs.folder.open_run_folder` for a folder
            holding other work (each difference named; nothing on disk is changed).
        FileNotFoundError: Before any work, if ``sample`` lacks the folders of ``image_format``.
    """
    timer = StageTimer()
    # 1. SAMPLE pairs listed (train on the synthetic chips, test on their measured twins), then the run-folder
    # rule, before any work; the SAMPLE folder is identified by its file names and sizes
    pairs = load_sample(config.sample, image_format=config.image_format)
    class_names = sorted({pair.real.target_class for pair in pairs})
    folder = open_stage_folder(
        config.output_dir, "synth_to_real", config, data={"sample": data_identity(config.sample)},
        resume=config.resume, restart=config.restart, may_differ=SYNTH_TO_REAL_MAY_DIFFER,
        resume_hint="--resume",
    )  # fmt: skip
    if folder.finished:
        logger.info("%s already holds this table", folder.path)
        return folder.path
    output_dir = folder.path

    # 2. the chips, read once
    with withdrawn_if_setup_fails(folder):
        synth = load_chips([pair.synth for pair in pairs], class_names, config.image_size, config.num_workers)
        real = load_chips([pair.real for pair in pairs], class_names, config.image_size, config.num_workers)
    save_config(config, output_dir)
    scaling = DecibelScaling.for_unit_magnitude()

    # 3. one classifier per augmentation row; a row saved by an interrupted session is kept
    rows = {}
    for row in config.rows:
        classifier_dir = output_dir / row / "classifier"
        if (classifier_dir / EVALUATOR_CONFIG_NAME).is_file():
            rows[row] = load_evaluator(classifier_dir, class_names).metrics
        else:
            model, rows[row] = train_row(row, synth, real, class_names, scaling, config)
            model.metrics = rows[row]
            model.save_pretrained(classifier_dir)
        logger.info("%s: real accuracy %.2f%%", row, rows[row]["real_accuracy"])

    # 4. tables, then the record
    result = {"rows": rows, "pairs": len(pairs), "class_names": class_names, "sample": str(config.sample)}
    write_json_atomic(result, output_dir / "table2.json")
    (output_dir / "table2.md").write_text(_format_markdown(rows, config, len(pairs)))
    finish_run(folder, ["table2.json", "table2.md"], seconds=timer.seconds, results={"rows": list(rows)})
    return output_dir
