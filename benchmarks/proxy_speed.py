"""What a view costs with and without the simulator proxy (issue 61)

    python benchmarks/proxy_speed.py --out proxy_speed.json

The bundled prior's plain call on one simulated 64 px chip asked for ``--views`` azimuth changes (one batch,
as ``sar-zero123-generate`` makes it), with its recorded sampler: without the input's azimuth (from noise)
and with it (from the proxy: one fit of the chip against the bank, then one render per view); with
``--proxy_pipeline``, also a proxy-conditioned prior's plain call (one fit, then the proxy rendered at the
input's pose and at each request and its flipped heading). The first call with the proxy also builds the
bank's vehicles (once per process); it is timed apart. Each timing is the median of ``--repeats`` calls,
each on a fresh chip (so that every call fits), on this process's threads.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from _common import device_record, script_parser

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.sim import make_target, render_chip


def main(argv: Sequence[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--views", type=int, default=3, help="views of the chip per call")
    parser.add_argument("--repeats", type=int, default=3, help="calls per timing (median)")
    parser.add_argument("--proxy_pipeline", default=None,
                        help="also time a spatial_pose='proxy' pipeline's plain call (folder or name)")
    parser.add_argument("--out", default="proxy_speed.json", help="output JSON")
    args = parser.parse_args(argv)
    if args.views < 1 or args.repeats < 1:
        raise ValueError(f"views and repeats must be >= 1, got {args.views} and {args.repeats}")
    pipe = SARZero123Pipeline.from_pretrained(SIM_PRIOR_ROTATED)
    pipe.set_progress_bar_config(disable=True)
    scaling = DecibelScaling.from_file(resolve_pretrained(SIM_PRIOR_ROTATED) / SCALING_FILE)
    d_az = [float(a) for a in np.linspace(30.0, 180.0, args.views)]

    def call(seed: int, model: SARZero123Pipeline = pipe, **kwargs) -> float:
        """One call on a fresh chip (its own clutter: a fit is never reused from an earlier call)."""
        magnitude = render_chip(make_target("TANK"), 30.0, 17.0, 64, np.random.default_rng(seed))
        chip = torch.from_numpy(scaling.normalize(magnitude).astype(np.float32))
        images = chip[None, None].repeat(args.views, 1, 1, 1)  # (V, 1, S, S): one chip, V requests
        begin = time.perf_counter()
        model(images, d_az=d_az, input_depression_deg=17.0, output_type="np", **kwargs)
        return time.perf_counter() - begin

    first_proxy_call = call(0, input_azimuth_deg=30.0)  # builds the bank's vehicles
    seconds = {
        "without the azimuth (from noise)": statistics.median(call(1 + k) for k in range(args.repeats)),
        "with the azimuth (from the proxy)": statistics.median(call(1 + k, input_azimuth_deg=30.0)
                                                               for k in range(args.repeats)),
    }  # fmt: skip
    if args.proxy_pipeline is not None:  # fits once, renders the proxy at the input's pose and each request
        other = SARZero123Pipeline.from_pretrained(args.proxy_pipeline)
        other.set_progress_bar_config(disable=True)
        name = f"{args.proxy_pipeline}, the proxy-conditioned prior (with the azimuth)"
        seconds[name] = statistics.median(call(100 + k, model=other, input_azimuth_deg=30.0)  # fresh chips
                                          for k in range(args.repeats))  # fmt: skip
    record = {"benchmark": "proxy_speed (issue 61)", "pipeline": SIM_PRIOR_ROTATED,
              "sampler": pipe.config.sampler, "proxy": pipe.config.proxy, "views_per_call": args.views,
              "seconds_per_call": seconds,
              "seconds_per_view": {name: value / args.views for name, value in seconds.items()},
              "first_proxy_call_seconds": first_proxy_call, "torch_threads": torch.get_num_threads(),
              **device_record()}  # fmt: skip
    write_json_atomic(record, Path(args.out))
    for name, value in seconds.items():
        print(f"{name}: {value:.2f} s per call of {args.views} views")
    print(f"first call with the proxy (bank built): {first_proxy_call:.2f} s")
    return record


if __name__ == "__main__":
    main()
