"""Which pose path lets a small UNet place the target view? Oracle ablation (results/history/learning.md, 3)

    python benchmarks/pose_paths.py --data runs/quickstart/data --vae runs/quickstart/vae/vae \\
        --evaluators runs/quickstart/evaluators --mode composed --steps 3000 --out pose_paths_composed.json

Trains the `micro` UNet (zero-1-to-3 layout, eps prediction, uniform timesteps, AdamW, batch 16) on
same-object pairs of the seen classes at one depression, with the pose given to its timestep embedding
(and as its one cross-attention token) in one of four ways, and every `--eval_every` steps samples 96
fixed pairs (DDIM, no guidance) and scores them with the evaluators (accuracy, azimuth error):

- ``absolute``: the target's class (one-hot) and azimuth; no input view. The ceiling of the UNet itself.
- ``source``: the input's condition latent, the input's true azimuth and ``d_az``: the UNet must add them.
- ``relative``: the input's condition latent and ``d_az`` only (zero-1-to-3's conditioning).
- ``composed``: the input's condition latent, ``d_az`` and the target's azimuth estimated by an
  :class:`~sar_zero123.model.orientation.AzimuthEstimator` and turned in closed form
  (:func:`~sar_zero123.model.orientation.turn_azimuth`), as ``--estimate_input_azimuth`` trains it.

Evaluation pairs are drawn from the training chips: this measures whether a pose path is learnable at
all, not generalisation (``train/evaluate.py`` does that). Writes the learning curve as JSON and an
``input | generated | target`` strip per evaluation next to it.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import PIL.Image
import torch
import torch.nn.functional as F
from diffusers import AutoencoderKL, DDIMScheduler, DDPMScheduler, UNet2DConditionModel

from sar_zero123.data import SCALING_FILE, DecibelScaling, load_chip, load_index, signed_to_unit
from sar_zero123.evaluation.evaluators import Evaluators, load_evaluators
from sar_zero123.evaluation.metrics import azimuth_error_deg
from sar_zero123.evaluation.scoring import resize_for_evaluator
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.model.conditioning import embed_pose, vae_input
from sar_zero123.model.orientation import (
    AzimuthEstimator,
    azimuth_estimation_loss,
    azimuth_vector,
    turn_azimuth,
)
from sar_zero123.model.zero123_checkpoints import ZERO123_SCHEDULER_CONFIG

MODES = ("absolute", "source", "relative", "composed")
EVAL_PAIRS = 96  # fixed evaluation pairs
BATCH_SIZE = 16  # training pairs per step


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--vae", required=True)
    parser.add_argument("--evaluators", required=True)
    parser.add_argument("--mode", choices=MODES, required=True)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--eval_every", type=int, default=500)
    parser.add_argument("--learning_rate", type=float, default=1e-3)
    parser.add_argument("--depression", type=float, default=17.0)
    parser.add_argument("--exclude_class", default="SPG", help="the unseen class of the ood protocol")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="JSON file; the strips go next to it")
    return parser.parse_args(argv)


@dataclass
class Chips:
    """The seen chips at one depression, their frozen VAE posteriors, and the evaluators that score views."""

    classes: list[str]  # sorted seen classes
    images: torch.Tensor  # (N, 1, H, W) normalised chips
    azimuth: torch.Tensor  # (N,) azimuth in degrees (float64)
    label: torch.Tensor  # (N,) index into `classes`
    by_class: list[torch.Tensor]  # per class, the indices of its chips
    mean: torch.Tensor  # (N, C, h, w) posterior means of the VAE
    std: torch.Tensor  # (N, C, h, w) posterior standard deviations
    scale: float  # the VAE's latent scaling factor
    vae: AutoencoderKL
    evaluators: Evaluators
    evaluator_label: torch.Tensor  # (len(classes),) evaluator class index of each class

    def draw_pairs(self, count: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` (source, target) index pairs of the same class."""
        source = torch.randint(0, len(self.label), (count,), generator=generator)
        partners = [self.by_class[int(self.label[i])] for i in source]
        target = torch.stack([p[torch.randint(0, len(p), (1,), generator=generator)[0]] for p in partners])
        return source, target


