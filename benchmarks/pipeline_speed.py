"""Sampling throughput and peak memory of SARZero123Pipeline against steps, scheduler and size.

Also compares, on identical weights and initial noise, with a plain fp32 loop that follows the original
zero-1-to-3 sampler (LDM DDIM, eta 0, 50 steps, guidance 3.0, conditional and unconditional inputs
concatenated into one UNet call), reporting the speed ratio and the largest output difference (the two
must agree: it checks the pipeline's scheduler/guidance wiring against the original equations).

    OMP_NUM_THREADS=1 python benchmarks/pipeline_speed.py --sizes tiny small --out bench.json
    python benchmarks/pipeline_speed.py --sizes zero123 --device cuda --dtype float16 --out gpu.json

Random weights (no downloads): speed does not depend on the weight values.
"""

from __future__ import annotations

import datetime
import math
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
from _common import synchronize

from sar_zero123.config import parse_config
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import embed_pose
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import SCHEDULERS, set_scheduler

DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


@dataclass
class BenchmarkConfig:
    """Throughput/memory benchmark of SARZero123Pipeline."""

    sizes: list[str] = field(default_factory=lambda: ["tiny", "small"])  # build_sar_zero123 sizes
    schedulers: list[str] = field(default_factory=lambda: ["ddim", "dpmsolver++", "euler"])  # samplers
    steps: list[int] = field(default_factory=lambda: [10, 25, 50])  # num_inference_steps values
    batch_size: int = 1  # input chips per call
    repeats: int = 3  # timed calls per setting (after one warm-up call); the median is reported
    guidance_scale: float = 3.0  # classifier-free guidance weight
    device: str = "cpu"  # torch device
    dtype: Literal["float32", "float16", "bfloat16"] = "float32"  # pipeline dtype (reference stays fp32)
    reference: bool = True  # also time the fp32 zero-1-to-3 reference loop (DDIM 50, guidance 3)
    out: str = "benchmarks/results/pipeline_speed.json"  # JSON output
    seed: int = 0  # weights and noise seed

    def __post_init__(self) -> None:
        unknown = [s for s in self.schedulers if s not in SCHEDULERS]
        if unknown:
            raise ValueError(f"schedulers: unknown {unknown}; choose from {sorted(SCHEDULERS)}")
        if not self.steps or min(self.steps) < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.batch_size < 1 or self.repeats < 1:
            raise ValueError(f"batch_size and repeats must be >= 1, got {self.batch_size}, {self.repeats}")


