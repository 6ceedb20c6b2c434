"""How L_simple and PFM pull on the trained weights: gradient norms, their angle and what clipping leaves.

For each model (a pipeline folder: the prior a fine-tune starts from, and fine-tunes of it) and each band
of timesteps, batches of training pairs go through the training step's own ``compute_losses`` at timesteps
drawn uniformly in the band (CFG dropout off, PFM on every sample, PFM's projection and encoder as the
fine-tune uses them). Per batch it records L_simple (Min-SNR weighted as in training) and PFM, the norms
of their gradients over the trained parameters (UNet and pose projection), the cosine between the two
gradients, and ``lambda * ||grad PFM|| / ||grad L_simple||`` (the trained parameters include a model's azimuth
estimator; its own loss is left out of both), and the same ratio and cosine on the pose projection alone
(``pose_*``), which trains at ``pose_lr_multiplier`` times the UNet's learning rate. A last row, ``train``,
draws timesteps as training does and applies the run's PFM fraction, so it also reports what gradient
clipping at ``--max_grad_norm`` leaves of L_simple's gradient: ``||grad L_simple|| * min(1, c / ||grad L||)``.

Run on the quickstart's folder (its data, SimCLR encoder and fine-tunes), JSON to ``--out``:

    python benchmarks/pfm_balance.py --data RUN/data --protocol ood-TANK --encoder RUN/simclr/encoder \\
        --model prior=sar-zero123/sim-prior --model lambda0=RUN/finetune_lambda0/pipeline \\
        --model lambda4=RUN/finetune_lambda4/pipeline --out pfm_balance.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from diffusers import DDPMScheduler

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sar_zero123.config import write_json_atomic  # noqa: E402
from sar_zero123.data.view_pairs import train_validation_pairs  # noqa: E402
from sar_zero123.model.build import load_sar_zero123  # noqa: E402
from sar_zero123.training.finetuning import finetuning_modules, training_image_size  # noqa: E402
from sar_zero123.training.latent_cache import CachedViewPairs, ChipLatentCache, load_chip_images  # noqa: E402
from sar_zero123.training.losses import DEFAULT_PFM_MIN_SNR, LossSettings  # noqa: E402
from sar_zero123.training.pfm import load_pfm_encoder  # noqa: E402
from sar_zero123.training.step import compute_losses, micro_batch_generator  # noqa: E402


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", required=True, metavar="LABEL=PATH",
                        help="a pipeline folder or bundled name, labelled (repeatable)")
    parser.add_argument("--data", default=None, help="dataset folder (default: the built-in simulator)")
    parser.add_argument("--protocol", default="ood-TANK")
    parser.add_argument("--encoder", required=True, help="the frozen SimCLR encoder folder PFM matches")
    parser.add_argument("--pfm_projection_dim", type=int, default=10, help="0: the 512-d features")
    parser.add_argument("--pfm_weight", type=float, default=4.0, help="lambda of Eq. (21)")
    parser.add_argument("--pfm_fraction", type=float, default=0.25, help="the run's fraction (train row)")
    parser.add_argument("--pfm_min_snr", type=float, default=DEFAULT_PFM_MIN_SNR,
                        help="the run's (train row)")
    parser.add_argument("--snr_gamma", type=float, default=5.0, help="Min-SNR gamma of L_simple; 0: none")
    parser.add_argument("--max_grad_norm", type=float, default=1.0)
    parser.add_argument("--bands", type=int, nargs="+", default=[0, 100, 300, 500, 700, 900, 1000])
    parser.add_argument("--batches", type=int, default=4, help="batches per band")
    parser.add_argument("--batch_size", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    for spec in args.model:
        if "=" not in spec:
            parser.error(f"--model: expected LABEL=PATH, got {spec!r}")
    if sorted(args.bands) != args.bands or len(args.bands) < 2:
        parser.error(f"--bands: expected increasing timestep edges, got {args.bands}")
    return args


def _norm(grads) -> float:
    return math.sqrt(sum(float(g.double().pow(2).sum()) for g in grads if g is not None))


def _dot(a, b) -> float:
    return sum(float((x.double() * y.double()).sum()) for x, y in zip(a, b))


def _grads(loss: torch.Tensor, params, retain: bool):
    grads = torch.autograd.grad(loss, params, retain_graph=retain, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)]


def measure_model(label: str, path: str, args: argparse.Namespace, work: Path) -> list[dict]:
    torch.manual_seed(args.seed)
    pipe = load_sar_zero123(path)
    image_size = training_image_size(pipe)
    vae, embedder, unet, pose_projection = finetuning_modules(pipe, device="cpu", weight_dtype=torch.float32)
    projection = args.pfm_projection_dim or None
    encoder = load_pfm_encoder(args.encoder, image_size=image_size, projection_dim=projection, seed=args.seed)
    pairs, _, _ = train_validation_pairs(args.data, args.protocol, work, image_size=image_size,
                                         seed=args.seed)  # fmt: skip
    cache = ChipLatentCache.encode(load_chip_images(pairs), vae, embedder.image_encoder)
    dataset = CachedViewPairs(pairs, cache)
    loader = torch.utils.data.DataLoader(dataset, args.batch_size, shuffle=True, drop_last=True,
                                         generator=torch.Generator().manual_seed(args.seed))  # fmt: skip
    trained = [m for m in (unet, pose_projection, pipe.azimuth_estimator) if m is not None]
    params = [p for module in trained for p in module.parameters() if p.requires_grad]
    n_pose = sum(1 for p in pose_projection.parameters() if p.requires_grad)
    first_pose = sum(1 for p in unet.parameters() if p.requires_grad)
    pose = slice(first_pose, first_pose + n_pose)  # the pose projection's gradients in `params` order
    gamma = args.snr_gamma or None
    common = {"unet": unet, "pose_projection": pose_projection, "vae": vae, "image_encoder": embedder,
              "encoder": encoder, "noise_scheduler": DDPMScheduler.from_config(pipe.scheduler.config),
              "azimuth_estimator": pipe.azimuth_estimator}
    probe = LossSettings(pfm_weight=1.0, pfm_min_snr=0.0, pfm_fraction=1.0, snr_gamma=gamma)
    train = LossSettings(pfm_weight=args.pfm_weight, pfm_min_snr=args.pfm_min_snr,
                         pfm_fraction=args.pfm_fraction, snr_gamma=gamma)  # fmt: skip
    batches = (batch for _ in iter(int, 1) for batch in loader)  # epochs without end
    rows = []
    bands = list(zip(args.bands[:-1], args.bands[1:])) + [("train", None)]
    for band_index, (low, high) in enumerate(bands):
        records = []
        for k in range(args.batches):
            batch = next(batches)
            generator = micro_batch_generator(args.seed, 1000 * band_index + k, 0)
            if low == "train":
                losses = compute_losses(batch, generator=generator, loss_settings=train, apply_dropout=True,
                                        **common)  # fmt: skip
                g_s = _grads(losses.denoising.mean(), params, retain=True)
                g_all = _grads(losses.loss.mean(), params, retain=False)
                total = _norm(g_all)
                simple = _norm(g_s)
                records.append({
                    "pose_simple": _norm(g_s[pose]), "pose_total": _norm(g_all[pose]),
                    "l_simple": float(losses.denoising.detach().mean()),
                    "pfm": float(losses.pfm.detach().mean()), "grad_total": total, "grad_simple": simple,
                    "cosine": _dot(g_s, g_all) / max(simple * total, 1e-30),
                    "simple_after_clip": simple * min(1.0, args.max_grad_norm / max(total, 1e-30)),
                })  # fmt: skip
                continue
            t = torch.randint(low, high, (args.batch_size,), generator=torch.Generator().manual_seed(k))
            losses = compute_losses(batch, generator=generator, loss_settings=probe, apply_dropout=False,
                                    timesteps=t, **common)  # fmt: skip
            g_s = _grads(losses.denoising.mean(), params, retain=True)
            g_p = _grads(losses.pfm.mean(), params, retain=False)
            simple, pfm = _norm(g_s), _norm(g_p)
            pose_simple, pose_pfm = _norm(g_s[pose]), _norm(g_p[pose])
            records.append({
                "pose_ratio": args.pfm_weight * pose_pfm / max(pose_simple, 1e-30),
                "pose_cosine": _dot(g_s[pose], g_p[pose]) / max(pose_simple * pose_pfm, 1e-30),
                "l_simple": float(losses.denoising.detach().mean()),
                "pfm": float(losses.pfm.detach().mean()), "grad_simple": simple, "grad_pfm": pfm,
                "cosine": _dot(g_s, g_p) / max(simple * pfm, 1e-30),
                "ratio": args.pfm_weight * pfm / max(simple, 1e-30),
            })  # fmt: skip
        summary = {key: {"mean": float(np.mean([r[key] for r in records])),
                         "se": float(np.std([r[key] for r in records], ddof=1) / math.sqrt(len(records)))
                         if len(records) > 1 else 0.0}
                   for key in records[0]}  # fmt: skip
        band = "train" if low == "train" else f"{low}-{high}"
        rows.append({"model": label, "band": band, "n_batches": len(records), **summary})
        means = {key: round(value["mean"], 5) for key, value in summary.items()}
        print(json.dumps({"model": label, "band": band, **means}), flush=True)
    return rows


def main(argv=None) -> dict:
    args = parse_args(argv)
    start = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for spec in args.model:
            label, path = spec.split("=", 1)
            rows.extend(measure_model(label, path, args, Path(work)))
    result = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
              "torch": torch.__version__, "seconds": time.perf_counter() - start, "rows": rows}  # fmt: skip
    if args.out is not None:
        write_json_atomic(result, args.out)
    return result


if __name__ == "__main__":
    main()
