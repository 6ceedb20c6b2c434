"""Pretrain the multi-view SAR prior on procedural simulated vehicles (the package's bundled prior).

    python train/pretrain_prior.py --output_dir runs/prior
    accelerate launch train/pretrain_prior.py --output_dir runs/prior --mixed_precision bf16   # GPUs

Stages, each resumable (a re-run of the same command continues where it stopped):

1. the corpus (`sar_zero123.sim.corpus.write_prior_corpus`): `num_vehicles` procedural vehicles, each at
   `views_per_vehicle` random azimuths and depressions in `depression_range_deg`; the named simulator
   classes are never in it (they are the prior's unseen test vehicles);
2. a VAE sized for the chip (`train_vae.py`) on the corpus;
3. the UNet with its pose path (`finetune_pfm.py`, lambda = 0): pairs of two views of one vehicle across
   depressions, the pose carrying the input's absolute depression (Stable Zero123's fourth slot) and the
   SAR-sized estimated-azimuth path, v prediction with Min-SNR weighting, latents cached once.

The pipeline lands in `output_dir/base/pipeline`; it records the d_el and depression ranges it was
trained on, which it then enforces. A constant learning rate makes `--base_steps` extendable: a re-run
with more steps resumes from the last checkpoint. `docs/results/prior.md` gives the measured recipe.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

if not __package__:  # run as a file: Python put only train/ on sys.path (see train/__init__.py)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from accelerate import PartialState  # noqa: E402

from sar_zero123.config import check_minimum, parse_config, save_config, write_json_atomic  # noqa: E402
from sar_zero123.data import SCALING_FILE  # noqa: E402
from sar_zero123.models import SAR_ZERO123_SIZES  # noqa: E402
from sar_zero123.sim.corpus import VALIDATION_CLASS, write_prior_corpus  # noqa: E402
from train import finetune_pfm, train_vae  # noqa: E402
from train.quickstart import script_argv  # noqa: E402

logger = logging.getLogger(__name__)


@dataclass
class PriorConfig:
    """Corpus, VAE and UNet of the multi-view prior (defaults: the bundled prior's recipe)."""

    output_dir: str = "runs/prior"  # run folder: corpus/, vae/, base/ (its pipeline/ is the prior)
    corpus: str | None = None  # an existing corpus folder to train on; None writes output_dir/corpus
    num_vehicles: int = 2000  # procedural vehicles in the corpus (validation ones included)
    views_per_vehicle: int = 24  # chips per vehicle
    num_validation_vehicles: int = 32  # vehicles held out as class PROCVAL (validation pairs)
    depression_range_deg: list[float] = field(default_factory=lambda: [10.0, 60.0])  # corpus depressions
    mstar_fraction: float = 0.25  # share of corpus views at MSTAR's 15/17 deg
    image_size: int = 64  # chip side in pixels
    corpus_workers: int = 2  # processes rendering the corpus
    model_size: str = "micro"  # build_sar_zero123 size of the UNet
    vae_widths: list[int] = field(default_factory=lambda: [16, 32, 64])  # VAE block widths (16x16 latents)
    vae_norm_groups: int = 8  # GroupNorm groups of the VAE
    vae_steps: int = 3000  # VAE optimisation steps
    vae_batch_size: int = 8  # chips per VAE step
    base_steps: int = 25000  # UNet optimisation steps (constant LR: a re-run may extend them)
    train_batch_size: int = 16  # pairs per UNet step
    learning_rate: float = 1e-3  # AdamW learning rate of the UNet (trained from scratch)
    input_depression: bool = True  # the pose's 4th entry is the input's absolute depression
    prediction_type: str = "v_prediction"  # the UNet's training target
    snr_gamma: float | None = 5.0  # Min-SNR-gamma weighting of L_simple
    checkpointing_steps: int = 1000  # resumable checkpoint interval of the VAE and UNet stages
    mixed_precision: str = "no"  # accelerate mixed precision of both training stages ("bf16" on GPUs)
    seed: int = 0  # seed of the corpus and of every stage

    def __post_init__(self) -> None:
        check_minimum(self, "num_vehicles", "views_per_vehicle", minimum=2)
        check_minimum(
            self,
            "num_validation_vehicles",
            "corpus_workers",
            "vae_steps",
            "vae_batch_size",
            "base_steps",
            "train_batch_size",
            "checkpointing_steps",
            minimum=1,
        )
        check_minimum(self, "learning_rate", minimum=0, strict=True)
        depressions = self.depression_range_deg
        if len(depressions) != 2 or not 0 < depressions[0] < depressions[1] < 90:
            raise ValueError(
                f"depression_range_deg must be two values 0 < low < high < 90, got {depressions}"
            )
        if self.model_size not in SAR_ZERO123_SIZES:
            raise ValueError(
                f"model_size must be one of {sorted(SAR_ZERO123_SIZES)}, got {self.model_size!r}"
            )
        if self.corpus is not None and not (Path(self.corpus) / "index.csv").is_file():
            raise FileNotFoundError(f"corpus: expected a corpus folder with index.csv, got {self.corpus}")


def stage(name: str, done: Path, timings: dict[str, float], function, *args) -> None:
    """Run one stage unless its last output exists; record its wall time only when it ran."""
    if done.exists():
        logger.info("stage %s: done (%s)", name, done)
        return
    logger.info("stage %s", name)
    begin = time.perf_counter()
    function(*args)
    timings[name] = time.perf_counter() - begin
    logger.info("stage %s took %.1f s", name, timings[name])


def main(argv: Sequence[str] | None = None) -> Path:
    """Run (or resume) the three stages; returns the prior's pipeline folder."""
    config = parse_config(PriorConfig, argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    # under `accelerate launch` every process runs this function: one writes the corpus and the records, the
    # training stages share the work through their own Accelerator
    state = PartialState()
    out = Path(config.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    if state.is_main_process:
        save_config(config, out)
    timings_path = out / "timings.json"
    timings: dict[str, float] = json.loads(timings_path.read_text()) if timings_path.is_file() else {}
    protocol = f"ood-{VALIDATION_CLASS}"
    common = {
        "seed": config.seed,
        "image_size": config.image_size,
        "protocol": protocol,
        "mixed_precision": config.mixed_precision,
        "checkpointing_steps": config.checkpointing_steps,
        "checkpoints_total_limit": 2,
        "resume_from_checkpoint": "latest",
        "report_to": "none",
    }

    # 1. corpus (its index is written last)
    corpus = Path(config.corpus) if config.corpus is not None else out / "corpus"
    with state.main_process_first():  # the others then find its index and skip the stage
        stage(
            "corpus",
            corpus / "index.csv",
            timings,
            lambda: write_prior_corpus(
                corpus,
                num_vehicles=config.num_vehicles,
                views_per_vehicle=config.views_per_vehicle,
                num_validation_vehicles=config.num_validation_vehicles,
                depression_range_deg=tuple(config.depression_range_deg),
                mstar_fraction=config.mstar_fraction,
                size=config.image_size,
                seed=config.seed,
                num_workers=config.corpus_workers,
            ),
        )
    common["data"] = str(corpus)

    # 2. VAE (decibel_scaling.json is the last file train_vae writes)
    vae_shape = SAR_ZERO123_SIZES[config.model_size]["vae"]
    vae_args = {
        **common,
        "output_dir": str(out / "vae"),
        "block_out_channels": config.vae_widths,
        "layers_per_block": vae_shape["layers_per_block"],
        "latent_channels": vae_shape["latent_channels"],
        "norm_num_groups": config.vae_norm_groups,
        "train_batch_size": config.vae_batch_size,
        "max_train_steps": config.vae_steps,
        "learning_rate": 1e-3,
        "num_eval_images": 64,
    }
    vae_dir = out / "vae" / "vae"
    stage("vae", vae_dir / SCALING_FILE, timings, train_vae.main, script_argv(train_vae, vae_args))

    # 3. UNet and pose path across depressions
    base_args = {
        **common,
        "output_dir": str(out / "base"),
        "size": config.model_size,
        "estimate_input_azimuth": True,
        "input_depression": config.input_depression,
        "same_depression": False,
        "prediction_type": config.prediction_type,
        "pfm_weight": 0.0,
        "vae": str(vae_dir),
        "train_batch_size": config.train_batch_size,
        "max_train_steps": config.base_steps,
        "learning_rate": config.learning_rate,
        "use_ema": False,
        "validation_steps": 0,
    }
    if config.snr_gamma is not None:
        base_args["snr_gamma"] = config.snr_gamma
    pipeline = out / "base" / "pipeline"
    done = pipeline / "model_index.json"
    base_config = out / "base" / "config.json"
    if done.exists() and json.loads(base_config.read_text())["max_train_steps"] < config.base_steps:
        done = out / "base" / f"extended_to_{config.base_steps}"  # more steps asked: resume and re-export
    stage("base", done, timings, finetune_pfm.main, script_argv(finetune_pfm, base_args))
    if state.is_main_process:
        write_json_atomic(timings, timings_path)
        write_json_atomic(dataclasses.asdict(config), out / "prior_config.json")
    print(f"prior pipeline: {pipeline}")
    return pipeline


if __name__ == "__main__":
    main()