def _reset_peak_memory(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    elif os.path.exists("/proc/self/clear_refs"):
        # Linux: writing 5 resets the process's peak resident set size (VmHWM).
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")


def _peak_memory_mib(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    if os.path.exists("/proc/self/status"):
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _time_call(function, device: torch.device) -> float:
    synchronize(device)
    start = time.perf_counter()
    function()
    synchronize(device)
    return time.perf_counter() - start


def _time_calls(functions: Sequence, device: torch.device, repeats: int) -> list[tuple[float, float]]:
    """Median seconds per call and peak memory (MiB) of each function, after one warm-up call each.

    The functions are timed in turn within each repeat, so load from other processes on a shared
    machine affects them alike, and the median discards the worst disturbances.
    """
    for function in functions:
        function()
    seconds: list[list[float]] = [[] for _ in functions]
    peaks = [0.0 for _ in functions]
    for _ in range(repeats):
        for index, function in enumerate(functions):
            _reset_peak_memory(device)
            seconds[index].append(_time_call(function, device))
            peaks[index] = max(peaks[index], _peak_memory_mib(device))
    return [(statistics.median(times), peak) for times, peak in zip(seconds, peaks)]


@torch.no_grad()
def reference_zero123_sample(
    pipe: SARZero123Pipeline,
    images: torch.Tensor,
    d_az: float,
    d_el: float,
    noise: torch.Tensor,
    num_inference_steps: int = 50,
    guidance_scale: float = 3.0,
) -> torch.Tensor:
    """The original zero-1-to-3 sampler written out in fp32: LDM DDIM (eta 0) with batched CFG.

    Timesteps ``arange(0, 1000, 1000 // S) + 1`` and ``alpha_prev`` of the last step ``alphas_cumprod[0]``
    as in LDM's ``DDIMSampler``; ``x_prev = sqrt(a_prev) * x0 + sqrt(1 - a_prev) * eps``.
    """
    # 1. conditioning, as the original: zeros after the projection and for the latent as the null
    pose = embed_pose(d_az, d_el).expand(images.shape[0], -1, -1)  # (B, 1, 4)
    tokens, condition = pipe.encode_conditioning(images, pose)
    tokens = torch.cat([torch.zeros_like(tokens), tokens]).float()
    condition = torch.cat([torch.zeros_like(condition), condition]).float()
    # 2. schedule (scaled_linear betas, 1000 steps), computed in float64
    betas = torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float64) ** 2
    alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)
    ddim_timesteps = torch.arange(0, 1000, 1000 // num_inference_steps) + 1
    alphas = alphas_cumprod[ddim_timesteps]
    alphas_prev = torch.cat([alphas_cumprod[:1], alphas_cumprod[ddim_timesteps[:-1]]])
    # 3. loop
    x = noise.float()
    for index in reversed(range(len(ddim_timesteps))):
        timestep = ddim_timesteps[index]
        model_input = torch.cat([torch.cat([x, x]), condition], dim=1)
        eps_uncond, eps_cond = pipe.unet(model_input, timestep, encoder_hidden_states=tokens).sample.chunk(2)
        eps = eps_uncond + guidance_scale * (eps_cond - eps_uncond)
        a_t, a_prev = float(alphas[index]), float(alphas_prev[index])
        x0 = (x - math.sqrt(1.0 - a_t) * eps) / math.sqrt(a_t)
        x = math.sqrt(a_prev) * x0 + math.sqrt(1.0 - a_prev) * eps
    return pipe.decode_latents(x)


def _parameter_counts(pipe: SARZero123Pipeline) -> dict[str, int]:
    counts = {name: sum(p.numel() for p in getattr(pipe, name).parameters())
              for name in ("unet", "vae", "image_encoder", "pose_projection")}
    counts["total"] = sum(counts.values())
    return counts


def benchmark_size(config: BenchmarkConfig, size: str) -> dict:
    """All measurements for one model size."""
    device, dtype = torch.device(config.device), DTYPES[config.dtype]
    pipe = build_sar_zero123(size, seed=config.seed).to(device)
    pipe.set_progress_bar_config(disable=True)
    image_size = pipe.default_image_size
    generator = torch.Generator().manual_seed(config.seed)
    images = torch.rand(config.batch_size, 1, image_size, image_size, generator=generator).to(device)
    latent_size = image_size // pipe.vae_scale_factor
    noise = torch.randn(config.batch_size, 4, latent_size, latent_size, generator=generator).to(device)
    result: dict = {"size": size, "image_size": image_size, "parameters": _parameter_counts(pipe), "runs": []}

    # 1. reference loop and the pipeline on the same weights and noise, both fp32
    if config.reference:
        def reference_call() -> torch.Tensor:
            return reference_zero123_sample(pipe, images, 30.0, 0.0, noise, 50, config.guidance_scale)

        def pipeline_call() -> torch.Tensor:
            return pipe(images, 30.0, 0.0, num_inference_steps=50, guidance_scale=config.guidance_scale,
                        latents=noise, output_type="pt").images

        timings = _time_calls([reference_call, pipeline_call], device, config.repeats)
        (reference_seconds, reference_memory), (pipeline_seconds, _) = timings
        result["reference_fp32_ddim50"] = {
            "seconds_per_call": reference_seconds, "images_per_second": config.batch_size / reference_seconds,
            "peak_memory_mib": reference_memory,
            "pipeline_fp32_images_per_second": config.batch_size / pipeline_seconds,
            "pipeline_fp32_speedup": reference_seconds / pipeline_seconds,  # interleaved with the reference
            "max_abs_difference": float((reference_call() - pipeline_call()).abs().max()),
        }  # fmt: skip

    # 2. pipeline in the requested dtype against scheduler and steps
    if dtype != torch.float32:
        pipe.to(dtype=dtype)
    for scheduler_name in config.schedulers:
        set_scheduler(pipe, scheduler_name)
        for steps in config.steps:
            def call(steps: int = steps) -> None:
                pipe(images, 30.0, 0.0, num_inference_steps=steps, guidance_scale=config.guidance_scale,
                     generator=torch.Generator().manual_seed(config.seed), output_type="pt")

            [(seconds, memory)] = _time_calls([call], device, config.repeats)
            run = {"scheduler": scheduler_name, "num_inference_steps": steps, "seconds_per_call": seconds,
                   "images_per_second": config.batch_size / seconds, "peak_memory_mib": memory}
            if config.reference and scheduler_name == "ddim" and steps == 50 and dtype != torch.float32:
                run["speedup_vs_reference"] = result["reference_fp32_ddim50"]["seconds_per_call"] / seconds
            result["runs"].append(run)
            print(f"{size:8s} {scheduler_name:12s} {steps:3d} steps: {run['images_per_second']:.3f} img/s, "
                  f"peak {memory:.0f} MiB", flush=True)
    return result


def main(argv: Sequence[str] | None = None) -> dict:
    """Run the benchmark and write its JSON."""
    config = parse_config(BenchmarkConfig, argv)
    device = torch.device(config.device)
    arguments = sys.argv[1:] if argv is None else list(argv)
    report = {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(["python benchmarks/pipeline_speed.py", *arguments]),
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.machine(),
        "cpu_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "load_average_at_start": os.getloadavg(), "torch": torch.__version__, "dtype": config.dtype,
        "batch_size": config.batch_size, "guidance_scale": config.guidance_scale,
        "results": [benchmark_size(config, size) for size in config.sizes],
    }  # fmt: skip
    write_json_atomic(report, config.out)
    return report


if __name__ == "__main__":
    main()
