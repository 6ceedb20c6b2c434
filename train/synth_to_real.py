"""Table II: synthetic-to-real transfer on SAMPLE with co-domain augmentations.

    python train/synth_to_real.py --sample /path/to/SAMPLE --output_dir runs/table2

For every augmentation row a ResNet-18 classifier (`sar_zero123.evaluators.SARClassifier`, trained from
scratch) learns the classes from SAMPLE's *synthetic* chips, augmented on the training device with the
row's preset (`sar_zero123.augment.augment_batch`; row `none` = no augmentation), and is tested on the
*measured* (real) twins. Writes `table2.json`, `table2.md` and one `<row>/classifier` folder per row.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader
from tqdm.auto import tqdm

from sar_zero123.augment import PRESETS, augment_batch
from sar_zero123.config import check_minimum, parse_config, save_config, write_json_atomic
from sar_zero123.data import ChipDataset, ChipRecord, DecibelScaling, load_sample
from sar_zero123.encoder import SAREncoderConfig
from sar_zero123.evaluators import SARClassifier
from sar_zero123.runs import start_run

logger = logging.getLogger(__name__)

NO_AUGMENTATION = "none"


@dataclass
class SynthToRealConfig:
    """Table II: classifiers trained on SAMPLE synthetic chips with each augmentation, tested on real."""

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
    weight_decay: float = 5e-4  # AdamW weight decay
    mixed_precision: str = "no"  # accelerate mixed precision: "no", "fp16" or "bf16"
    num_workers: int = 0  # DataLoader workers for reading the chips once
    seed: int = 0  # seeds initialisation, batch order and augmentations (the same for every row)

    def __post_init__(self) -> None:
        if self.sample is None:
            raise ValueError("sample must name the SAMPLE folder (--sample DIR)")
        unknown = [r for r in self.rows if r != NO_AUGMENTATION and r not in PRESETS]
        if unknown or not self.rows:
            raise ValueError(
                f"rows must be non-empty names from {[NO_AUGMENTATION, *PRESETS]}, got {list(self.rows)}"
            )
        check_minimum(self, "image_size", "epochs", "train_batch_size", minimum=1)
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        check_minimum(self, "weight_decay", minimum=0)
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be 'no', 'fp16' or 'bf16', got {self.mixed_precision!r}")


def load_chips(records: list[ChipRecord], class_names: list[str], config: SynthToRealConfig):
    """Magnitudes (N, 1, S, S) and labels (N,) of the records, read once."""
    dataset = ChipDataset(records, size=config.image_size, return_magnitude=True, class_names=class_names)
    loader = DataLoader(dataset, batch_size=256, num_workers=config.num_workers)
    batches = list(loader)
    return torch.cat([b["magnitude"] for b in batches]), torch.cat([b["label"] for b in batches]).long()


def train_row(
    row: str,
    synth: tuple[torch.Tensor, torch.Tensor],
    real: tuple[torch.Tensor, torch.Tensor],
    class_names: list[str],
    scaling: DecibelScaling,
    config: SynthToRealConfig,
) -> tuple[SARClassifier, dict[str, float]]:
    """Trains one classifier on augmented synthetic chips; returns it and its real-chip accuracy."""
    accelerator = start_run(None, seed=config.seed, mixed_precision=config.mixed_precision)
    device = accelerator.device
    encoder_config = SAREncoderConfig(
        image_size=config.image_size,
        cifar_stem=config.cifar_stem,
        hidden_sizes=config.hidden_sizes,
        embedding_size=config.embedding_size,
    )
    model = SARClassifier(encoder_config, class_names, scaling)
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay
    )
    magnitude, labels = synth[0].to(device), synth[1].to(device)
    steps_per_epoch = -(-len(labels) // config.train_batch_size)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.epochs * steps_per_epoch)
    model, optimizer = accelerator.prepare(model, optimizer)
    order_generator = torch.Generator().manual_seed(config.seed)
    aug_generator = torch.Generator(device=device).manual_seed(config.seed)
    model.train()
    for epoch in tqdm(range(config.epochs), desc=row, disable=not accelerator.is_local_main_process):
        order = torch.randperm(len(labels), generator=order_generator).to(device)
        for start in range(0, len(labels), config.train_batch_size):
            index = order[start : start + config.train_batch_size]
            if row == NO_AUGMENTATION:
                images = scaling.normalize(magnitude[index])
            else:
                images = augment_batch(magnitude[index], row, scaling, generator=aug_generator)
            loss = F.cross_entropy(model(images), labels[index])
            optimizer.zero_grad(set_to_none=True)
            accelerator.backward(loss)
            optimizer.step()
            scheduler.step()
        logger.info("%s epoch %d: last loss %.4f", row, epoch + 1, loss.item())
    model = accelerator.unwrap_model(model).eval()
    predictions = []
    with torch.no_grad():
        for chunk in real[0].split(256):
            predictions.append(model(scaling.normalize(chunk.to(device))).argmax(dim=1).cpu())
    accuracy = 100.0 * (torch.cat(predictions) == real[1]).double().mean().item()
    return model, {"real_accuracy": accuracy, "final_train_loss": loss.item()}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Builds Table II; returns the dict written to `table2.json`."""
    config = parse_config(SynthToRealConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    output_dir = Path(config.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, output_dir)

    # 1. SAMPLE pairs: train on the synthetic chips, test on their measured twins
    pairs = load_sample(config.sample, image_format=config.image_format)
    class_names = sorted({pair.real.target_class for pair in pairs})
    synth = load_chips([pair.synth for pair in pairs], class_names, config)
    real = load_chips([pair.real for pair in pairs], class_names, config)
    scaling = DecibelScaling.for_unit_magnitude()

    # 2. one classifier per augmentation row
    rows = {}
    for row in config.rows:
        model, metrics = train_row(row, synth, real, class_names, scaling, config)
        model.metrics = metrics
        model.save_pretrained(output_dir / row / "classifier")
        rows[row] = metrics
        logger.info("%s: real accuracy %.2f%%", row, metrics["real_accuracy"])

    # 3. tables
    result = {"rows": rows, "pairs": len(pairs), "class_names": class_names, "sample": str(config.sample)}
    write_json_atomic(result, output_dir / "table2.json")
    lines = [
        f"Table II on `{config.sample}` ({config.image_format}, {len(pairs)} synthetic/real pairs): "
        f"train on synthetic, test on real, {config.epochs} epochs, {config.image_size} px.",
        "",
        "| augmentation | real accuracy % |",
        "| --- | ---: |",
        *[f"| {row} | {metrics['real_accuracy']:.1f} |" for row, metrics in rows.items()],
    ]
    (output_dir / "table2.md").write_text("\n".join(lines) + "\n")
    return result


if __name__ == "__main__":
    main()
