"""The proxy-conditioned prior on unseen vehicles: what the generator adds to its simulator proxy (issue 61)

    python benchmarks/proxy_prior_views.py --pipeline PROXY_PRIOR --out proxy_prior_views.json

The pairs, rows and readings of ``benchmarks/proxy_views.py`` (the eight named simulator vehicles, 17 deg
inputs, ``60 <= |d_az| <= 180``, template-matched azimuth, front/back and identity), for a pipeline whose
UNet takes the proxy pair (``spatial_pose="proxy"``). Each input's proxy is fitted once, by the pipeline's
own code (:func:`~sar_zero123.model.proxy.draft_target_views`, in ``--workers`` processes), rendered at the
input's pose, at the request and at the flipped heading, and handed to the pipeline as ``proxy_views``: the
same views its plain call fits and renders itself. Rows, on the same pairs:

- the floor (input copy), the ceiling (the true view, another speckle draw) and the proxy alone;
- ``--baseline`` (``sim-prior-rotated``) with its recorded sampler and the input's azimuth (its best row);
- the proxy prior with its recorded sampler (its plain call given the input's azimuth), from noise at each
  ``--headings`` weight of heading guidance and without it, and from the proxy at other strengths;
- both with an oracle proxy (the true vehicle at the three poses, another clutter draw): where the
  remaining error sits.

Writes JSON (per row: template azimuth error and its standard error, gap closed, front/back right,
identity kept, seconds; the best proxy-prior row's paired error differences from the baseline and from the
proxy alone; with ``--compare``, each row's identity where the fitted proxy keeps the vehicle and where it
does not, :func:`~sar_zero123.evaluation.template.identity_by_proxy`) and prints a table. ``--consensus``,
``--refine``, ``--retrieval``, ``--compare`` and ``--steps`` each run only their own rows (their
``--help``); ``--fits`` keeps the fits for a re-run.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from _common import cpu_device, device_record, parallel_map, script_parser
from threadpoolctl import threadpool_limits

from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline, resolve_pretrained
from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.domain import to_decibels
from sar_zero123.evaluation.template import identity_by_proxy, summarise_readings, turned_and_kept
from sar_zero123.model.pipeline import SAMPLER_DEFAULTS
from sar_zero123.model.proxy import PROXY_FIELDS, check_proxy_settings, draft_target_views, proxy_bank
from sar_zero123.sim import render_chip
from sar_zero123.sim.primitives import Box, HorizontalCylinder, VerticalCylinder, Wedge
from sar_zero123.sim.proxy import blurred_correlation
from sar_zero123.sim.targets import Target

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for `benchmarks`
from benchmarks.proxy_views import INPUT_DEPRESSION_DEG, SimulatedPairs, format_table, print_row  # noqa: E402


def _fitted(args: tuple) -> np.ndarray:
    """One input's proxy at its pose, at the request and at the flipped heading ``(3, S, S)`` (one fit)."""
    proxy, image, azimuth, d_az = args
    threadpool_limits(limits=1)  # one BLAS thread per process
    one = torch.tensor
    drafts, _ = draft_target_views(
        torch.from_numpy(image)[None, None].expand(3, 1, *image.shape), one([azimuth] * 3),
        one([INPUT_DEPRESSION_DEG] * 3), one([0.0, d_az, d_az + 180.0]), one([0.0] * 3), proxy,
    )  # fmt: skip
    return drafts[:, 0].numpy()


def fitted_views(
    proxy: dict, images: np.ndarray, azimuths: Sequence[float], d_az: Sequence[float], workers: int
) -> np.ndarray:
    """Every input's fitted proxy at the three poses ``(N, 3, S, S)``, in ``workers`` processes."""
    jobs = [(proxy, im, float(a), float(d)) for im, a, d in zip(images, azimuths, d_az)]
    return np.stack(parallel_map(_fitted, jobs, workers))


