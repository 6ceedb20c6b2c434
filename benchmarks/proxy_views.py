"""Analysis by synthesis on unseen vehicles: template-matched azimuth, front/back and identity (issue 61)

    python benchmarks/proxy_views.py --out proxy_views.json
    python benchmarks/proxy_views.py --pairs_per_class 8 --bank_sizes 250 --out quick.json

On the simulator's eight named vehicles (never in a prior's corpus), each pair's input is rendered at 17 deg
and a random azimuth, and the request turns it by ``d_az`` with ``60 <= |d_az| <= 180`` deg (sign random),
``d_el = 0``. Every row's views are read by template matching (:mod:`sar_zero123.evaluation.template`):
each view's blurred correlation with its true vehicle's 17 deg renders on a 5 deg grid gives its azimuth;
over all eight vehicles' renders, its identity. Rows, on the same pairs: the input copy, the input turned
in the image plane (as ``rotated_input`` turns it) and the true view (another speckle draw: the ceiling);
the proxy alone (the bank vehicle fitted to the input, :class:`~sar_zero123.sim.proxy.ProxyBank`,
re-rendered at the request); the pipeline from noise with and without heading guidance and from the input
noised to each ``--strengths`` level and to 80 %; the pipeline from the proxy's render (``start_image``)
and from an oracle proxy (the true vehicle, another clutter draw) noised to each ``--strengths`` level.

Writes JSON (per row: mean template azimuth error and its standard error, gap closed between floor and
ceiling, front/back right, identity kept, seconds) and prints a table.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from _common import device_record, parallel_map, script_parser
from threadpoolctl import threadpool_limits

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.evaluation.template import read_templates, summarise_readings
from sar_zero123.model.conditioning import embed_pose, encode_condition_latents
from sar_zero123.model.orientation import azimuth_deg
from sar_zero123.model.proxy import DEFAULT_PROXY, check_proxy_settings, draft_target_views
from sar_zero123.model.spatial_pose import rotate_condition_latents
from sar_zero123.sim import TARGET_CLASSES, make_target, render_chip

INPUT_DEPRESSION_DEG = 17.0
SIM_ROTATION_SIGN = -1
GRID_DEG = np.arange(0.0, 360.0, 5.0)


def draw_pairs(classes: Sequence[str], pairs_per_class: int, seed: int) -> list[tuple[int, float, float]]:
    """``(vehicle index, input azimuth, d_az)`` per pair: azimuth in [0, 360), 60 <= |d_az| <= 180."""
    rng = np.random.default_rng(seed)
    pairs = []
    for v in range(len(classes)):
        for _ in range(pairs_per_class):
            magnitude = float(rng.uniform(60.0, 180.0))
            pairs.append((v, float(rng.uniform(0.0, 360.0)), magnitude * float(rng.choice([-1.0, 1.0]))))
    return pairs


def _draft(args: tuple) -> tuple[np.ndarray, float]:
    """One pair's proxy draft at the request and its fitted azimuth (a worker process), by the pipeline's
    own code (:func:`~sar_zero123.model.proxy.draft_target_views`; its bank is built once per process)."""
    proxy, image, azimuth, d_az, resolve_heading = args
    threadpool_limits(limits=1)  # one BLAS thread per process: N processes on N cores, not N x N threads
    one = torch.tensor
    draft, fitted = draft_target_views(
        torch.from_numpy(image)[None, None], one([azimuth]), one([INPUT_DEPRESSION_DEG]), one([d_az]),
        one([0.0]), proxy, resolve_heading=resolve_heading,
    )  # fmt: skip
    return draft[0, 0].numpy(), float(fitted[0])


def drafts_all(
    proxy: dict, images: np.ndarray, azimuths: Sequence[float], d_az: Sequence[float], resolve_heading: bool,
    workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Every pair's proxy draft ``(N, S, S)`` and fitted azimuth ``(N,)``, in ``workers`` processes."""
    jobs = [(proxy, im, float(a), float(d), resolve_heading) for im, a, d in zip(images, azimuths, d_az)]
    done = parallel_map(_draft, jobs, workers)
    return np.stack([d for d, _ in done]).astype(np.float32), np.array([a for _, a in done])