def load_chips(
    data: str, vae_path: str, evaluators_path: str, depression: float, exclude_class: str
) -> Chips:
    """Chips of every class but ``exclude_class`` at ``depression``, encoded by the frozen VAE."""
    vae = AutoencoderKL.from_pretrained(vae_path).eval()
    scaling = DecibelScaling.from_dict(json.loads((Path(vae_path) / SCALING_FILE).read_text()))
    records = [
        r
        for r in load_index(data)
        if r.target_class != exclude_class and abs(r.depression_deg - depression) < 0.1
    ]
    classes = sorted({r.target_class for r in records})
    size = SAR_ZERO123_SIZES["micro"]["image_size"]
    images = torch.stack(
        [torch.from_numpy(scaling.normalize(load_chip(r.path, size)))[None] for r in records]
    )
    azimuth = torch.tensor([r.azimuth_deg for r in records], dtype=torch.float64)
    label = torch.tensor([classes.index(r.target_class) for r in records])
    with torch.no_grad():
        posterior = vae.encode(vae_input(vae, images.float())).latent_dist
    evaluators = load_evaluators(evaluators_path)
    return Chips(
        classes=classes,
        images=images,
        azimuth=azimuth,
        label=label,
        by_class=[torch.nonzero(label == k).flatten() for k in range(len(classes))],
        mean=posterior.mean,
        std=posterior.std,
        scale=vae.config.scaling_factor,
        vae=vae,
        evaluators=evaluators,
        evaluator_label=torch.tensor([evaluators.class_names.index(c) for c in classes]),
    )