def paired_differences(readings: dict, pairs_of_rows: Sequence[tuple[str, str]]) -> dict[str, dict]:
    """Each ``(first, second)`` row pair's template azimuth error differenced on the same pairs: mean and
    standard error (negative: the first is nearer the request); printed as it goes."""
    comparisons = {}
    for first, second in pairs_of_rows:
        diff = readings[first].azimuth_error_deg - readings[second].azimuth_error_deg
        se = float(diff.std(ddof=1) / np.sqrt(len(diff)))
        comparisons[f"{first} - {second}"] = {"mean_deg": float(diff.mean()), "se_deg": se}
        print(f"paired: {first} - {second}: {diff.mean():+.1f} ± {se:.1f} deg")
    return comparisons


def _consensus(args: tuple) -> np.ndarray:
    """One input's consensus proxy at the three poses ``(3, S, S)``: its ``k`` best-fitting bank vehicles'
    renders, averaged in normalised dB with weights ``exp((score - best) / temperature)``."""
    proxy, image, azimuth, d_az, k, temperature = args
    threadpool_limits(limits=1)
    bank = proxy_bank(*(proxy[key] for key in PROXY_FIELDS[:6]))
    scaling = DecibelScaling(min_db=float(proxy["min_db"]), max_db=float(proxy["max_db"]))
    scores = bank.scores(image, azimuth, INPUT_DEPRESSION_DEG)
    best = np.argsort(-scores, kind="stable")[:k]
    weights = np.exp((scores[best] - scores[best[0]]) / temperature)
    weights /= weights.sum()
    size = image.shape[-1]
    return np.stack([
        np.einsum("k,khw->hw", weights, np.stack(
            [scaling.normalize(bank.render(int(v), azimuth + turn, INPUT_DEPRESSION_DEG, size)) for v in best]
        ))
        for turn in (0.0, d_az, d_az + 180.0)
    ]).astype(np.float32)  # fmt: skip


def consensus_views(
    proxy: dict, images: np.ndarray, azimuths: Sequence[float], d_az: Sequence[float], k: int,
    temperature: float, workers: int,
) -> np.ndarray:  # fmt: skip
    """Every input's consensus proxy (:func:`_consensus`) at the three poses ``(N, 3, S, S)``."""
    jobs = [(proxy, im, float(a), float(d), k, temperature) for im, a, d in zip(images, azimuths, d_az)]
    return np.stack(parallel_map(_consensus, jobs, workers))


def stretched(target: Target, length_scale: float, width_scale: float) -> Target:
    """``target`` stretched by ``length_scale`` along its length (``u``) and ``width_scale`` across it
    (``v``): scatterer positions and solids alike (a cylinder's radius by the mean of the two; a yawed solid's
    extents along its own axes, a refinement's approximation)."""

    def solid(p):
        fields = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
        fields["center_u"] *= length_scale
        fields["center_v"] *= width_scale
        if isinstance(p, Box | Wedge):
            fields["length"] *= length_scale
            fields["width"] *= width_scale
        elif isinstance(p, VerticalCylinder):
            fields["radius"] *= float(np.sqrt(length_scale * width_scale))
        elif isinstance(p, HorizontalCylinder):
            fields["length"] *= length_scale
        return type(p)(**fields)

    position = target.scatterers.position * np.array([length_scale, width_scale, 1.0])
    return dataclasses.replace(
        target, primitives=tuple(solid(p) for p in target.primitives),
        scatterers=dataclasses.replace(target.scatterers, position=position),
        radius_m=target.radius_m * max(length_scale, width_scale),
    )  # fmt: skip