class SimulatedPairs:
    """The benchmark's pairs on the named vehicles: inputs, true views, turntables and the template reader.

    Attributes:
        pairs: ``(vehicle index, input azimuth, d_az)`` per pair (:func:`draw_pairs`).
        vehicle, d_az, requested: Per pair: vehicle index, azimuth change, requested absolute azimuth.
        inputs, truth: Normalised dB chips ``(N, S, S)``: the 17 deg input and the true view (another
            speckle and clutter draw).
        turntables: Each vehicle's 17 deg renders on :data:`GRID_DEG` ``(V, G, S, S)``.
    """

    def __init__(self, size: int, scaling: DecibelScaling, pairs_per_class: int, seed: int) -> None:
        self.classes = list(TARGET_CLASSES)
        self.size, self.scaling, self.seed = size, scaling, seed
        self.targets = [make_target(name) for name in self.classes]
        self.pairs = draw_pairs(self.classes, pairs_per_class, seed)
        self.vehicle = np.array([v for v, _, _ in self.pairs])
        self.d_az = [d for _, _, d in self.pairs]
        self.input_azimuth = [a for _, a, _ in self.pairs]
        self.requested = np.array([(a + d) % 360.0 for _, a, d in self.pairs])
        self.inputs = np.stack([self.render(v, a, (seed, k, 0)) for k, (v, a, _) in enumerate(self.pairs)])
        self.truth = np.stack([self.render(v, a + d, (seed, k, 1)) for k, (v, a, d) in enumerate(self.pairs)])
        vehicles = range(len(self.targets))
        self.turntables = np.stack(
            [[self.render(v, g, (seed, 10_000 + v, int(g))) for g in GRID_DEG] for v in vehicles]
        )

    def render(self, v: int, azimuth: float, stream: tuple[int, ...]) -> np.ndarray:
        """Vehicle ``v`` at 17 deg and ``azimuth``, clutter and speckle from ``stream``, in normalised dB."""
        chip = render_chip(
            self.targets[v], azimuth % 360.0, INPUT_DEPRESSION_DEG, self.size, np.random.default_rng(stream)
        )
        return self.scaling.normalize(chip).astype(np.float32)

    def read(self, views: np.ndarray):
        """Template readings of one view per pair (:func:`sar_zero123.evaluation.template.read_templates`)."""
        return read_templates(views, self.turntables, GRID_DEG, self.vehicle, self.requested)


