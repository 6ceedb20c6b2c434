"""Does a view turn the vehicle's front to the requested heading, or only its body's axis? (issue 35)

    python benchmarks/front_back.py --pipeline sar-zero123/sim-prior-rotated --out front_back.json
    python benchmarks/front_back.py --pipeline A --pipeline B --pairs_per_class 32 --out front_back.json

The evaluators' azimuth error counts a view turned by 180 deg as wrong, and their regressor reads the
heading from learned features, which a generated view may lack even where its pixels are right. This
benchmark asks the pixels: on the simulator's eight named vehicles (never in the prior's corpus), each
pair's input at 17 deg and a random azimuth, a request ``d_az`` uniform in [-180, 180), and the simulator's
truth at the requested heading, at the same heading turned by 180 deg (the flip), and at the input's
heading. With every image blurred (sigma 1.5 px), per row and pair:

- ``heading``: the view correlates better with the truth than with the flip (0.5: the front is a coin toss,
  as for any view whose body lies on the right axis but whose front is not drawn from the input);
- ``pose``: better with the truth than with the input's pose (0.5 for a generator that ignores d_az);
- ``corr_truth``: the Pearson correlation with the truth.

Rows: ``input copy`` (the floor), ``input turned`` (the input chip turned in the image plane by the request,
what ``spatial_pose="rotated_input"`` shows the UNet, at the simulator's ``rotation_sign`` -1),
``VAE round trip`` of the truth (the ceiling, through the first pipeline's VAE), then each pipeline (at each
``--heading_guidance_scales`` weight of guidance away from the flipped heading). If the
turned input scores high on ``heading`` and a model does not, the model loses the front that its hint held.
With ``--evaluators DIR``, each row also gets the evaluators' azimuth regressor's error on its views, overall
and split by whether the pixels got the heading right: whether the regressor reads what the pixels show.
Writes JSON (means, standard errors, and ``heading`` per |d_az| band) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from sar_zero123 import SIM_PRIOR, SARZero123Pipeline, resolve_pretrained
from sar_zero123.config import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling, signed_to_unit
from sar_zero123.evaluation.evaluators import load_evaluators
from sar_zero123.model.conditioning import embed_pose, rotate_condition_latents
from sar_zero123.sim import TARGET_CLASSES, make_target, render_chip

INPUT_DEPRESSION_DEG = 17.0
SIM_ROTATION_SIGN = -1  # the simulator's turn direction (docs/results/history/prior.md, section 6)
BANDS_DEG = ((0.0, 60.0), (60.0, 120.0), (120.0, 180.0))


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two images."""
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    return float((a * b).sum() / max(np.sqrt((a * a).sum() * (b * b).sum()), 1e-12))


def turn_images(images: np.ndarray, d_az_deg: Sequence[float], rotation_sign: int) -> np.ndarray:
    """Images ``(N, S, S)`` turned about their centre as the rotated-input condition turns latents."""
    pose = embed_pose(list(d_az_deg), [0.0] * len(d_az_deg))
    turned = rotate_condition_latents(torch.from_numpy(images)[:, None].float(), pose, rotation_sign)
    return turned[:, 0].numpy()


def draw_pairs(classes: Sequence[str], pairs_per_class: int, seed: int) -> list[tuple[str, float, float]]:
    """``(class, input azimuth, d_az)`` per pair, seeded: azimuth uniform in [0, 360), d_az in [-180, 180)."""
    rng = np.random.default_rng(seed)
    return [
        (name, float(rng.uniform(0.0, 360.0)), float(rng.uniform(-180.0, 180.0)))
        for name in classes
        for _ in range(pairs_per_class)
    ]


def score(views: np.ndarray, truth: np.ndarray, flip: np.ndarray, at_input: np.ndarray) -> dict[str, list]:
    """Per pair: heading right, pose right, correlation with the truth (all blurred, sigma 1.5 px)."""
    out: dict[str, list] = {"heading": [], "pose": [], "corr_truth": []}
    for v, t, f, a in zip(views, truth, flip, at_input):
        v, t, f, a = (gaussian_filter(x.astype(np.float64), 1.5) for x in (v, t, f, a))
        c_t = pearson(v, t)
        out["heading"].append(c_t > pearson(v, f))
        out["pose"].append(c_t > pearson(v, a))
        out["corr_truth"].append(c_t)
    return out


