"""Training throughput against the machine's limit: the fine-tune's UNet step beside this device's GEMM rate.

    python benchmarks/training_throughput.py --out docs/results/data/training_throughput_cpu.json

For the bundled prior's UNet (``sar-zero123/sim-prior-rotated``, the quickstart's model), at each batch size:
the FLOPs of one training step per sample (``torch.utils.flop_counter.FlopCounterMode``); steps/s and
samples/s of a step (forward, MSE, backward, AdamW) in float32, channels-last, bf16 autocast and
``torch.compile``, each also with the fine-tunes' fused AdamW (``fused AdamW``, ``fused AdamW +
torch.compile``), timed in alternating rounds so that a busier machine moment hits them alike; the
achieved FLOP rate as a fraction of this device's best ``torch.mm`` rate (at the model's matrix sizes and
at 2048^2); and the ten most expensive operators of a float32 step (``torch.profiler``). The data are
random latents of the model's shape: a step's cost does not depend on the values, and a fine-tune caches
its latents.
"""

from __future__ import annotations

import json
import platform
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from _common import script_parser
from torch.utils.flop_counter import FlopCounterMode

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline
from sar_zero123.config.json_io import write_json_atomic


def _inputs(unet, batch: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random latents, timesteps, image tokens and (a UNet that embeds the pose with its timestep) the
    pose vector, in the training step's shapes."""
    generator = torch.Generator().manual_seed(seed)
    size = unet.config.sample_size
    sample = torch.randn(batch, unet.config.in_channels, size, size, generator=generator)
    timesteps = torch.randint(0, 1000, (batch,), generator=generator)
    hidden = torch.randn(batch, 1, unet.config.cross_attention_dim, generator=generator)
    pose_dim = unet.config.projection_class_embeddings_input_dim
    labels = None if pose_dim is None else torch.randn(batch, pose_dim, generator=generator)
    return sample, timesteps, hidden, labels


def _step_function(unet, optimizer, variant: str):
    """One training step of ``unet`` (forward, MSE against a target, backward, AdamW) for a variant."""
    autocast = variant == "bf16 autocast"

    def step(sample, timesteps, hidden, labels, target):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            prediction = unet(sample, timesteps, encoder_hidden_states=hidden, class_labels=labels).sample
        loss = F.mse_loss(prediction.float(), target)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        return loss

    return step


def flops_per_sample(unet, batch: int) -> float:
    """Forward and backward FLOPs of one training step, per sample."""
    sample, timesteps, hidden, labels = _inputs(unet, batch)
    counter = FlopCounterMode(display=False)
    with counter:
        prediction = unet(sample, timesteps, encoder_hidden_states=hidden, class_labels=labels).sample
        F.mse_loss(prediction, torch.zeros_like(prediction)).backward()
    unet.zero_grad(set_to_none=True)
    return counter.get_total_flops() / batch


def gemm_rate(unet, batch: int, repeats: int = 5) -> dict[str, float]:
    """float32 ``torch.mm`` FLOP/s at the UNet's convolution sizes (as im2col products) and at 2048^2."""
    size = unet.config.sample_size
    shapes = {"2048x2048x2048": (2048, 2048, 2048)}
    for level, width in enumerate(unet.config.block_out_channels):
        side = max(size // 2**level, 1)
        shapes[f"conv level {level}"] = (batch * side * side, width * 9, width)
    rates = {}
    for name, (m, k, n) in shapes.items():
        a, b = torch.randn(m, k), torch.randn(k, n)
        torch.mm(a, b)
        best = float("inf")
        for _ in range(repeats):
            begin = time.perf_counter()
            torch.mm(a, b)
            best = min(best, time.perf_counter() - begin)
        rates[name] = 2.0 * m * k * n / best
    return rates


def time_variants(pipeline: str, batch: int, variants: list[str], rounds: int, steps: int) -> dict:
    """Seconds per step of each variant, in alternating rounds (each round times ``steps`` steps)."""
    runs = {}
    for variant in variants:
        unet = SARZero123Pipeline.from_pretrained(pipeline).unet.train()
        if variant == "channels-last":
            unet = unet.to(memory_format=torch.channels_last)
        # "fused AdamW": the fine-tunes' optimizer (sar_zero123.training.finetuning), one kernel per update
        fused = variant.startswith("fused AdamW")
        optimizer = torch.optim.AdamW(unet.parameters(), lr=1e-5, fused=fused)
        step = _step_function(unet, optimizer, variant)
        if variant.endswith("torch.compile"):
            step = torch.compile(step)
        sample, timesteps, hidden, labels = _inputs(unet, batch)
        if variant == "channels-last":
            sample = sample.contiguous(memory_format=torch.channels_last)
        target = torch.randn_like(sample[:, : unet.config.out_channels])
        begin = time.perf_counter()
        for _ in range(2):  # warm-up (and compilation)
            step(sample, timesteps, hidden, labels, target)
        runs[variant] = {"step": step, "args": (sample, timesteps, hidden, labels, target), "times": [],
                         "warmup_s": time.perf_counter() - begin}  # fmt: skip
    for _ in range(rounds):
        for run in runs.values():
            begin = time.perf_counter()
            for _ in range(steps):
                run["step"](*run["args"])
            run["times"].append((time.perf_counter() - begin) / steps)
    return {
        variant: {"seconds_per_step": statistics.median(run["times"]), "rounds": run["times"],
                  "warmup_s": run["warmup_s"]}
        for variant, run in runs.items()
    }  # fmt: skip


def profile_step(pipeline: str, batch: int) -> dict:
    """Where a float32 step's CPU time goes: the top operators and the convolution / matmul share."""
    from torch.profiler import ProfilerActivity, profile

    unet = SARZero123Pipeline.from_pretrained(pipeline).unet.train()
    optimizer = torch.optim.AdamW(unet.parameters(), lr=1e-5)
    step = _step_function(unet, optimizer, "float32")
    sample, timesteps, hidden, labels = _inputs(unet, batch)
    target = torch.randn_like(sample[:, : unet.config.out_channels])
    step(sample, timesteps, hidden, labels, target)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(3):
            step(sample, timesteps, hidden, labels, target)
    events = [e for e in prof.key_averages() if e.key.startswith("aten::")]
    total = sum(e.self_cpu_time_total for e in events)
    dense = ("conv", "mm", "addmm", "bmm", "matmul", "linear", "baddbmm", "mkldnn")
    dense_time = sum(e.self_cpu_time_total for e in events if any(d in e.key for d in dense))
    top = sorted(events, key=lambda e: -e.self_cpu_time_total)[:10]
    return {"dense_share": dense_time / total if total else float("nan"),
            "top": [{"op": e.key, "share": e.self_cpu_time_total / total, "calls": e.count} for e in top]}


def main(argv: list[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--pipeline", default=SIM_PRIOR_ROTATED, help="the pipeline whose UNet is trained")
    parser.add_argument("--batch_sizes", type=int, nargs="+", default=[16, 64])
    parser.add_argument("--variants", nargs="+",
                        default=["float32", "channels-last", "bf16 autocast", "torch.compile"])  # fmt: skip
    parser.add_argument("--rounds", type=int, default=5, help="alternating timing rounds per variant")
    parser.add_argument("--steps", type=int, default=5, help="training steps per round")
    parser.add_argument("--out", type=Path, required=True, help="JSON of the results")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    unet = SARZero123Pipeline.from_pretrained(args.pipeline).unet
    results = {
        "pipeline": str(args.pipeline), "device": f"CPU ({platform.processor() or platform.machine()}), "
        f"{torch.get_num_threads()} threads", "torch": torch.__version__,
        "unet_parameters": sum(p.numel() for p in unet.parameters()), "batches": {},
    }  # fmt: skip
    for batch in args.batch_sizes:
        flops = flops_per_sample(unet, batch)
        gemm = gemm_rate(unet, batch)
        peak = max(gemm.values())
        timing = time_variants(args.pipeline, batch, args.variants, args.rounds, args.steps)
        base = timing["float32"]["seconds_per_step"] if "float32" in timing else None
        for row in timing.values():
            seconds = row["seconds_per_step"]
            rate = flops * batch / seconds
            row.update(steps_per_s=1.0 / seconds, samples_per_s=batch / seconds, achieved_flops_per_s=rate,
                       fraction_of_gemm_rate=rate / peak,
                       speedup_over_float32=None if base is None else base / seconds)  # fmt: skip
        results["batches"][str(batch)] = {
            "train_flops_per_sample": flops, "gemm_flops_per_s": gemm, "gemm_peak_flops_per_s": peak,
            "variants": timing, "profile_float32": profile_step(args.pipeline, batch),
        }  # fmt: skip
        print(json.dumps({"batch": batch, **{v: round(r["samples_per_s"], 1) for v, r in timing.items()}}))
    write_json_atomic(results, args.out)
    return results


if __name__ == "__main__":
    main()