def run(
    pipeline: str = SIM_PRIOR_ROTATED,
    *,
    pairs_per_class: int = 32,
    bank_sizes: Sequence[int] = (250, 1000),
    strengths: Sequence[float] = (0.3, 0.5),
    heading_guidance_scale: float = 1.5,
    num_inference_steps: int = 20,
    batch_size: int = 32,
    seed: int = 0,
    workers: int = 2,
    max_shift_px: int | None = None,
) -> dict:
    """Every row's template readings on the same pairs; see the module docstring."""
    scaling = DecibelScaling.from_dict(json.loads((resolve_pretrained(pipeline) / SCALING_FILE).read_text()))
    pipe = SARZero123Pipeline.from_pretrained(pipeline)
    pipe.set_progress_bar_config(disable=True)
    size = pipe.default_image_size
    sim = SimulatedPairs(size, scaling, pairs_per_class, seed)
    pairs, d_az, inputs, truth = sim.pairs, sim.d_az, sim.inputs, sim.truth
    render, read = sim.render, sim.read

    floor, ceiling = read(inputs), read(truth)
    rows: dict[str, dict] = {}

    def add(name: str, views: np.ndarray, seconds: float) -> None:
        rows[name] = summarise_readings(read(views), floor, ceiling) | {"seconds": seconds}
        print_row(name, rows[name])

    add("input copy (unturned, keeps identity)", inputs, 0.0)
    pose = embed_pose(d_az, [0.0] * len(d_az))
    turned = rotate_condition_latents(torch.from_numpy(inputs)[:, None], pose, SIM_ROTATION_SIGN)[:, 0]
    add("input turned", turned.numpy(), 0.0)
    add("true view, another speckle draw (ceiling)", truth, 0.0)

    proxies: dict[str, np.ndarray] = {}
    # the pipeline's recorded proxy settings (a pipeline without them: the defaults at its scaling)
    recorded_proxy = check_proxy_settings(pipe.config.proxy or {**DEFAULT_PROXY, **scaling.to_dict()})
    if max_shift_px is not None:
        recorded_proxy["max_shift_px"] = max_shift_px
    input_azimuth = sim.input_azimuth
    for bank_size in bank_sizes:
        proxy = {**recorded_proxy, "num_vehicles": bank_size}
        begin = time.perf_counter()
        proxies[str(bank_size)], _ = drafts_all(proxy, inputs, input_azimuth, d_az, False, workers)
        add(f"proxy alone (bank {bank_size}), input azimuth given", proxies[str(bank_size)],
            time.perf_counter() - begin)  # fmt: skip
    # the pipeline's path without the input's azimuth: its estimator's reading, the heading fitted
    smallest = {**recorded_proxy, "num_vehicles": min(bank_sizes)}
    with torch.no_grad():
        latents = encode_condition_latents(pipe.vae, torch.from_numpy(inputs)[:, None])
        estimated = azimuth_deg(pipe.azimuth_estimator(latents)).numpy()
    begin = time.perf_counter()
    proxies["estimated"], fitted = drafts_all(smallest, inputs, estimated, d_az, True, workers)
    add(f"proxy alone (bank {min(bank_sizes)}), azimuth estimated, heading fitted", proxies["estimated"],
        time.perf_counter() - begin)  # fmt: skip
    truth_azimuth = np.array(input_azimuth)
    estimate = {
        "estimator_error_deg": float(np.mean(np.abs((estimated - truth_azimuth + 180.0) % 360.0 - 180.0))),
        "fitted_error_deg": float(np.mean(np.abs((fitted - truth_azimuth + 180.0) % 360.0 - 180.0))),
        "fitted_heading_right": float(np.mean(np.abs((fitted - truth_azimuth + 180.0) % 360.0 - 180.0) < 90)),
    }
    print(f"azimuth estimate: {estimate}", flush=True)

    def sample(start: np.ndarray | None, strength: float, heading: float) -> tuple[np.ndarray, float]:
        begin, views = time.perf_counter(), []
        for s in range(0, len(pairs), batch_size):
            chunk = slice(s, s + batch_size)
            n = len(d_az[chunk])
            views.append(pipe(
                torch.from_numpy(inputs[chunk])[:, None], d_az=d_az[chunk], d_el=0.0,
                input_depression_deg=INPUT_DEPRESSION_DEG, num_inference_steps=num_inference_steps,
                heading_guidance_scale=heading, strength=strength,
                start_image=None if start is None else torch.from_numpy(start[chunk])[:, None],
                generator=[torch.Generator().manual_seed(seed + k) for k in range(s, s + n)],
                output_type="np",
            ).images[..., 0])  # fmt: skip
        return np.concatenate(views), time.perf_counter() - begin

    add(f"{pipeline}, from noise, no heading guidance", *sample(None, 1.0, 0.0))
    add(f"{pipeline}, from noise, heading guidance {heading_guidance_scale:g}",
        *sample(None, 1.0, heading_guidance_scale))  # fmt: skip
    add(f"{pipeline}, heading guidance {heading_guidance_scale:g}, strength 0.8",
        *sample(None, 0.8, heading_guidance_scale))  # fmt: skip
    best = proxies[str(max(bank_sizes))]
    for strength in strengths:
        for heading in (0.0, heading_guidance_scale):
            name = f"{pipeline} from the proxy (bank {max(bank_sizes)}), strength {strength:g}, "
            name += f"heading {heading:g}"
            add(name, *sample(best, strength, heading))
    for strength in strengths:
        name = f"{pipeline} from the input, strength {strength:g}, heading {heading_guidance_scale:g}"
        add(name, *sample(None, strength, heading_guidance_scale))
    oracle = np.stack([render(v, a + d, (seed, k, 2)) for k, (v, a, d) in enumerate(pairs)])
    for strength in strengths:  # the true vehicle as the proxy: what a perfect fit would give
        name = f"{pipeline} from an oracle proxy (the true vehicle), strength {strength:g}, "
        name += f"heading {heading_guidance_scale:g}"
        add(name, *sample(oracle, strength, heading_guidance_scale))
    return {"benchmark": "proxy_views (issue 61)", "pipeline": str(pipeline), "classes": sim.classes,
            "pairs_per_class": pairs_per_class, "d_az_range_deg": [60.0, 180.0],
            "input_depression_deg": INPUT_DEPRESSION_DEG, "template_grid_deg": 5.0,
            "num_inference_steps": num_inference_steps, "seed": seed, **device_record(),
            "input_azimuth_estimate": estimate, "rows": rows}  # fmt: skip


