"""Cost and behaviour of Projected Feature Matching (Eq. 20-21).

Two measurements, JSON on stdout (and in ``--out``):

``--mode step``: one fine-tuning step (``finetune_pfm.compute_losses`` + backward + AdamW) of a named
model size on one fixed batch, for lambda = 0 and for lambda = 4 with each way of making PFM cheaper
(centre crop, fraction of the batch, bf16 frozen decoder/encoder, channels_last, decoder gradient
checkpointing). Times: median over ``--steps`` rounds (after ``--warmup``) in which every variant runs
one step, round-robin in one process, so that a shared machine's load affects all variants alike.
Memory: each variant again alone in its own process: the kernel's peak-RSS mark is reset after the
models are built, and the peak over two steps minus the resident memory before them is the training
footprint (activations, gradients, AdamW state, allocator caches). Also reports what the crop costs:
cosine similarity between the
PFM gradient w.r.t. the network output with and without the crop, and how far a decoded latent window
is from the centre of the full decode.

``--mode timesteps``: why PFM needs an SNR floor. On real chips encoded by a trained VAE, for each
schedule and timestep: the amplification 1/sqrt(SNR), the x0-estimate error for a network whose epsilon
prediction has a fixed RMS error, the PFM value of that estimate against the chance level (PFM between
two different real chips), and the norm of the PFM gradient w.r.t. the network output.

    python benchmarks/bench_pfm.py --mode step --size small --batch_size 8 --out step.json
    python benchmarks/bench_pfm.py --mode timesteps --vae runs/vae/vae --data /path/to/mstar --out t.json
"""

from __future__ import annotations

import argparse
import copy
import json
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sar_zero123.encoder import SAREncoder, SAREncoderConfig  # noqa: E402
from sar_zero123.model.conditioning import downsampling_factor, encode_condition_latents  # noqa: E402
from sar_zero123.training.losses import LossSettings, estimate_x0, signal_to_noise_ratio  # noqa: E402
from sar_zero123.training.pfm import pfm_loss  # noqa: E402
from sar_zero123.training.step import ImageEmbedder, compute_losses  # noqa: E402

#: lambda = 4 variants: (overrides of the fine-tuning config, frozen-module options).
VARIANTS: dict[str, dict] = {
    "lambda0": {"pfm_weight": 0.0},
    "pfm": {},
    "pfm_crop_half": {"pfm_crop_size": "half"},
    "pfm_fraction_0.5": {"pfm_fraction": 0.5},
    "pfm_fraction_0.25": {"pfm_fraction": 0.25},
    "pfm_bf16": {"frozen_dtype": "bf16"},
    "pfm_channels_last": {"channels_last": True},
    "pfm_checkpoint_decoder": {"checkpoint_decoder": True},
    "pfm_crop_half_fraction_0.5": {"pfm_crop_size": "half", "pfm_fraction": 0.5},
    "pfm_bf16_fraction_0.25": {"frozen_dtype": "bf16", "pfm_fraction": 0.25},
    "pfm_encoder_imagenet_stem": {"encoder_stem": "imagenet"},
    "pfm_encoder_imagenet_stem_bf16": {"encoder_stem": "imagenet", "frozen_dtype": "bf16"},
}
SCHEDULES = {
    "scaled_linear": dict(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012),
    "linear": dict(beta_schedule="linear"),
    "squaredcos_cap_v2": dict(beta_schedule="squaredcos_cap_v2"),
    "zero_snr": dict(
        beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012, rescale_betas_zero_snr=True
    ),
}


