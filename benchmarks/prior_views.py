"""Views of a pipeline on named simulator vehicles at azimuth and depression requests, beside the truth.

    python benchmarks/prior_views.py --out docs/figures/prior_views.png
    python benchmarks/prior_views.py --pipeline runs/quickstart/finetune_lambda0/pipeline --out views.png

Each vehicle gets two rows: the generated views (the input chip first) and the simulator's true views at
the requested poses. The input is at 17 deg depression (MSTAR's training depression) and its azimuth
is given to the pipeline (the bundled `sim-prior-rotated` then starts from its simulator proxy); the
default pipeline is the bundled prior, which never saw the named vehicles. Also prints, per request,
whether each blurred view (sigma 1.5 px) correlates better with the truth at the requested pose than with
the truth at the input pose, and writes those numbers beside the figure as JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from _common import script_parser
from scipy.ndimage import gaussian_filter

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.sim import Target, make_target, render_chip

REQUESTS = ((60.0, 0.0), (150.0, 0.0), (0.0, -7.0), (0.0, 13.0), (0.0, 28.0), (90.0, 28.0))


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two images."""
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    return float((a * b).sum() / max(np.sqrt((a * a).sum() * (b * b).sum()), 1e-12))


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = script_parser(__doc__)
    parser.add_argument("--pipeline", default=SIM_PRIOR_ROTATED, help="pipeline folder or bundled name")
    parser.add_argument("--classes", nargs="+", default=["TANK", "TRUCK", "AAGUN"], help="named vehicles")
    parser.add_argument("--input_azimuth_deg", type=float, default=30.0, help="azimuth of every input")
    parser.add_argument("--num_inference_steps", type=int, default=20, help="DDIM steps")
    parser.add_argument("--seed", type=int, default=0, help="clutter and sampling seed")
    parser.add_argument("--out", default="prior_views.png", help="output PNG (and .json beside it)")
    return parser.parse_args(argv)


def simulated_view(
    target: Target, azimuth_deg: float, depression_deg: float, size: int, scaling: DecibelScaling,
    seed: Sequence[int],
) -> np.ndarray:
    """The simulator's normalised chip of ``target`` at one pose, its clutter drawn from ``seed``."""
    chip = render_chip(target, azimuth_deg % 360.0, depression_deg, size, np.random.default_rng(seed))
    return scaling.normalize(chip).astype(np.float32)


def generate_views(
    args: argparse.Namespace,
) -> tuple[list[tuple[str, list[np.ndarray]]], dict[str, list[bool]], float]:
    """Each vehicle's generated and true views, and per request whether each view is closer to the truth.

    Returns:
        ``(rows, scores, seconds)``: two labelled rows of images per vehicle (the input chip first), per
        request one bool per vehicle, and the seconds it took after loading the pipeline.
    """
    pipe = SARZero123Pipeline.from_pretrained(args.pipeline)
    pipe.set_progress_bar_config(disable=True)
    folder = resolve_pretrained(args.pipeline)
    scaling = DecibelScaling.from_dict(json.loads((Path(folder) / SCALING_FILE).read_text()))
    size = pipe.default_image_size
    input_depression = 17.0
    rows, scores = [], {}
    begin = time.perf_counter()
    for i, name in enumerate(args.classes):
        target = make_target(name)

        def view(azimuth: float, depression: float, stream: int, target=target, i=i) -> np.ndarray:
            return simulated_view(target, azimuth, depression, size, scaling, [args.seed, i, stream])

        azimuth = args.input_azimuth_deg
        chip = view(azimuth, input_depression, 0)
        d_az = [r[0] for r in REQUESTS]
        d_el = [r[1] for r in REQUESTS]
        generated = pipe(
            torch.from_numpy(chip)[None, None].expand(len(REQUESTS), -1, -1, -1), d_az=d_az, d_el=d_el,
            input_depression_deg=input_depression,
            input_azimuth_deg=args.input_azimuth_deg,  # known here: a recorded proxy start uses it
            num_inference_steps=args.num_inference_steps,
            generator=[torch.Generator().manual_seed(args.seed + k) for k in range(len(REQUESTS))],
            output_type="np",
        ).images[..., 0]  # fmt: skip
        truth = [view(azimuth + a, input_depression + e, 1 + k) for k, (a, e) in enumerate(REQUESTS)]
        at_input = view(args.input_azimuth_deg, input_depression, 99)
        for k, (a, e) in enumerate(REQUESTS):
            blurred = [gaussian_filter(x, 1.5) for x in (generated[k], truth[k], at_input)]
            closer = pearson(blurred[0], blurred[1]) > pearson(blurred[0], blurred[2])
            scores.setdefault(f"d_az {a:+g}, d_el {e:+g}", []).append(bool(closer))
        rows.append((f"{name}: generated", [chip, *generated]))
        rows.append((f"{name}: truth", [chip, *truth]))
    return rows, scores, time.perf_counter() - begin


def draw_views(rows: list[tuple[str, list[np.ndarray]]], out: Path) -> None:
    """The figure: one labelled row per entry of ``rows``, one column per request (the input first)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    titles = ["input (17 deg)", *[f"d_az {a:+g}\nd_el {e:+g}" for a, e in REQUESTS]]
    size = (1.3 * len(titles), 1.4 * len(rows))
    fig, axes = plt.subplots(len(rows), len(titles), figsize=size, squeeze=False)
    for r, (label, images) in enumerate(rows):
        for c, image in enumerate(images):
            ax = axes[r, c]
            ax.imshow(image, cmap="gray", vmin=0.0, vmax=1.0)
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[c], fontsize=7)
            if c == 0:
                ax.set_ylabel(label, fontsize=6)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)


def write_record(args: argparse.Namespace, scores: dict[str, list[bool]], seconds: float, out: Path) -> None:
    """The scores as JSON beside the figure, and a line per request on stdout."""
    record = {"pipeline": str(args.pipeline), "classes": args.classes,
              "num_inference_steps": args.num_inference_steps, "seconds": round(seconds, 1),
              "device": "cuda" if torch.cuda.is_available() else "cpu", "closer_to_requested_pose": scores}
    out.with_suffix(".json").write_text(json.dumps(record, indent=2) + "\n")
    for request, wins in scores.items():
        print(f"{request}: closer to the requested pose's truth in {sum(wins)}/{len(wins)}")
    print(f"wrote {out} ({seconds:.1f} s)")


def main(argv: Sequence[str] | None = None) -> Path:
    args = parse_args(argv)
    rows, scores, seconds = generate_views(args)
    out = Path(args.out)
    draw_views(rows, out)
    write_record(args, scores, seconds, out)
    return out


if __name__ == "__main__":
    main()
