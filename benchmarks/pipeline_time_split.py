"""Where the time of a pipeline call goes: the UNet, the VAE, the image tower, the proxy, and the rest.

    python benchmarks/pipeline_time_split.py --out docs/results/data/pipeline_time_split_cpu.json

For each bundled pipeline, one call on a batch of simulated chips (the named vehicles at 17 deg, each asked
for a 90 deg turn) with the pipeline's recorded sampler; the proxy prior and the rotated prior's proxy start
are given each chip's azimuth. Forward hooks time the UNet, the VAE's encoder and decoder, the CLIP image
tower and the azimuth estimator; a wrapper times the proxy's fit and renders. What the call spends outside
them is the pipeline's own overhead. The UNet's calls are then replayed as a bare loop (the same input
shapes, random values, no pipeline around them), so that the call's cost is a ratio to the network work it
cannot avoid. Each call runs ``--repeats`` times on fresh chips (so that the proxy fit is never a cached
one); the medians are reported.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import script_parser

from sar_zero123 import SIM_PRIOR_IDENTITY, SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained  # noqa: E402
from sar_zero123.config.json_io import write_json_atomic  # noqa: E402
from sar_zero123.data import SCALING_FILE, DecibelScaling  # noqa: E402
from sar_zero123.model import proxy as proxy_module  # noqa: E402
from sar_zero123.model.proxy import _fit as proxy_fits  # noqa: E402
from sar_zero123.sim import TARGET_CLASSES, make_target, render_chip  # noqa: E402

PARTS = ("unet", "vae encoder", "vae decoder", "image encoder", "azimuth estimator", "proxy")


class Timer:
    """Seconds spent in each hooked part of a pipeline, and the UNet calls' input shapes."""

    def __init__(self, pipe: SARZero123Pipeline) -> None:
        self.seconds = dict.fromkeys(PARTS, 0.0)
        self.unet_calls: list[dict[str, tuple]] = []
        self._handles = []
        modules = {"unet": pipe.unet, "vae encoder": pipe.vae.encoder, "vae decoder": pipe.vae.decoder,
                   "image encoder": pipe.image_encoder,
                   "azimuth estimator": pipe.azimuth_estimator}  # fmt: skip
        for name, module in modules.items():
            if module is not None:
                self._hook(name, module)
        self._draft = proxy_module.draft_target_views

        def timed_draft(*args, **kwargs):
            begin = time.perf_counter()
            try:
                return self._draft(*args, **kwargs)
            finally:
                self.seconds["proxy"] += time.perf_counter() - begin

        proxy_module.draft_target_views = timed_draft

    def _hook(self, name: str, module: torch.nn.Module) -> None:
        starts: list[float] = []

        def before(mod, args, kwargs):
            if name == "unet":
                sample = args[0] if args else kwargs["sample"]
                timestep = args[1] if len(args) > 1 else kwargs["timestep"]
                hidden = kwargs.get("encoder_hidden_states")
                labels = kwargs.get("class_labels")
                self.unet_calls.append({
                    "sample": tuple(sample.shape), "timestep": tuple(torch.as_tensor(timestep).shape),
                    "hidden": None if hidden is None else tuple(hidden.shape),
                    "labels": None if labels is None else tuple(labels.shape),
                })  # fmt: skip
            starts.append(time.perf_counter())

        def after(mod, args, kwargs, output):
            self.seconds[name] += time.perf_counter() - starts.pop()

        self._handles.append(module.register_forward_pre_hook(before, with_kwargs=True))
        self._handles.append(module.register_forward_hook(after, with_kwargs=True))

    def close(self) -> None:
        for handle in self._handles:
            handle.remove()
        proxy_module.draft_target_views = self._draft


@torch.no_grad()
def bare_unet_loop(unet: torch.nn.Module, calls: list[dict[str, tuple]]) -> float:
    """Seconds for the same UNet calls with random inputs of the same shapes, nothing around them."""
    generator = torch.Generator().manual_seed(0)
    inputs = []
    for call in calls:
        sample = torch.randn(call["sample"], generator=generator)
        shape = call["timestep"]
        timestep = torch.full(shape, 500, dtype=torch.long) if shape else torch.tensor(500)
        hidden = None if call["hidden"] is None else torch.randn(call["hidden"], generator=generator)
        labels = None if call["labels"] is None else torch.randn(call["labels"], generator=generator)
        inputs.append((sample, timestep, hidden, labels))
    begin = time.perf_counter()
    for sample, timestep, hidden, labels in inputs:
        unet(sample, timestep, encoder_hidden_states=hidden, class_labels=labels)
    return time.perf_counter() - begin


