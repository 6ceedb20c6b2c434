"""Real MSTAR, 17 -> 30 deg: are generated views nearer the real 30 deg chip than a 17 deg one? (issue 61)

    python benchmarks/proxy_mstar_depression.py --mstar ../shared/data/mstar \
        --eoc1 ../shared/data/mstar_eoc1 --out proxy_mstar_depression.json \
        [--proxy_pipeline sar-zero123/sim-prior-identity]

For the serials of EOC-1's test set (2S1, BRDM2, T72, ZSU234: their 30 deg chips in ``--eoc1``), each pair's
input is a 17 deg chip of ``--mstar`` (a 64 px centre crop at the native 0.2 m spacing), the request is
``d_el = +13`` deg at the same azimuth, and two real references are kept: the same serial's 30 deg chip
nearest in azimuth, and its other 17 deg chip nearest in azimuth (a second look at the input's pose). A view
*wins* when its blurred correlation (sigma 1.5 px) with the 30 deg chip exceeds that with the 17 deg one.
Pairs whose references lie more than ``--max_azimuth_gap`` deg from the input's azimuth are left out.

Rows: the input copy; the 30 deg chip (ceiling, 100 % by construction); the simulator proxy alone (the
bank vehicle fitted to the input at its header pose, rendered at 30 deg); the bundled prior from noise with
no guidance, with its recorded sampler without the input's azimuth, and with it (from the proxy, at its
recorded noise level and others); with ``--proxy_pipeline``, a proxy-conditioned prior on the same fits.
Writes JSON.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from _common import cpu_device, device_record, parallel_map, script_parser
from threadpoolctl import threadpool_limits

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling, load_chip
from sar_zero123.model.proxy import PROXY_FIELDS, draft_target_views, proxy_bank
from sar_zero123.model.spatial_pose import takes_proxy
from sar_zero123.sim.proxy import blurred_correlation

CLASSES = ("2S1", "BRDM2", "T72", "ZSU234")
INPUT_DEPRESSION_DEG, TARGET_DEPRESSION_DEG = 17.0, 30.0
SIZE = 64


def _rows(index: Path) -> list[dict[str, str]]:
    with open(index, newline="") as handle:
        return list(csv.DictReader(handle))


def _gap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def draw_pairs(mstar: Path, eoc1: Path, per_class: int, max_gap: float, seed: int) -> list[dict]:
    """``per_class`` pairs per class: input (17 deg), the 30 deg and second 17 deg references."""
    high = [r for r in _rows(eoc1 / "index.csv") if float(r["depression_deg"]) == TARGET_DEPRESSION_DEG]
    low = [r for r in _rows(mstar / "index.csv") if float(r["depression_deg"]) == INPUT_DEPRESSION_DEG]
    rng = np.random.default_rng(seed)
    pairs = []
    for name in CLASSES:
        serials = {r["serial"] for r in high if r["target_class"] == name}
        inputs = [r for r in low if r["target_class"] == name and r["serial"] in serials]
        candidates = []
        for r in inputs:
            azimuth = float(r["azimuth_deg"])
            same_high = [h for h in high if h["serial"] == r["serial"] and h["target_class"] == name]
            same_low = [q for q in inputs if q["serial"] == r["serial"] and q["path"] != r["path"]]
            if not same_high or not same_low:
                continue
            at_30 = min(same_high, key=lambda h: _gap(float(h["azimuth_deg"]), azimuth))
            at_17 = min(same_low, key=lambda q: _gap(float(q["azimuth_deg"]), azimuth))
            gaps = (_gap(float(at_30["azimuth_deg"]), azimuth), _gap(float(at_17["azimuth_deg"]), azimuth))
            if max(gaps) <= max_gap:
                candidates.append({"class": name, "input": r, "at_30": at_30, "at_17": at_17})
        chosen = rng.choice(len(candidates), size=min(per_class, len(candidates)), replace=False)
        pairs += [candidates[k] for k in sorted(chosen)]
    return pairs


def _draft(args: tuple) -> np.ndarray:
    """One input's proxy at its own pose, at 30 deg, and at 30 deg with the heading flipped ``(3, S, S)``
    (a worker process; one fit; its bank is built once per process)."""
    proxy, image, azimuth = args
    threadpool_limits(limits=1)
    one = torch.tensor
    d_el = TARGET_DEPRESSION_DEG - INPUT_DEPRESSION_DEG
    drafts, _ = draft_target_views(
        torch.from_numpy(image)[None, None].expand(3, 1, *image.shape), one([azimuth] * 3),
        one([INPUT_DEPRESSION_DEG] * 3), one([0.0, 0.0, 180.0]), one([0.0, d_el, d_el]), proxy,
    )  # fmt: skip
    return drafts[:, 0].numpy()


def _consensus(args: tuple) -> np.ndarray:
    """One input's consensus proxy at 30 deg ``(S, S)``: the renders of its ``k`` best-fitting bank vehicles
    (each shifted onto the chip as fitted), averaged in normalised dB with weights
    ``exp((score - best) / temperature)`` (a worker process)."""
    proxy, image, azimuth, k, temperature = args
    threadpool_limits(limits=1)
    bank = proxy_bank(*(proxy[key] for key in PROXY_FIELDS[:6]))
    scaling = DecibelScaling(min_db=float(proxy["min_db"]), max_db=float(proxy["max_db"]))
    scores, shifts = bank.scores_and_shifts(image, azimuth, INPUT_DEPRESSION_DEG)
    best = np.argsort(-scores, kind="stable")[:k]
    weights = np.exp((scores[best] - scores[best[0]]) / temperature)
    size = image.shape[-1]
    renders = [
        scaling.normalize(bank.render(int(v), azimuth, TARGET_DEPRESSION_DEG, size, tuple(shifts[v])))
        for v in best
    ]
    return np.einsum("k,khw->hw", weights / weights.sum(), np.stack(renders)).astype(np.float32)


def wins(views: np.ndarray, at_30: np.ndarray, at_17: np.ndarray) -> np.ndarray:
    """Per view: blurred correlation with the 30 deg chip above that with the 17 deg one."""
    scores = [blurred_correlation(v, np.stack([h, q]), 1.5) for v, h, q in zip(views, at_30, at_17)]
    return np.array([high > low for high, low in scores])


def run(
    mstar: Path,
    eoc1: Path,
    per_class: int = 64,
    max_gap: float = 3.0,
    seed: int = 0,
    workers: int = 2,
    max_shifts_px: Sequence[int] = (0,),
    proxy_pipeline: str | None = None,
    consensus: tuple[int, float] | None = None,
    retrieval: tuple[str, Sequence[int]] | None = None,
) -> dict:
    """Every row's share of views nearer the 30 deg chip, on the same pairs; see the module docstring."""
    pipe = SARZero123Pipeline.from_pretrained(SIM_PRIOR_ROTATED)
    pipe.set_progress_bar_config(disable=True)
    scaling = DecibelScaling.from_file(resolve_pretrained(SIM_PRIOR_ROTATED) / SCALING_FILE)
    pairs = draw_pairs(mstar, eoc1, per_class, max_gap, seed)

    def chip(root: Path, row: dict) -> np.ndarray:
        return scaling.normalize(load_chip(root / row["path"], SIZE, crop_size=SIZE)).astype(np.float32)

    inputs = np.stack([chip(mstar, p["input"]) for p in pairs])
    at_30 = np.stack([chip(eoc1, p["at_30"]) for p in pairs])
    at_17 = np.stack([chip(mstar, p["at_17"]) for p in pairs])
    azimuths = [float(p["input"]["azimuth_deg"]) for p in pairs]
    classes = np.array([p["class"] for p in pairs])
    rows: dict[str, dict] = {}

    def add(name: str, views: np.ndarray, seconds: float) -> None:
        won = wins(views, at_30, at_17).astype(np.float64)
        se = float(won.std(ddof=1) / np.sqrt(len(won)))
        rows[name] = {"n": len(won), "nearer_30": float(won.mean()), "nearer_30_se": se, "seconds": seconds}
        rows[name] |= {f"nearer_30_{c}": float(won[classes == c].mean()) for c in CLASSES}
        print(f"{name}: {won.mean():.1%} ± {se:.1%} ({seconds:.0f} s)", flush=True)

    add("input copy (unturned, keeps identity)", inputs, 0.0)
    add("the 30 deg chip (ceiling)", at_30, 0.0)

    def fit(proxy: dict) -> np.ndarray:
        """Every input's proxy at 30 deg, by the pipeline's own code, in ``workers`` processes."""
        return np.stack(parallel_map(_draft, [(proxy, im, a) for im, a in zip(inputs, azimuths)], workers))

    drafts: dict[int, np.ndarray] = {}
    recorded_shift = int(pipe.config.proxy.get("max_shift_px", 0))
    exhaustive = {**pipe.config.proxy, "shortlist": 0, "retrieval": None}
    # the pipeline's own fit (its recorded proxy); the exhaustive one beside a shortlist or a consensus
    base = exhaustive if retrieval is not None or consensus is not None else pipe.config.proxy
    for shift in sorted({recorded_shift, *max_shifts_px}):
        begin = time.perf_counter()
        drafts[shift] = fit({**base, "max_shift_px": shift})
        name = f"proxy alone (bank {pipe.config.proxy['num_vehicles']}, shifts up to {shift} px)"
        add(name, drafts[shift][:, 1], time.perf_counter() - begin)
    if retrieval is not None:  # the proxy alone only: the exhaustive fit against the learned shortlist
        name, sizes = retrieval
        for shift in sorted(drafts):
            best = f"proxy alone (bank {pipe.config.proxy['num_vehicles']}, shifts up to {shift} px)"
            for k in sizes:
                begin = time.perf_counter()
                learned = fit({**exhaustive, "max_shift_px": shift, "shortlist": int(k), "retrieval": name})
                row = f"proxy alone, learned shortlist of {k} (shifts up to {shift} px)"
                add(row, learned[:, 1], time.perf_counter() - begin)
                won = wins(learned[:, 1], at_30, at_17).astype(float)
                diff = won - wins(drafts[shift][:, 1], at_30, at_17)
                se = float(diff.std(ddof=1) / np.sqrt(len(diff)))
                same = np.all(learned[:, 0] == drafts[shift][:, 0], axis=(1, 2))
                rows[row] |= {"paired_difference_from_exhaustive": float(diff.mean()),
                              "paired_difference_se": se,
                              "same_fit_as_exhaustive": float(same.mean())}  # fmt: skip
                print(f"paired: {row} - {best}: {diff.mean():+.1%} ± {se:.1%}; the same vehicle in "
                      f"{rows[row]['same_fit_as_exhaustive']:.0%}", flush=True)  # fmt: skip
        return {"benchmark": "proxy_mstar_depression (issue 61: learned shortlist)", "retrieval": name,
                "proxy": exhaustive, "per_class": per_class, "seed": seed, "rows": rows,
                "device": cpu_device()}  # fmt: skip
    if consensus is not None:  # the proxy alone only: the best fit against the consensus of the k best
        k, temperature = consensus
        shift = max(drafts)
        begin = time.perf_counter()
        jobs = [({**pipe.config.proxy, "max_shift_px": shift}, image, a, k, temperature)
                for image, a in zip(inputs, azimuths)]  # fmt: skip
        mean = np.stack(parallel_map(_consensus, jobs, workers))
        name = f"proxy alone, consensus of the {k} best (temperature {temperature:g}, shifts <= {shift} px)"
        add(name, mean, time.perf_counter() - begin)
        best = f"proxy alone (bank {pipe.config.proxy['num_vehicles']}, shifts up to {shift} px)"
        diff = wins(mean, at_30, at_17).astype(float) - wins(drafts[shift][:, 1], at_30, at_17).astype(float)
        rows[name]["paired_difference_from_best_fit"] = float(diff.mean())
        se = float(diff.std(ddof=1) / np.sqrt(len(diff)))
        rows[name]["paired_difference_se"] = se
        print(f"paired: {name} - {best}: {diff.mean():+.1%} ± {se:.1%}")
        return {"benchmark": "proxy_mstar_depression (issue 61: consensus proxy)",
                "consensus": [k, temperature], "proxy": pipe.config.proxy, "per_class": per_class,
                "seed": seed, "rows": rows,
                "device": cpu_device()}  # fmt: skip
    views_at_three_poses = drafts[recorded_shift]
    proxies = views_at_three_poses[:, 1]

    def sample(from_proxy: bool = False, model=pipe, **kwargs) -> tuple[np.ndarray, float]:
        """The pipeline's views of every pair; ``from_proxy``: the drafts above, as its proxy start; a
        proxy-conditioned ``model`` takes the fitted proxy at the three poses (``proxy_views``)."""
        begin, views = time.perf_counter(), []
        for s in range(0, len(pairs), 32):
            chunk = slice(s, s + 32)
            n = len(inputs[chunk])
            start = {"start_image": torch.from_numpy(proxies[chunk])[:, None]} if from_proxy else {}
            if takes_proxy(model.pose_projection):
                start["proxy_views"] = torch.from_numpy(views_at_three_poses[chunk])
            views.append(model(
                torch.from_numpy(inputs[chunk])[:, None], d_az=0.0,
                d_el=TARGET_DEPRESSION_DEG - INPUT_DEPRESSION_DEG, input_depression_deg=INPUT_DEPRESSION_DEG,
                output_type="np", **kwargs, **start,
                generator=[torch.Generator().manual_seed(seed + k) for k in range(s, s + n)],
            ).images[..., 0])  # fmt: skip
        return np.concatenate(views), time.perf_counter() - begin

    add("bundled prior, library sampler (50 steps from noise)",
        *sample(num_inference_steps=50, strength=1.0, heading_guidance_scale=0.0, start_from="input"))
    add("bundled prior, its recorded sampler, no input azimuth (from noise, heading guidance)", *sample())
    # the drafts above are the pipeline's own proxy starts (draft_target_views), made in parallel; a call
    # given start_image takes the strength it is given, so the recorded proxy_strength is passed here
    recorded = pipe.config.sampler["proxy_strength"]
    add(f"bundled prior, its recorded sampler, input azimuth given (from the proxy noised to {recorded:.0%})",
        *sample(from_proxy=True, strength=recorded))
    for strength in sorted({0.3, 0.5, 0.7} - {recorded}):
        name = f"bundled prior, from the proxy noised to {strength:.0%}"
        add(name, *sample(from_proxy=True, strength=strength))
    if proxy_pipeline is not None:  # a proxy-conditioned prior on the same pairs and fits
        other = SARZero123Pipeline.from_pretrained(proxy_pipeline)
        other.set_progress_bar_config(disable=True)
        own = other.config.sampler["proxy_strength"]
        add(f"proxy prior, its recorded sampler, input azimuth given (from the proxy noised to {own:.0%})",
            *sample(from_proxy=True, model=other, strength=own))  # fmt: skip
        add("proxy prior, from noise", *sample(model=other, strength=1.0))
    for shift in sorted(set(drafts) - {recorded_shift}):
        proxies = drafts[shift][:, 1]
        name = f"bundled prior, from the proxy fitted with shifts up to {shift} px, noised to {recorded:.0%}"
        add(name, *sample(from_proxy=True, strength=recorded))
    return {"benchmark": "proxy_mstar_depression (issue 61)", "pipeline": SIM_PRIOR_ROTATED,
            "proxy_pipeline": proxy_pipeline, "sampler": pipe.config.sampler, "proxy": pipe.config.proxy,
            "per_class": per_class, "max_azimuth_gap_deg": max_gap, "seed": seed, **device_record(),
            "rows": rows}  # fmt: skip