def print_row(name: str, r: dict) -> None:
    """One row's readings on stdout as it is done: error, gap closed, front/back, identity, seconds."""
    print(f"{name}: err {r['azimuth_error_deg']:.1f} ± {r['azimuth_error_deg_se']:.1f}, gap "
          f"{r['gap_closed']:.0%}, front/back {r['front_back_right']:.0%}, identity "
          f"{r['identity_kept']:.0%} ({r['seconds']:.0f} s)", flush=True)  # fmt: skip


def format_table(record: dict) -> str:
    lines = [
        "| row | template azimuth error (deg) ↓ | gap closed ↑ | front/back right ↑ | identity kept ↑ "
        "| turned and kept ↑ |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name, r in record["rows"].items():
        lines.append(
            f"| {name} | {r['azimuth_error_deg']:.1f} ± {r['azimuth_error_deg_se']:.1f} | "
            f"{r['gap_closed']:.0%} | "
            f"{r['front_back_right']:.0%} ± {r['front_back_right_se']:.0%} | "
            f"{r['identity_kept']:.0%} ± {r['identity_kept_se']:.0%} | "
            f"{r['turned_and_kept']:.0%} ± {r['turned_and_kept_se']:.0%} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--pipeline", default=SIM_PRIOR_ROTATED, help="pipeline folder or bundled name")
    parser.add_argument("--pairs_per_class", type=int, default=32, help="pairs per named vehicle (8)")
    parser.add_argument("--bank_sizes", nargs="+", type=int, default=[250, 1000], help="proxy bank sizes")
    parser.add_argument("--strengths", nargs="+", type=float, default=[0.3, 0.5],
                        help="noise levels the proxy start is noised to")  # fmt: skip
    parser.add_argument("--heading_guidance_scale", type=float, default=1.5, help="heading guidance weight")
    parser.add_argument("--num_inference_steps", type=int, default=20, help="DDIM steps")
    parser.add_argument("--batch_size", type=int, default=32, help="views per pipeline call")
    parser.add_argument("--seed", type=int, default=0, help="pairs, clutter and sampling seed")
    parser.add_argument("--workers", type=int, default=2, help="processes for the proxy retrieval")
    parser.add_argument("--max_shift_px", type=int, default=None,
                        help="the proxy fit's largest shift (default: the pipeline's recorded one)")
    parser.add_argument("--out", default="proxy_views.json", help="output JSON")
    args = parser.parse_args(argv)
    if args.pairs_per_class < 2:
        raise ValueError(f"pairs_per_class must be >= 2, got {args.pairs_per_class}")
    record = run(
        args.pipeline, pairs_per_class=args.pairs_per_class, bank_sizes=args.bank_sizes,
        strengths=args.strengths, heading_guidance_scale=args.heading_guidance_scale,
        num_inference_steps=args.num_inference_steps,
        batch_size=args.batch_size, seed=args.seed, workers=args.workers, max_shift_px=args.max_shift_px,
    )  # fmt: skip
    write_json_atomic(record, Path(args.out))
    print(format_table(record))
    return record


if __name__ == "__main__":
    main()