def _status_mib(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0  # kB
    raise KeyError(field)


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) of this process; False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mib() -> float:
    """Peak resident memory since the last :func:`reset_peak_rss` (or since start), MiB."""
    try:
        return _status_mib("VmHWM")
    except (OSError, KeyError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def build_step_setup(size: str, batch_size: int, seed: int = 0):
    """Pipeline parts, a random ResNet-18 SAR encoder at the chip size and one fixed batch."""
    from sar_zero123.model.build import build_sar_zero123

    pipe = build_sar_zero123(size, seed=seed)
    image_size = pipe.default_image_size
    torch.manual_seed(seed)
    encoder = SAREncoder(SAREncoderConfig(image_size=image_size)).eval().requires_grad_(False)
    generator = torch.Generator().manual_seed(seed)
    batch = {
        "input": torch.rand(batch_size, 1, image_size, image_size, generator=generator),
        "target": torch.rand(batch_size, 1, image_size, image_size, generator=generator),
        "d_az_deg": torch.rand(batch_size, generator=generator) * 360 - 180,
        "d_el_deg": torch.zeros(batch_size),
    }
    return pipe, encoder, batch, image_size


def prepare_variant(name: str, pipe, encoder, image_size: int) -> dict:
    """The config and own copies of the frozen modules (dtype, memory format, checkpointing) of a variant."""
    options = dict(VARIANTS[name])
    frozen_dtype = torch.bfloat16 if options.pop("frozen_dtype", None) == "bf16" else torch.float32
    channels_last = options.pop("channels_last", False)
    checkpoint_decoder = options.pop("checkpoint_decoder", False)
    if (
        options.pop("encoder_stem", "cifar") == "imagenet"
    ):  # 7x7/2 + max-pool stem: 16x fewer stem-level FLOPs
        torch.manual_seed(0)
        encoder = (
            SAREncoder(SAREncoderConfig(image_size=image_size, cifar_stem=False)).eval().requires_grad_(False)
        )
    if options.get("pfm_crop_size") == "half":
        options["pfm_crop_size"] = image_size // 2
    loss_options = {
        "pfm_weight": 4.0,
        "pfm_min_snr": 0.0,
        "drop_image_prob": 0.0,
        "drop_both_prob": 0.0,
        "drop_latent_prob": 0.0,
        **options,
    }
    vae = copy.deepcopy(pipe.vae).to(frozen_dtype).eval().requires_grad_(False)
    variant_encoder = copy.deepcopy(encoder).to(frozen_dtype)
    if channels_last:
        vae.to(memory_format=torch.channels_last)
        variant_encoder.to(memory_format=torch.channels_last)
    if checkpoint_decoder:
        vae.enable_gradient_checkpointing()
    image_encoder = copy.deepcopy(pipe.image_encoder).to(frozen_dtype).eval().requires_grad_(False)
    return {
        "loss_settings": LossSettings(**loss_options),
        "vae": vae,
        "image_encoder": ImageEmbedder(image_encoder),
        "encoder": variant_encoder if loss_options["pfm_weight"] > 0 else None,
    }


def train_step(batch: dict, trainer: dict, prepared: dict, seed: int):
    """One compute_losses + backward + AdamW step; returns (seconds, losses)."""
    start = time.perf_counter()
    losses = compute_losses(
        batch,
        unet=trainer["unet"],
        pose_projection=trainer["projection"],
        noise_scheduler=trainer["noise_scheduler"],
        generator=torch.Generator().manual_seed(seed),
        **prepared,
    )
    losses.loss.mean().backward()
    trainer["optimizer"].step()
    trainer["optimizer"].zero_grad(set_to_none=True)
    return time.perf_counter() - start, losses


def build_trainer(pipe) -> dict:
    from diffusers import DDPMScheduler

    unet, projection = pipe.unet.train(), pipe.pose_projection.train()
    return {
        "unet": unet,
        "projection": projection,
        "optimizer": torch.optim.AdamW(list(unet.parameters()) + list(projection.parameters()), lr=1e-4),
        "noise_scheduler": DDPMScheduler.from_config(pipe.scheduler.config),
    }


def run_variant(name: str, size: str, batch_size: int, steps: int, warmup: int) -> dict:
    """Peak memory (and times) of one variant alone in this process."""
    pipe, encoder, batch, image_size = build_step_setup(size, batch_size)
    prepared = prepare_variant(name, pipe, encoder, image_size)
    trainer = build_trainer(pipe)
    rss_before = _status_mib("VmRSS")
    reset_ok = reset_peak_rss()
    times = [train_step(batch, trainer, prepared, seed)[0] for seed in range(warmup + steps)]
    return {
        "variant": name,
        "step_times_s": times[warmup:],
        "peak_rss_increase_mib": peak_rss_mib() - rss_before,
        "peak_reset": reset_ok,
    }


def interleaved_timing(names: list[str], size: str, batch_size: int, rounds: int, warmup: int) -> dict:
    """Median step time of every variant, measured round-robin in one process (rotating the order each
    round) so that the load of a shared machine drifts over all variants alike."""
    pipe, encoder, batch, image_size = build_step_setup(size, batch_size)
    prepared = {name: prepare_variant(name, pipe, encoder, image_size) for name in names}
    trainer = build_trainer(pipe)
    times: dict[str, list[float]] = {name: [] for name in names}
    samples: dict[str, int] = {}
    for round_index in range(warmup + rounds):
        shift = round_index % len(names)
        for name in names[shift:] + names[:shift]:
            seconds, losses = train_step(batch, trainer, prepared[name], seed=round_index)
            samples[name] = int(losses.pfm_mask.sum())
            if round_index >= warmup:
                times[name].append(seconds)
    return {name: {"step_times_s": times[name], "pfm_samples_per_step": samples[name]} for name in names}


def real_chips(data: str, image_size: int, num_images: int) -> torch.Tensor:
    """``num_images`` random test-split chips (extended protocol) as normalised dB, (N, 1, S, S)."""
    from sar_zero123.data import ChipDataset, load_index, split_records

    records = split_records(load_index(data), "extended")["test"]
    rng = np.random.default_rng(0)
    picked = [records[i] for i in rng.choice(len(records), size=num_images, replace=False)]
    return torch.stack([item["image"] for item in ChipDataset(picked, size=image_size)])


def crop_quality(size: str, batch_size: int, vae_path: str | None = None, data: str | None = None) -> dict:
    """What the centre crop costs: gradient agreement with the full-image PFM and the error of decoding a
    latent window instead of cropping the full decode (on real chips through a trained VAE if given)."""
    from diffusers import AutoencoderKL

    pipe, encoder, batch, image_size = build_step_setup(size, batch_size)
    vae = pipe.vae if vae_path is None else AutoencoderKL.from_pretrained(vae_path)
    vae = vae.eval().requires_grad_(False)
    factor = downsampling_factor(vae.config.block_out_channels)
    crop = image_size // 2
    generator = torch.Generator().manual_seed(1)
    if vae_path is not None and data is not None:
        batch["target"] = real_chips(data, image_size, batch_size)
        with torch.no_grad():
            clean = encode_condition_latents(vae, batch["target"]) * vae.config.scaling_factor
        latents = clean + 0.3 * torch.randn(clean.shape, generator=generator)  # an imperfect x0 estimate
    else:
        latents = torch.randn(batch_size, 4, image_size // factor, image_size // factor, generator=generator)
    grads = []
    for crop_size in (None, crop):
        x0_hat = latents.clone().requires_grad_(True)
        pfm_loss(x0_hat, batch["target"], vae, encoder, crop_size=crop_size).sum().backward()
        grads.append(x0_hat.grad.flatten(1))
    cosine = F.cosine_similarity(grads[0], grads[1], dim=1)
    with torch.no_grad():
        full = vae.decode(latents / vae.config.scaling_factor).sample
        lo = (image_size - crop) // 2
        window = latents[..., lo // factor : (lo + crop) // factor, lo // factor : (lo + crop) // factor]
        decoded_window = vae.decode(window / vae.config.scaling_factor).sample
        difference = (decoded_window - full[..., lo : lo + crop, lo : lo + crop]).abs()
    return {
        "crop_size": crop,
        "grad_cosine_crop_vs_full_mean": float(cosine.mean()),
        "window_decode_abs_diff_mean": float(difference.mean()),
        "window_decode_abs_diff_top_bottom_4px_mean": float(
            torch.cat([difference[..., :4, :].flatten(), difference[..., -4:, :].flatten()]).mean()
        ),
        "window_decode_abs_diff_interior_mean": float(difference[..., 4:-4, 4:-4].mean()),
        "vae": vae_path or "random init",
        "note": "random-init ResNet-18 encoder; decoded values in the VAE's [-1, 1] domain",
    }


def step_mode(args: argparse.Namespace) -> dict:
    names = args.variants or list(VARIANTS)
    timing = interleaved_timing(names, args.size, args.batch_size, args.steps, args.warmup)
    results = []
    for name in names:
        command = [sys.executable, __file__, "--mode", "variant", "--variant", name, "--size", args.size,
                   "--batch_size", str(args.batch_size), "--steps", "1", "--warmup", "1"]  # fmt: skip
        memory = json.loads(
            subprocess.run(command, check=True, capture_output=True, text=True).stdout.splitlines()[-1]
        )
        times = timing[name]["step_times_s"]
        results.append({
            "variant": name,
            "options": VARIANTS[name],
            "median_step_s": statistics.median(times),
            "step_times_s": times,
            "pfm_samples_per_step": timing[name]["pfm_samples_per_step"],
            "peak_rss_increase_mib": memory["peak_rss_increase_mib"],
        })  # fmt: skip
        print(f"{name}: {results[-1]['median_step_s']:.3f} s", file=sys.stderr)
    base = next(r for r in results if r["variant"] == "lambda0")
    for result in results:
        result["time_ratio_vs_lambda0"] = result["median_step_s"] / base["median_step_s"]
        result["memory_ratio_vs_lambda0"] = result["peak_rss_increase_mib"] / base["peak_rss_increase_mib"]
    return {
        "mode": "step",
        "size": args.size,
        "batch_size": args.batch_size,
        "rounds": args.steps,
        "variants": results,
        "crop_quality": crop_quality(args.size, args.batch_size, args.vae, args.data),
    }


def timesteps_mode(args: argparse.Namespace) -> dict:
    """x0-estimate error, PFM value and PFM gradient norm against t on real chips."""
    from diffusers import AutoencoderKL, DDPMScheduler

    vae = AutoencoderKL.from_pretrained(args.vae).eval().requires_grad_(False)
    factor = downsampling_factor(vae.config.block_out_channels)
    image_size = vae.config.sample_size
    images = real_chips(args.data, image_size, args.num_images)
    if args.encoder:
        encoder = SAREncoder.from_pretrained(args.encoder)
    else:
        torch.manual_seed(0)
        encoder = SAREncoder(SAREncoderConfig(image_size=image_size))
    encoder = encoder.eval().requires_grad_(False)
    with torch.no_grad():
        latents = encode_condition_latents(vae, images) * vae.config.scaling_factor
        chance = pfm_loss(latents.roll(1, dims=0), images, vae, encoder)  # a different chip's latent
        floor = pfm_loss(latents, images, vae, encoder)  # the VAE's own reconstruction error
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(latents.shape, generator=generator)
    error = torch.randn(latents.shape, generator=generator) * args.eps_error
    rows = []
    for schedule_name, kwargs in SCHEDULES.items():
        scheduler = DDPMScheduler(num_train_timesteps=1000, **kwargs)
        for t in args.timesteps:
            timesteps = torch.full((latents.shape[0],), t, dtype=torch.long)
            x_t = scheduler.add_noise(latents, noise, timesteps)
            eps_hat = (noise + error).requires_grad_(True)
            x0_hat = estimate_x0(x_t, eps_hat, timesteps, scheduler)
            pfm = pfm_loss(x0_hat, images, vae, encoder)
            pfm.sum().backward()
            snr = float(signal_to_noise_ratio(scheduler, timesteps[:1]))
            rows.append(
                {
                    "schedule": schedule_name,
                    "t": t,
                    "snr": snr,
                    "amplification": float("inf") if snr == 0 else 1 / np.sqrt(snr),
                    "x0_rmse": float((x0_hat - latents).pow(2).mean().sqrt()),
                    "pfm_mean": float(pfm.mean()),
                    "pfm_grad_norm_mean": float(eps_hat.grad.flatten(1).norm(dim=1).mean()),
                }
            )
    l_simple_grad = float((2 * error / error[0].numel()).flatten(1).norm(dim=1).mean())
    return {
        "mode": "timesteps",
        "num_images": args.num_images,
        "image_size": image_size,
        "latent_std": float(latents.std()),
        "eps_error_rms": args.eps_error,
        "pfm_chance_level_mean": float(chance.mean()),
        "pfm_vae_floor_mean": float(floor.mean()),
        "l_simple_grad_norm_mean": l_simple_grad,
        "encoder": args.encoder or "random init ResNet-18",
        "vae": str(args.vae),
        "latent_factor": factor,
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=["step", "variant", "timesteps"], default="step")
    parser.add_argument("--size", default="small")
    parser.add_argument("--batch_size", type=int, default=8)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--variant", choices=list(VARIANTS))
    parser.add_argument("--variants", nargs="*", choices=list(VARIANTS))
    parser.add_argument("--vae", help="AutoencoderKL folder (timesteps mode)")
    parser.add_argument("--encoder", help="SAREncoder folder (timesteps mode; default: random init)")
    parser.add_argument("--data", help="dataset folder with index.csv (timesteps mode)")
    parser.add_argument("--num_images", type=int, default=16)
    parser.add_argument("--eps_error", type=float, default=0.1, help="RMS error of the epsilon prediction")
    parser.add_argument("--timesteps", type=int, nargs="+", default=[0, 250, 500, 750, 900, 950, 990, 999])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    if args.mode == "variant":
        result = run_variant(args.variant, args.size, args.batch_size, args.steps, args.warmup)
        print(json.dumps(result))
        return result
    result = step_mode(args) if args.mode == "step" else timesteps_mode(args)
    result.update(
        device=f"CPU ({platform.processor() or platform.machine()}), torch threads {torch.get_num_threads()}",
        torch=torch.__version__,
        command=" ".join(sys.argv),
    )
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return result


if __name__ == "__main__":
    main()