def main(argv: Sequence[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--mstar", required=True, help="MSTAR folder with index.csv (17 deg inputs)")
    parser.add_argument("--eoc1", required=True, help="EOC-1 folder with index.csv (the 30 deg chips)")
    parser.add_argument("--per_class", type=int, default=64, help="pairs per class (4 classes)")
    parser.add_argument("--max_azimuth_gap", type=float, default=3.0, help="references' largest azimuth gap")
    parser.add_argument("--seed", type=int, default=0, help="pair draw and sampling seed")
    parser.add_argument("--workers", type=int, default=2, help="processes for the proxy fits")
    parser.add_argument("--max_shifts_px", nargs="*", type=int, default=[0],
                        help="also fit the proxy with shifts up to each of these (pixels)")
    parser.add_argument("--proxy_pipeline", default=None,
                        help="also a spatial_pose='proxy' pipeline (folder or name) on the same pairs")
    parser.add_argument("--consensus", nargs=2, type=float, default=None, metavar=("K", "TEMPERATURE"),
                        help="only the proxies alone: the best fit and the weighted mean of the K best fits")
    parser.add_argument("--retrieval", nargs="+", default=None, metavar="NAME_THEN_SIZES",
                        help="only the proxy alone: the exhaustive fit against a learned shortlist (a name "
                        "or folder) of each size")  # fmt: skip
    parser.add_argument("--out", default="proxy_mstar_depression.json", help="output JSON")
    args = parser.parse_args(argv)
    for name in ("mstar", "eoc1"):
        if not (Path(getattr(args, name)) / "index.csv").is_file():
            raise FileNotFoundError(f"--{name}: no index.csv in {getattr(args, name)!r}")
    record = run(
        Path(args.mstar), Path(args.eoc1), args.per_class, args.max_azimuth_gap, args.seed, args.workers,
        args.max_shifts_px, args.proxy_pipeline,
        None if args.consensus is None else (int(args.consensus[0]), float(args.consensus[1])),
        None if args.retrieval is None else (args.retrieval[0], [int(k) for k in args.retrieval[1:]]),
    )  # fmt: skip
    write_json_atomic(record, Path(args.out))
    return record


if __name__ == "__main__":
    main()