def _refined(args: tuple) -> np.ndarray:
    """One input's proxies at the three poses ``(3, 3, S, S)`` (best fit; refined; refined among the k
    best): a stretch of a fitted vehicle replaces it where it correlates better with the input."""
    proxy, image, azimuth, d_az, k, factors = args
    threadpool_limits(limits=1)
    bank = proxy_bank(*(proxy[key] for key in PROXY_FIELDS[:6]))
    scaling = DecibelScaling(min_db=float(proxy["min_db"]), max_db=float(proxy["max_db"]))
    size = image.shape[-1]

    def render(target: Target, turn: float) -> np.ndarray:
        rng = np.random.default_rng(bank.render_seed)
        return render_chip(target, (azimuth + turn) % 360.0, INPUT_DEPRESSION_DEG, size, rng)

    scores = bank.scores(image, azimuth, INPUT_DEPRESSION_DEG)
    order = np.argsort(-scores, kind="stable")[:k]
    best = best_first = (scores[order[0]], bank.target(int(order[0])))
    for rank, index in enumerate(order):
        vehicle = bank.target(int(index))
        candidates = [stretched(vehicle, a, b) for a in factors for b in factors if (a, b) != (1, 1)]
        fit = blurred_correlation(image, np.stack([to_decibels(render(c, 0.0)) for c in candidates]),
                                  bank.blur_sigma_px)  # fmt: skip
        if fit.max() > best[0]:
            best = (fit.max(), candidates[int(np.argmax(fit))])
        if rank == 0:
            best_first = best
    vehicles = (bank.target(int(order[0])), best_first[1], best[1])
    return np.stack([
        np.stack([scaling.normalize(render(v, turn)) for turn in (0.0, d_az, d_az + 180.0)]) for v in vehicles
    ]).astype(np.float32)  # fmt: skip


def refined_views(
    proxy: dict, images: np.ndarray, azimuths: Sequence[float], d_az: Sequence[float], k: int,
    factors: Sequence[float], workers: int,
) -> np.ndarray:  # fmt: skip
    """Every input's proxies (:func:`_refined`) ``(3, N, 3, S, S)``: best fit, refined, refined among k."""
    jobs = [(proxy, im, float(a), float(d), k, tuple(factors)) for im, a, d in zip(images, azimuths, d_az)]
    return np.stack(parallel_map(_refined, jobs, workers)).transpose(1, 0, 2, 3, 4)


def _fit_seconds(proxy: dict, sim: SimulatedPairs, chips: int) -> float:
    """Median seconds of one fit and one render (one request) on one thread, over the first ``chips`` inputs,
    after a first call that builds the bank and any learned shortlist."""
    one = torch.tensor
    times = []
    with threadpool_limits(limits=1):
        for k in range(-1, chips):
            image = sim.inputs[k] if k >= 0 else np.flip(sim.inputs[0]).copy()  # the first: a warm-up
            begin = time.perf_counter()
            draft_target_views(
                torch.from_numpy(image)[None, None], one([sim.input_azimuth[k]]), one([INPUT_DEPRESSION_DEG]),
                one([sim.d_az[k]]), one([0.0]), proxy,
            )  # fmt: skip
            times.append(time.perf_counter() - begin)
    return float(np.median(times[1:]))