def summarise(per_pair: dict[str, list], d_az: Sequence[float]) -> dict[str, float]:
    """Means and standard errors, and ``heading`` per |d_az| band."""
    summary: dict[str, float] = {"n": len(d_az)}
    for key, values in per_pair.items():
        x = np.asarray(values, dtype=np.float64)
        summary[key] = float(x.mean())
        summary[f"{key}_se"] = float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else 0.0
    heading = np.asarray(per_pair["heading"], dtype=np.float64)
    magnitude = np.abs(np.asarray(d_az))
    for low, high in BANDS_DEG:
        members = (magnitude >= low) & (magnitude < high)
        if members.any():
            summary[f"heading_abs_d_az_{low:g}_{high:g}"] = float(heading[members].mean())
    return summary


def run(
    pipelines: Sequence[str],
    *,
    classes: Sequence[str] = TARGET_CLASSES,
    pairs_per_class: int = 16,
    num_inference_steps: int = 20,
    guidance_scale: float = 3.0,
    batch_size: int = 16,
    seed: int = 0,
    heading_guidance_scales: Sequence[float] = (0.0,),
    evaluators: str | None = None,
) -> dict:
    """Every row's scores on the same pairs; see the module docstring."""
    first = SARZero123Pipeline.from_pretrained(pipelines[0])
    scaling_file = resolve_pretrained(pipelines[0]) / SCALING_FILE
    scaling = DecibelScaling.from_dict(json.loads(scaling_file.read_text()))
    size = first.default_image_size
    pairs = draw_pairs(classes, pairs_per_class, seed)
    targets = {name: make_target(name) for name in classes}

    def render(k: int, name: str, azimuth: float, stream: int) -> np.ndarray:
        rng = np.random.default_rng([seed, k, stream])
        chip = render_chip(targets[name], azimuth % 360.0, INPUT_DEPRESSION_DEG, size, rng)
        return scaling.normalize(chip).astype(np.float32)

    inputs = np.stack([render(k, n, a, 0) for k, (n, a, _) in enumerate(pairs)])
    truth = np.stack([render(k, n, a + d, 1) for k, (n, a, d) in enumerate(pairs)])
    flip = np.stack([render(k, n, a + d + 180.0, 2) for k, (n, a, d) in enumerate(pairs)])
    at_input = np.stack([render(k, n, a, 3) for k, (n, a, _) in enumerate(pairs)])
    d_az = [d for _, _, d in pairs]
    target_azimuth = np.array([(a + d) % 360.0 for _, a, d in pairs])
    regressor = None if evaluators is None else load_evaluators(evaluators).regressor.eval()

    def scored(views: np.ndarray) -> dict[str, float]:
        per_pair = score(views, truth, flip, at_input)
        summary = summarise(per_pair, d_az)
        if regressor is not None:  # what the evaluators read from the same views
            with torch.no_grad():
                predicted = regressor.predict_azimuth_deg(torch.from_numpy(views)[:, None].float()).numpy()
            error = np.abs((predicted - target_azimuth + 180.0) % 360.0 - 180.0)
            right = np.asarray(per_pair["heading"], dtype=bool)
            summary["regressor_azimuth_error_deg"] = float(error.mean())
            summary["regressor_azimuth_error_deg_se"] = float(error.std(ddof=1) / np.sqrt(len(error)))
            summary["regressor_axis_error_deg"] = float(np.minimum(error, 180.0 - error).mean())
            for name, members in (("heading_right", right), ("heading_wrong", ~right)):
                if members.any():
                    summary[f"regressor_azimuth_error_deg_{name}"] = float(error[members].mean())
        return summary

    @torch.no_grad()
    def round_trip(images: np.ndarray) -> np.ndarray:
        signed = torch.from_numpy(images)[:, None] * 2.0 - 1.0
        latents = first.vae.encode(signed).latent_dist.mode()
        return signed_to_unit(first.vae.decode(latents).sample).clamp(0.0, 1.0)[:, 0].numpy()

    rows: dict[str, Callable[[], np.ndarray]] = {
        "input copy (floor)": lambda: inputs,
        "input turned": lambda: turn_images(inputs, d_az, SIM_ROTATION_SIGN),
        "VAE round trip (ceiling)": lambda: round_trip(truth),
    }
    results, seconds = {}, {}
    for name, make in rows.items():
        results[name] = scored(make())
    for path, heading in ((p, h) for p in pipelines for h in heading_guidance_scales):
        name = str(path) if heading == 0.0 else f"{path}, heading guidance {heading:g}"
        pipe = SARZero123Pipeline.from_pretrained(path)
        pipe.set_progress_bar_config(disable=True)
        begin, views = time.perf_counter(), []
        for start in range(0, len(pairs), batch_size):
            chunk = slice(start, start + batch_size)
            views.append(pipe(
                torch.from_numpy(inputs[chunk])[:, None], d_az=d_az[chunk], d_el=0.0,
                input_depression_deg=INPUT_DEPRESSION_DEG, num_inference_steps=num_inference_steps,
                guidance_scale=guidance_scale, heading_guidance_scale=heading,
                generator=[torch.Generator().manual_seed(seed + k) for k in range(start, start + batch_size)][
                    : len(d_az[chunk])
                ],
                output_type="np",
            ).images[..., 0])  # fmt: skip
        seconds[name] = time.perf_counter() - begin
        results[name] = scored(np.concatenate(views))
    return {
        "benchmark": "front_back (issue 35)",
        "pipelines": [str(p) for p in pipelines],
        "classes": list(classes),
        "pairs_per_class": pairs_per_class,
        "num_inference_steps": num_inference_steps,
        "guidance_scale": guidance_scale,
        "heading_guidance_scales": list(heading_guidance_scales),
        "evaluators": evaluators,
        "seed": seed,
        "device": f"CPU, {os.cpu_count()} cores, torch {torch.__version__}",
        "platform": platform.platform(),
        "generation_seconds": seconds,
        "rows": results,
    }