@dataclass
class PosePathModel:
    """The `micro` UNet, its pose token and (``composed``) the azimuth estimator, for one pose path."""

    mode: str  # one of MODES
    chips: Chips
    unet: UNet2DConditionModel
    token: torch.nn.Linear  # the pose condition as the one cross-attention token
    estimator: AzimuthEstimator | None  # `composed` only

    @property
    def modules(self) -> list[torch.nn.Module]:
        return [self.unet, self.token] + ([self.estimator] if self.estimator is not None else [])

    def predict(
        self, x_t: torch.Tensor, t: torch.Tensor, source: torch.Tensor, target: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns (noise prediction, estimator loss or 0)."""
        chips, azimuth = self.chips, self.chips.azimuth
        pose = embed_pose(azimuth[target] - azimuth[source], torch.zeros(len(source)))
        d_vector, extra = pose[:, 0, 1:3], torch.zeros(())
        if self.mode == "absolute":
            condition = torch.cat(
                [F.one_hot(chips.label[target], len(chips.classes)).float(), azimuth_vector(azimuth[target])],
                -1,
            )
        elif self.mode == "source":
            condition = torch.cat([azimuth_vector(azimuth[source]), d_vector], -1)
        elif self.mode == "relative":
            condition = torch.cat([d_vector, d_vector], -1)  # same width as `source`, no extra information
        else:
            estimate = self.estimator(chips.mean[source])
            extra = azimuth_estimation_loss(estimate, azimuth[source]).mean()
            condition = torch.cat([turn_azimuth(estimate, pose), d_vector, d_vector], -1)
        model_input = x_t if self.mode == "absolute" else torch.cat([x_t, chips.mean[source]], 1)
        output = self.unet(
            model_input, t, encoder_hidden_states=self.token(condition)[:, None], class_labels=condition
        )
        return output.sample, extra


def build_model(mode: str, chips: Chips, seed: int) -> PosePathModel:
    """The mode's model, initialised from ``seed``."""
    torch.manual_seed(seed)
    condition_dim = {"absolute": len(chips.classes) + 2, "source": 4, "relative": 4, "composed": 6}[mode]
    spec = SAR_ZERO123_SIZES["micro"]["unet"]
    latent_channels = chips.mean.shape[1]
    unet = UNet2DConditionModel(
        **spec,
        sample_size=chips.mean.shape[-1],
        in_channels=latent_channels * (1 if mode == "absolute" else 2),
        out_channels=latent_channels,
        class_embed_type="projection",
        projection_class_embeddings_input_dim=condition_dim,
    )
    token = torch.nn.Linear(condition_dim, spec["cross_attention_dim"])
    estimator = AzimuthEstimator(latent_channels) if mode == "composed" else None
    return PosePathModel(mode=mode, chips=chips, unet=unet, token=token, estimator=estimator)


@torch.no_grad()
def evaluate(
    model: PosePathModel, eval_source: torch.Tensor, eval_target: torch.Tensor, step: int, out: Path
) -> dict:
    """Samples the evaluation pairs (20 DDIM steps), saves a strip, scores them against copy and truth."""
    chips, evaluators = model.chips, model.chips.evaluators
    for module in model.modules:
        module.eval()
    ddim = DDIMScheduler(**ZERO123_SCHEDULER_CONFIG)
    ddim.set_timesteps(20)
    x = torch.randn((EVAL_PAIRS, *chips.mean.shape[1:]), generator=torch.Generator().manual_seed(7))
    for t in ddim.timesteps:
        x = ddim.step(model.predict(x, t.expand(EVAL_PAIRS), eval_source, eval_target)[0], t, x).prev_sample
    views = signed_to_unit(chips.vae.decode(x / chips.scale).sample).clamp(0, 1)
    for module in model.modules:
        module.train()

    def score(batch: torch.Tensor) -> tuple[float, float]:
        batch = resize_for_evaluator(batch, evaluators.image_size)
        correct = evaluators.classifier(batch).argmax(1) == chips.evaluator_label[chips.label[eval_target]]
        predicted = evaluators.regressor.predict_azimuth_deg(batch).double()
        return correct.float().mean().item() * 100, azimuth_error_deg(
            predicted, chips.azimuth[eval_target]
        ).mean().item()

    strip = torch.cat(
        [torch.cat(list(b[:8, 0]), 1) for b in (chips.images[eval_source], views, chips.images[eval_target])],
        0,
    )
    PIL.Image.fromarray((strip.numpy() * 255).round().astype(np.uint8)).save(
        out.with_name(f"{out.stem}_{step}.png")
    )
    (accuracy, error), (copy_accuracy, copy_error) = score(views), score(chips.images[eval_source].float())
    real_accuracy, real_error = score(chips.images[eval_target].float())
    return {
        "step": step,
        "accuracy": accuracy,
        "azimuth_error_deg": error,
        "input_copy": {"accuracy": copy_accuracy, "azimuth_error_deg": copy_error},
        "real_target": {"accuracy": real_accuracy, "azimuth_error_deg": real_error},
    }


def train(model: PosePathModel, args: argparse.Namespace, out: Path) -> list[dict]:
    """Trains ``model`` for ``args.steps`` steps; the learning curve, one row per evaluation."""
    chips = model.chips
    parameters = [p for m in model.modules for p in m.parameters()]
    optimizer = torch.optim.AdamW(parameters, lr=args.learning_rate, weight_decay=1e-2)
    scheduler_config = {k: v for k, v in ZERO123_SCHEDULER_CONFIG.items() if k != "set_alpha_to_one"}
    noise_scheduler = DDPMScheduler(**{k: v for k, v in scheduler_config.items() if k != "steps_offset"})
    eval_source, eval_target = chips.draw_pairs(EVAL_PAIRS, torch.Generator().manual_seed(123))
    generator = torch.Generator().manual_seed(args.seed)
    curve, start = [], time.perf_counter()
    for step in range(1, args.steps + 1):
        source, target = chips.draw_pairs(BATCH_SIZE, generator)
        epsilon = torch.randn(chips.mean[target].shape, generator=generator)
        x0 = (chips.mean[target] + chips.std[target] * epsilon) * chips.scale
        noise = torch.randn(x0.shape, generator=generator)
        t = torch.randint(0, noise_scheduler.config.num_train_timesteps, (BATCH_SIZE,), generator=generator)
        prediction, extra = model.predict(noise_scheduler.add_noise(x0, noise, t), t, source, target)
        loss = F.mse_loss(prediction, noise) + extra
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(parameters, 1.0)
        optimizer.step()
        if step % args.eval_every == 0 or step == args.steps:
            row = evaluate(model, eval_source, eval_target, step, out)
            row = {**row, "train_minutes": (time.perf_counter() - start) / 60}
            print(json.dumps(row), flush=True)
            curve.append(row)
    return curve


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # 1. chips, their frozen VAE posteriors, the evaluators
    chips = load_chips(args.data, args.vae, args.evaluators, args.depression, args.exclude_class)
    # 2. the model of the mode
    model = build_model(args.mode, chips, args.seed)
    # 3. train
    curve = train(model, args, out)
    result = {"mode": args.mode, "threads": torch.get_num_threads(), "args": vars(args), "curve": curve}
    out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