def run(
    pipeline: str, *, baseline: str = SIM_PRIOR_ROTATED, pairs_per_class: int = 32, batch_size: int = 32,
    seed: int = 0, workers: int = 2, headings: Sequence[float] = (1.5, 3.0), fits: str | None = None,
    steps_sweep: Sequence[int] = (), shortlist: int | None = None, bank_size: int | None = None,
    consensus: tuple[int, float] | None = None, refine: tuple[int, Sequence[float]] | None = None,
    retrieval: tuple[str, Sequence[int], int] | None = None, compare: Sequence[str] = (),
) -> dict:  # fmt: skip
    """Every row's template readings on the same pairs; see the module docstring."""
    scaling = DecibelScaling.from_dict(json.loads((resolve_pretrained(pipeline) / SCALING_FILE).read_text()))
    pipe = SARZero123Pipeline.from_pretrained(pipeline)
    pipe.set_progress_bar_config(disable=True)
    base = SARZero123Pipeline.from_pretrained(baseline)
    base.set_progress_bar_config(disable=True)
    sim = SimulatedPairs(pipe.default_image_size, scaling, pairs_per_class, seed)
    rows: dict[str, dict] = {}
    floor, ceiling = sim.read(sim.inputs), sim.read(sim.truth)

    readings = {}

    def add(name: str, views: np.ndarray, seconds: float) -> None:
        readings[name] = sim.read(views)
        rows[name] = summarise_readings(readings[name], floor, ceiling) | {"seconds": seconds}
        print_row(name, rows[name])

    add("input copy (unturned, keeps identity)", sim.inputs, 0.0)
    add("true view, another speckle draw (ceiling)", sim.truth, 0.0)
    proxy = check_proxy_settings(pipe.config.proxy)
    if bank_size is not None:  # another bank than the pipeline's (its first bank_size vehicles)
        proxy = check_proxy_settings({**proxy, "num_vehicles": bank_size})
    if shortlist is not None:  # the fits made in two stages (sar_zero123.sim.proxy.ProxyBank's shortlist)
        proxy = check_proxy_settings({**proxy, "shortlist": shortlist})
    if retrieval is not None:  # the exhaustive fit, whatever the pipeline records
        proxy = check_proxy_settings({**proxy, "shortlist": 0, "retrieval": None})
    key = json.dumps({"proxy": proxy, "pairs_per_class": pairs_per_class, "seed": seed}, sort_keys=True)
    cached = None if fits is None or not Path(fits).is_file() else np.load(fits)
    if cached is not None and str(cached["key"]) == key:  # the same pairs and bank: the same fits
        fitted, fit_seconds = cached["views"], float(cached["seconds"])
    else:
        begin = time.perf_counter()
        fitted = fitted_views(proxy, sim.inputs, sim.input_azimuth, sim.d_az, workers)
        fit_seconds = time.perf_counter() - begin
        if fits is not None:
            np.savez(fits, views=fitted, seconds=fit_seconds, key=key)
    alone_row = f"proxy alone (bank {proxy['num_vehicles']})"
    add(alone_row, fitted[:, 1], fit_seconds)
    oracle = np.stack([
        np.stack([sim.render(v, a + turn, (seed, k, 2 + j)) for j, turn in enumerate((0.0, d, d + 180.0))])
        for k, (v, a, d) in enumerate(sim.pairs)
    ])  # fmt: skip
    recorded = {**SAMPLER_DEFAULTS, **(pipe.config.sampler or {})}
    steps, heading = int(recorded["num_inference_steps"]), float(recorded["heading_guidance_scale"])
    proxy_strength = float(recorded["proxy_strength"] or recorded["strength"])
    # the baseline's own recorded sampler (sim-prior-rotated: from its proxy noised to 30 %, heading 1.5)
    base_recorded = {**SAMPLER_DEFAULTS, **(base.config.sampler or {})}
    base_strength = float(base_recorded["proxy_strength"] or base_recorded["strength"])
    base_heading = float(base_recorded["heading_guidance_scale"])

    def sample(model, views, start, strength, heading_scale, num_steps=None) -> tuple[np.ndarray, float]:
        begin, out = time.perf_counter(), []
        for s in range(0, len(sim.pairs), batch_size):
            chunk = slice(s, s + batch_size)
            n = len(sim.d_az[chunk])
            extra = {} if views is None else {"proxy_views": torch.from_numpy(views[chunk])}
            out.append(model(
                torch.from_numpy(sim.inputs[chunk])[:, None], d_az=sim.d_az[chunk], d_el=0.0,
                input_depression_deg=INPUT_DEPRESSION_DEG, num_inference_steps=num_steps or steps,
                guidance_scale=float(recorded["guidance_scale"]), heading_guidance_scale=heading_scale,
                strength=strength,
                start_image=None if start is None else torch.from_numpy(start[chunk])[:, None],
                generator=[torch.Generator().manual_seed(seed + k) for k in range(s, s + n)],
                output_type="np", **extra,
            ).images[..., 0])  # fmt: skip
        return np.concatenate(out), time.perf_counter() - begin

    start = "from noise" if proxy_strength >= 1.0 else f"from the proxy at {proxy_strength:g}"
    if compare:  # each pipeline's plain call and its perfect proxy from noise, paired with the first
        pairs_of_rows, shares = [], {}
        for number, name in enumerate([pipeline, *compare]):
            model = pipe if number == 0 else SARZero123Pipeline.from_pretrained(name)
            model.set_progress_bar_config(disable=True)
            own = {**SAMPLER_DEFAULTS, **(model.config.sampler or {})}
            own_strength = float(own["proxy_strength"] or own["strength"])
            own_heading = float(own["heading_guidance_scale"])
            plain, perfect = f"{name}, its plain call (fitted proxy)", f"{name}, perfect proxy, from noise"
            add(plain, *sample(model, fitted, fitted[:, 1], own_strength, own_heading))
            add(f"{name}, fitted proxy, from noise", *sample(model, fitted, None, 1.0, own_heading))
            add(perfect, *sample(model, oracle, None, 1.0, own_heading))
            add(f"{name}, perfect proxy, its plain call",
                *sample(model, oracle, oracle[:, 1], own_strength, own_heading))
            if number:
                pairs_of_rows += [(plain, f"{pipeline}, its plain call (fitted proxy)"),
                                  (perfect, f"{pipeline}, perfect proxy, from noise")]  # fmt: skip
        comparisons = paired_differences(readings, pairs_of_rows)
        per_view = {"identity_kept": lambda r: r.identity_kept,
                    "turned_and_kept": lambda r: turned_and_kept(r.azimuth_error_deg, r.identity_kept)}
        for first, second in pairs_of_rows:  # the shares' paired differences on the same pairs
            for share, values in per_view.items():
                diff = values(readings[first]).astype(float) - values(readings[second]).astype(float)
                se = float(diff.std(ddof=1) / np.sqrt(len(diff)))
                shares[f"{first} - {second}: {share}"] = {"mean": float(diff.mean()), "se": se}
                print(f"paired: {first} - {second}: {share} {diff.mean():+.1%} ± {se:.1%}")
        by_proxy = {name: identity_by_proxy(r.identity_kept, readings[alone_row].identity_kept)
                    for name, r in readings.items()}  # fmt: skip
        views = {name: {"azimuth_error_deg": np.round(r.azimuth_error_deg, 2).tolist(),
                        "identity_kept": r.identity_kept.astype(int).tolist()}
                 for name, r in readings.items()}  # fmt: skip
        return {"benchmark": "proxy_prior_views (identity)", "pipelines": [str(pipeline), *compare],
                "pairs_per_class": pairs_per_class, "seed": seed, "proxy": proxy,
                "paired_azimuth_error_differences": comparisons, "paired_share_differences": shares,
                "rows": rows, "identity_by_proxy": by_proxy, "per_view": views,
                "device": cpu_device()}  # fmt: skip
    if retrieval is not None:  # the exhaustive fit against the learned shortlist of each size
        name, sizes = retrieval[0], [int(k) for k in retrieval[1]]
        same_fit, fit_seconds_per_chip = {}, {"exhaustive": _fit_seconds(proxy, sim, 8)}
        recorded_rows = ["proxy prior, its recorded sampler, exhaustive fit"]
        add(recorded_rows[0], *sample(pipe, fitted, fitted[:, 1], proxy_strength, heading))
        pairs_of_rows = []
        for k in sizes:
            learned = check_proxy_settings({**proxy, "shortlist": k, "retrieval": name})
            begin = time.perf_counter()
            views = fitted_views(learned, sim.inputs, sim.input_azimuth, sim.d_az, workers)
            label = f"learned shortlist of {k}"
            add(f"proxy alone, {label}", views[:, 1], time.perf_counter() - begin)
            same_fit[k] = float(np.mean(np.all(views[:, 0] == fitted[:, 0], axis=(1, 2))))
            fit_seconds_per_chip[label] = _fit_seconds(learned, sim, 8)
            print(f"{label}: the exhaustive fit's vehicle in {same_fit[k]:.0%} of inputs; "
                  f"{fit_seconds_per_chip[label]:.3f} s per fit", flush=True)  # fmt: skip
            pairs_of_rows.append((f"proxy alone, {label}", alone_row))
            if k == retrieval[2]:
                recorded_rows.append(f"proxy prior, its recorded sampler, {label}")
                add(recorded_rows[-1], *sample(pipe, views, views[:, 1], proxy_strength, heading))
                pairs_of_rows.append((recorded_rows[-1], recorded_rows[0]))
        comparisons = paired_differences(readings, pairs_of_rows)
        return {"benchmark": "proxy_prior_views (issue 61: learned shortlist)", "pipeline": str(pipeline),
                "retrieval": name, "pairs_per_class": pairs_per_class, "seed": seed, "proxy": proxy,
                "same_fit_as_exhaustive": same_fit, "fit_seconds_per_chip": fit_seconds_per_chip,
                "paired_azimuth_error_differences": comparisons, "rows": rows,
                "device": cpu_device()}  # fmt: skip
    if refine is not None:  # the best fit against its stretches refined by rendering and comparing
        k, factors = int(refine[0]), [float(f) for f in refine[1]]
        begin = time.perf_counter()
        variants = refined_views(proxy, sim.inputs, sim.input_azimuth, sim.d_az, k, factors, workers)
        seconds = time.perf_counter() - begin
        names = ["the best fit", "the best fit stretched", f"the best stretch of the {k} best fits"]
        for views, name in zip(variants, names):
            add(f"proxy alone, {name}", views[:, 1], seconds)
            add(f"proxy prior, its recorded sampler, {name}",
                *sample(pipe, views, views[:, 1], proxy_strength, heading))  # fmt: skip
        comparisons = paired_differences(readings, [
            (f"{model}, {name}", f"{model}, {names[0]}") for name in names[1:]
            for model in ("proxy alone", "proxy prior, its recorded sampler")
        ])  # fmt: skip
        return {"benchmark": "proxy_prior_views (issue 61: refined proxy)", "pipeline": str(pipeline),
                "recorded_sampler": recorded, "refine": {"k": k, "factors": factors}, "seed": seed,
                "proxy": proxy, "paired_azimuth_error_differences": comparisons, "rows": rows,
                "device": cpu_device()}  # fmt: skip
    if consensus is not None:  # the best fit against the consensus of the k best, through both samplers
        k, temperature = int(consensus[0]), float(consensus[1])
        begin = time.perf_counter()
        mean = consensus_views(proxy, sim.inputs, sim.input_azimuth, sim.d_az, k, temperature, workers)
        label = f"consensus of the {k} best (temperature {temperature:g})"
        add(f"proxy alone, {label}", mean[:, 1], time.perf_counter() - begin)
        base_steps = int(base_recorded["num_inference_steps"])
        pairs_of_rows = [(f"proxy alone, {label}", next(n for n in rows if n.startswith("proxy alone (")))]
        for views, name in ((fitted, "the best fit"), (mean, label)):
            add(f"proxy prior, its recorded sampler, {name}",
                *sample(pipe, views, views[:, 1], proxy_strength, heading))
            add(f"{baseline}, its recorded sampler, {name}",
                *sample(base, None, views[:, 1], base_strength, base_heading, base_steps))  # fmt: skip
        for model in ("proxy prior", baseline):
            pairs_of_rows.append((f"{model}, its recorded sampler, {label}",
                                  f"{model}, its recorded sampler, the best fit"))  # fmt: skip
        comparisons = paired_differences(readings, pairs_of_rows)
        return {"benchmark": "proxy_prior_views (issue 61: consensus proxy)", "pipeline": str(pipeline),
                "baseline": str(baseline), "recorded_sampler": recorded, "consensus": [k, temperature],
                "seed": seed, "proxy": proxy, "paired_azimuth_error_differences": comparisons, "rows": rows,
                "device": cpu_device()}  # fmt: skip
    if steps_sweep:  # the recorded sampler at other step counts only, paired with its own step count
        add(f"proxy prior, its recorded sampler ({start}, heading {heading:g})",
            *sample(pipe, fitted, fitted[:, 1], proxy_strength, heading))  # fmt: skip
        recorded_row = next(n for n in rows if n.startswith("proxy prior, its recorded sampler"))
        comparisons = {}
        # the baseline's two recorded samplers: from its proxy (azimuth given) and from noise (no azimuth)
        base_steps = int(base_recorded["num_inference_steps"])
        base_rows = {"from its proxy": (fitted[:, 1], base_strength),
                     "from noise, no azimuth": (None, 1.0)}  # fmt: skip
        for label, (start_views, strength) in base_rows.items():
            views, seconds = sample(base, None, start_views, strength, base_heading, base_steps)
            add(f"{baseline}, recorded sampler {label}", views, seconds)
        for count in steps_sweep:
            name = f"proxy prior, its recorded sampler at {count} steps"
            add(name, *sample(pipe, fitted, fitted[:, 1], proxy_strength, heading, count))
            pairs_of_rows = [(name, recorded_row)]
            for label, (start_views, strength) in base_rows.items():
                other = f"{baseline}, recorded sampler {label} at {count} steps"
                add(other, *sample(base, None, start_views, strength, base_heading, count))
                pairs_of_rows.append((other, f"{baseline}, recorded sampler {label}"))
            comparisons |= paired_differences(readings, pairs_of_rows)
        return {"benchmark": "proxy_prior_views (issue 63: step counts)", "pipeline": str(pipeline),
                "recorded_sampler": recorded, "steps": list(steps_sweep), "seed": seed, "proxy": proxy,
                "paired_azimuth_error_differences": comparisons, "rows": rows,
                "device": cpu_device()}  # fmt: skip
    name = f"{baseline}, its recorded sampler, input azimuth given (from its proxy at {base_strength:g}, "
    add(name + f"heading {base_heading:g})", *sample(base, None, fitted[:, 1], base_strength, base_heading))
    add(f"proxy prior, its recorded sampler ({start}, heading {heading:g})",
        *sample(pipe, fitted, fitted[:, 1], proxy_strength, heading))  # fmt: skip
    for strength in sorted({0.3, 0.5} - {proxy_strength}):
        add(f"proxy prior from the proxy at {strength:g}, heading {heading:g}",
            *sample(pipe, fitted, fitted[:, 1], strength, heading))  # fmt: skip
    for scale in sorted({0.0, *headings} - ({heading} if proxy_strength >= 1.0 else set())):
        add(f"proxy prior from noise, heading {scale:g}", *sample(pipe, fitted, None, 1.0, scale))
    add(f"{baseline} from an oracle proxy at {base_strength:g}, heading {base_heading:g}",
        *sample(base, None, oracle[:, 1], base_strength, base_heading))  # fmt: skip
    add(f"proxy prior, oracle proxy pair, from the oracle at 0.3, heading {heading:g}",
        *sample(pipe, oracle, oracle[:, 1], 0.3, heading))  # fmt: skip
    add(f"proxy prior, oracle proxy pair, {start}, heading {heading:g}",
        *sample(pipe, oracle, oracle[:, 1], proxy_strength, heading))  # fmt: skip
    add(f"proxy prior, oracle proxy pair, from noise, heading {heading:g}",
        *sample(pipe, oracle, None, 1.0, heading))  # fmt: skip
    # paired differences of the template azimuth error on the same pairs (negative: the first is nearer)
    best = min((n for n in rows if n.startswith("proxy prior") and "oracle" not in n),
               key=lambda n: rows[n]["azimuth_error_deg"])  # fmt: skip
    baseline_row = next(n for n in rows if n.startswith(f"{baseline}, its recorded"))
    alone = next(n for n in rows if n.startswith("proxy alone"))
    recorded_row = next(n for n in rows if n.startswith("proxy prior, its recorded sampler"))
    firsts = dict.fromkeys((recorded_row, best))
    comparisons = paired_differences(readings, [(f, o) for f in firsts for o in (baseline_row, alone)])
    return {"benchmark": "proxy_prior_views (issue 61)", "best_row": best,
            "paired_azimuth_error_differences": comparisons, "pipeline": str(pipeline),
            "baseline": str(baseline), "classes": sim.classes, "pairs_per_class": pairs_per_class,
            "d_az_range_deg": [60.0, 180.0], "input_depression_deg": INPUT_DEPRESSION_DEG,
            "recorded_sampler": recorded, "proxy": proxy, "seed": seed, **device_record(),
            "rows": rows}  # fmt: skip