def format_table(record: dict) -> str:
    lines = [
        "| row | heading right | pose right | corr. with truth "
        "| heading right at abs(d_az) <60 / 60-120 / 120+ | regressor az. err. (deg): all / heading right |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name, r in record["rows"].items():
        keys = [f"heading_abs_d_az_{lo:g}_{hi:g}" for lo, hi in BANDS_DEG]
        bands = " / ".join(f"{r.get(key, float('nan')):.2f}" for key in keys)
        lines.append(
            f"| {name} | {r['heading']:.2f} ± {r['heading_se']:.2f} | {r['pose']:.2f} ± {r['pose_se']:.2f} | "
            f"{r['corr_truth']:.3f} ± {r['corr_truth_se']:.3f} | {bands} | "
            f"{r.get('regressor_azimuth_error_deg', float('nan')):.1f} / "
            f"{r.get('regressor_azimuth_error_deg_heading_right', float('nan')):.1f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", action="append", help="pipeline folder or bundled name (repeatable)")
    parser.add_argument("--classes", nargs="+", default=list(TARGET_CLASSES), help="simulator vehicles")
    parser.add_argument("--pairs_per_class", type=int, default=16, help="random pairs per vehicle")
    parser.add_argument("--num_inference_steps", type=int, default=20, help="DDIM steps")
    parser.add_argument("--guidance_scale", type=float, default=3.0, help="classifier-free guidance")
    parser.add_argument("--batch_size", type=int, default=16, help="views per pipeline call")
    parser.add_argument("--seed", type=int, default=0, help="pairs, clutter and sampling seed")
    parser.add_argument("--heading_guidance_scales", nargs="+", type=float, default=[0.0],
                        help="each pipeline at each weight of guidance away from the flipped heading")
    parser.add_argument("--evaluators", default=None,
                        help="evaluators folder: also the azimuth regressor's error on every row's views")
    parser.add_argument("--out", default="front_back.json", help="output JSON")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.classes) - set(TARGET_CLASSES))
    if unknown:
        raise ValueError(f"classes: {unknown} are not simulator classes; choose from {list(TARGET_CLASSES)}")
    if args.pairs_per_class < 2:
        raise ValueError(f"pairs_per_class must be >= 2, got {args.pairs_per_class}")
    record = run(
        args.pipeline or [SIM_PRIOR], classes=args.classes, pairs_per_class=args.pairs_per_class,
        num_inference_steps=args.num_inference_steps, guidance_scale=args.guidance_scale,
        batch_size=args.batch_size, seed=args.seed, heading_guidance_scales=args.heading_guidance_scales,
        evaluators=args.evaluators,
    )  # fmt: skip
    write_json_atomic(record, Path(args.out))
    print(format_table(record))
    return record


if __name__ == "__main__":
    main()