def chips(scaling: DecibelScaling, batch: int, seed: int) -> tuple[torch.Tensor, list[float]]:
    """``batch`` simulated chips (named vehicles in turn, random azimuths, 17 deg) and their azimuths."""
    rng = np.random.default_rng(seed)
    images, azimuths = [], []
    for k in range(batch):
        azimuth = float(rng.uniform(0.0, 360.0))
        target = make_target(TARGET_CLASSES[k % len(TARGET_CLASSES)])
        magnitude = render_chip(target, azimuth, 17.0, 64, np.random.default_rng(seed * 1000 + k))
        images.append(scaling.normalize(magnitude))
        azimuths.append(azimuth)
    return torch.from_numpy(np.stack(images)[:, None]).float(), azimuths


def split(pipeline: str, batch: int, repeats: int, with_azimuth: bool) -> dict:
    pipe = SARZero123Pipeline.from_pretrained(pipeline)
    pipe.set_progress_bar_config(disable=True)
    scaling = DecibelScaling.from_file(resolve_pretrained(pipeline) / SCALING_FILE)
    runs = []
    for repeat in range(repeats + 1):  # the first call builds the proxy bank and warms up: not counted
        images, azimuths = chips(scaling, batch, seed=repeat)
        proxy_fits.cache_clear()  # every call fits its chips (the process remembers fits otherwise)
        timer = Timer(pipe)
        begin = time.perf_counter()
        pipe(images, d_az=90.0, d_el=0.0, input_depression_deg=17.0,
             input_azimuth_deg=azimuths if with_azimuth else None,
             generator=torch.Generator().manual_seed(repeat), output_type="np")  # fmt: skip
        total = time.perf_counter() - begin
        timer.close()
        if repeat == 0:
            continue
        bare = bare_unet_loop(pipe.unet, timer.unet_calls)
        parts = dict(timer.seconds)
        overhead = total - sum(parts.values())
        samples = sum(call["sample"][0] for call in timer.unet_calls)
        runs.append({"total_s": total, **{f"{k}_s": v for k, v in parts.items()}, "overhead_s": overhead,
                     "bare_unet_loop_s": bare, "unet_calls": len(timer.unet_calls),
                     "unet_evaluations_per_image": samples / batch})  # fmt: skip
    median = {key: statistics.median(run[key] for run in runs) for key in runs[0]}
    median["total_over_bare_unet_loop"] = median["total_s"] / median["bare_unet_loop_s"]
    median["seconds_per_view"] = median["total_s"] / batch
    return {"pipeline": str(pipeline), "batch": batch, "input_azimuth_given": with_azimuth,
            "recorded_sampler": pipe.config.sampler, "repeats": repeats, "median": median,
            "runs": runs}  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--batch", type=int, default=8, help="chips per call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per row (after one warm-up)")
    parser.add_argument("--out", type=Path, required=True, help="JSON of the results")
    args = parser.parse_args(argv)
    rows = [
        split(SIM_PRIOR_ROTATED, args.batch, args.repeats, with_azimuth=False),
        split(SIM_PRIOR_ROTATED, args.batch, args.repeats, with_azimuth=True),
        split(SIM_PRIOR_IDENTITY, args.batch, args.repeats, with_azimuth=True),
    ]
    result = {"device": f"CPU, {torch.get_num_threads()} torch threads, torch {torch.__version__}",
              "rows": rows}
    write_json_atomic(result, args.out)
    for row in rows:
        m = row["median"]
        parts = ", ".join(f"{k} {m[f'{k}_s']:.2f}" for k in PARTS if m[f"{k}_s"] > 0)
        print(f"{row['pipeline']} (azimuth {'given' if row['input_azimuth_given'] else 'not given'}): "
              f"{m['total_s']:.2f} s for {row['batch']} views = {parts}, overhead {m['overhead_s']:.2f}; "
              f"bare UNet loop {m['bare_unet_loop_s']:.2f} s (x{m['total_over_bare_unet_loop']:.2f}), "
              f"{m['unet_evaluations_per_image']:.0f} UNet evaluations per view")  # fmt: skip
    return result


if __name__ == "__main__":
    main()