def main(argv: Sequence[str] | None = None) -> dict:
    parser = script_parser(__doc__)
    parser.add_argument("--pipeline", required=True, help="a spatial_pose='proxy' pipeline folder or name")
    parser.add_argument("--baseline", default=SIM_PRIOR_ROTATED, help="the pipeline to compare with")
    parser.add_argument("--pairs_per_class", type=int, default=32, help="pairs per named vehicle (8)")
    parser.add_argument("--batch_size", type=int, default=32, help="views per pipeline call")
    parser.add_argument("--seed", type=int, default=0, help="pairs, clutter and sampling seed")
    parser.add_argument("--workers", type=int, default=2, help="processes fitting the proxies")
    parser.add_argument("--headings", nargs="+", type=float, default=[1.5, 3.0],
                        help="heading guidance weights of the rows from noise (0 is always one)")
    parser.add_argument("--fits", default=None,
                        help="an .npz to keep the proxy fits in (reused when the pairs and bank match)")
    parser.add_argument("--steps", nargs="+", type=int, default=[],
                        help="only the recorded sampler, at its own and at these step counts (paired)")
    parser.add_argument("--shortlist", type=int, default=None,
                        help="fit in two stages, this many vehicles re-rendered at the exact pose")
    parser.add_argument("--bank_size", type=int, default=None,
                        help="fit with a bank of this many vehicles (default: the pipeline's)")
    parser.add_argument("--consensus", nargs=2, type=float, default=None, metavar=("K", "TEMPERATURE"),
                        help="only the proxy alone and both recorded samplers, from the best fit and from "
                        "the weighted mean of the K best fits' renders (weights exp(score / T))")
    parser.add_argument("--refine", nargs="+", type=float, default=None, metavar="K_THEN_FACTORS",
                        help="only the proxy alone and the recorded sampler, from the best fit and from the "
                        "K best fits stretched along length and width by each pair of the factors")
    parser.add_argument("--retrieval", nargs="+", default=None, metavar="NAME_THEN_SIZES",
                        help="only the proxy alone from the exhaustive fit and from a learned shortlist (a "
                        "name or folder) of each size, and the recorded sampler from the exhaustive fit and "
                        "from the first size")
    parser.add_argument("--compare", nargs="+", default=[],
                        help="only each pipeline's plain call with the fitted and the perfect proxy, both "
                        "also from noise: the first --pipeline, then these, paired with it")  # fmt: skip
    parser.add_argument("--out", default="proxy_prior_views.json", help="output JSON")
    args = parser.parse_args(argv)
    if args.consensus is not None and not (args.consensus[0] >= 1 and args.consensus[1] > 0):
        raise ValueError(f"consensus: expected K >= 1 and a temperature > 0, got {args.consensus}")
    if args.pairs_per_class < 2:
        raise ValueError(f"pairs_per_class must be >= 2, got {args.pairs_per_class}")
    consensus = None if args.consensus is None else (int(args.consensus[0]), args.consensus[1])
    refine = None
    if args.refine is not None:
        if len(args.refine) < 2 or args.refine[0] < 1 or min(args.refine[1:]) <= 0:
            raise ValueError(f"refine: expected K >= 1 then factors > 0, got {args.refine}")
        refine = (int(args.refine[0]), args.refine[1:])
    retrieval = None
    if args.retrieval is not None:
        sizes = [int(k) for k in args.retrieval[1:]]
        if not sizes or min(sizes) < 1:
            raise ValueError(f"retrieval: expected a name then shortlist sizes >= 1, got {args.retrieval}")
        retrieval = (args.retrieval[0], sizes, sizes[0])
    record = run(args.pipeline, baseline=args.baseline, pairs_per_class=args.pairs_per_class,
                 batch_size=args.batch_size, seed=args.seed, workers=args.workers, headings=args.headings,
                 fits=args.fits, steps_sweep=args.steps, shortlist=args.shortlist, bank_size=args.bank_size,
                 consensus=consensus, refine=refine, retrieval=retrieval, compare=args.compare)  # fmt: skip
    write_json_atomic(record, Path(args.out))
    print(format_table(record))
    return record


if __name__ == "__main__":
    main()
