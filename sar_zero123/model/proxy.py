"""The simulator proxy of each input chip, as the pipeline builds it (analysis by synthesis).

A :class:`~sar_zero123.sim.proxy.ProxyBank` vehicle is fitted to each chip at its pose (best blurred
correlation) and re-rendered at the requested pose in normalised dB: a draft whose shadow, layover and
front are the requested pose's. Sampling from it, conditioned on the input, lets the input bring the
identity and the simulator the geometry. A pipeline records its settings (:data:`PROXY_FIELDS`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from sar_zero123.data import DecibelScaling
from sar_zero123.data.scaling import ZERO_MAGNITUDE_DB
from sar_zero123.model.conditioning import as_angle_tensor, encode_condition_latents
from sar_zero123.model.spatial_pose import proxy_condition_views, proxy_pair_latents
from sar_zero123.model.view_request import Angles, ViewRequest, per_input_angles
from sar_zero123.sim.proxy import MAX_RENDERED_BANK, PROXY_FIRST_SEED, ProxyBank

__all__ = [
    "DATASET_SHORTLIST", "DEFAULT_PROXY", "PROXY_FIELDS", "check_proxy_settings", "draft_target_views",
    "MIN_FIT_SCORE", "fit_scores", "proxy_bank", "proxy_drafts", "proxy_latents", "with_shortlist",
]  # fmt: skip

#: The fit score below which a chip holds no vehicle the simulator can fit: between real MSTAR vehicles'
#: scores and their own clutter's.
MIN_FIT_SCORE = 0.3
#: What a pipeline records of its proxy: the bank (:class:`ProxyBank`'s arguments), the decibel bounds of
#: its normalised dB domain, its learned shortlist (``retrieval``: ``None``, or the name or folder of a
#: :class:`~sar_zero123.model.retrieval.ProxyRetrievalNet` for that bank, whose ``shortlist`` best vehicles
#: a fit renders) and ``min_fit_score`` (a best fit scoring below it is refused).
PROXY_FIELDS = (
    "num_vehicles", "first_seed", "blur_sigma_px", "render_seed", "max_shift_px", "shortlist", "min_db",
    "max_db", "retrieval", "min_fit_score",
)  # fmt: skip
#: The fields that build the bank (:class:`ProxyBank`'s arguments, in order).
_BANK_FIELDS = PROXY_FIELDS[:6]
#: The fields :func:`proxy_bank` takes (the bank and its learned shortlist).
_FIT_FIELDS = (*_BANK_FIELDS, "retrieval")
#: Fields a record may leave out, and their values (records written before they existed).
_PROXY_OPTIONAL = {"max_shift_px": 0, "shortlist": 0, "retrieval": None, "min_fit_score": MIN_FIT_SCORE}
#: The shortlist a dataset's fits use (``sar-zero123-augment``): near the exhaustive fit, for far fewer
#: renders per chip.
DATASET_SHORTLIST = 128
#: The bank the bundled priors record.
DEFAULT_PROXY: dict[str, Any] = {
    "num_vehicles": 1000,
    "first_seed": PROXY_FIRST_SEED,
    "blur_sigma_px": 1.5,
    "render_seed": 0,
    "max_shift_px": 0,
    "shortlist": 0,
    "min_db": -60.0,
    "max_db": 0.0,
    "retrieval": None,
    "min_fit_score": MIN_FIT_SCORE,
}


#: The decibels of the largest float32 magnitude: no view's decibels lie above them.
MAX_FLOAT32_DB = 20.0 * math.log10(float(np.finfo(np.float32).max))


def check_proxy_settings(proxy: Mapping[str, Any], name: str = "proxy") -> dict[str, Any]:
    """A pipeline's proxy settings, checked: exactly :data:`PROXY_FIELDS`, a valid bank, ``min_db < max_db``.

    Raises:
        ValueError: Naming ``name`` and the field, for a missing, unknown or invalid entry.
    """
    if not isinstance(proxy, Mapping):
        raise ValueError(f"{name}: expected a mapping of {list(PROXY_FIELDS)}, got {type(proxy).__name__}")
    proxy = {**_PROXY_OPTIONAL, **proxy}
    missing, unknown = set(PROXY_FIELDS) - set(proxy), set(proxy) - set(PROXY_FIELDS)
    if missing or unknown:
        raise ValueError(f"{name}: expected the fields {list(PROXY_FIELDS)}; missing {sorted(missing)}, "
                         f"unknown {sorted(unknown)}")  # fmt: skip
    bounds = [proxy["min_db"], proxy["max_db"]]
    if not all(
        isinstance(b, int | float) and not isinstance(b, bool) and math.isfinite(b) for b in bounds
    ) or not (bounds[0] < bounds[1]):
        raise ValueError(
            f"{name}.min_db, {name}.max_db: expected finite decibels with min < max, got {bounds}"
        )
    if not (ZERO_MAGNITUDE_DB <= bounds[0] and bounds[1] <= MAX_FLOAT32_DB):  # past them every view is flat
        raise ValueError(
            f"{name}.min_db, {name}.max_db: expected decibels in [{ZERO_MAGNITUDE_DB:g}, "
            f"{MAX_FLOAT32_DB:.4g}] (zero magnitude's and the largest float32 magnitude's), got {bounds}"
        )
    try:
        ProxyBank(*(proxy[key] for key in _BANK_FIELDS))
    except ValueError as error:
        raise ValueError(f"{name}.{error}") from None
    floor = proxy["min_fit_score"]
    if isinstance(floor, bool) or not isinstance(floor, int | float) or not -1.0 <= floor <= 1.0:
        raise ValueError(f"{name}.min_fit_score: expected a correlation in [-1, 1], got {floor!r}")
    retrieval = proxy["retrieval"]
    if retrieval is None and proxy["num_vehicles"] > MAX_RENDERED_BANK:
        raise ValueError(
            f"{name}.num_vehicles: a bank without a learned shortlist ({name}.retrieval) renders all "
            f"its vehicles in each fit; expected at most {MAX_RENDERED_BANK:,}, got {proxy['num_vehicles']:,}"
        )
    if retrieval is not None:
        if not isinstance(retrieval, str) or not retrieval:
            raise ValueError(f"{name}.retrieval: expected null or the name or folder of a learned shortlist, "
                             f"got {retrieval!r}")  # fmt: skip
        if not proxy["shortlist"]:
            raise ValueError(f"{name}.retrieval: a learned shortlist needs shortlist > 0 (the vehicles it "
                             "renders), got shortlist = 0")  # fmt: skip
    return {key: proxy[key] for key in PROXY_FIELDS}


@functools.lru_cache(maxsize=4)
def proxy_bank(
    num_vehicles: int,
    first_seed: int,
    blur_sigma_px: float,
    render_seed: int,
    max_shift_px: int = 0,
    shortlist: int = 0,
    retrieval: str | None = None,
) -> ProxyBank:
    """The bank for these settings, shared within a process (its vehicles are built once; a learned
    shortlist, :func:`~sar_zero123.pretrained.resolve_retrieval`, loaded once).

    Raises:
        FileNotFoundError, ValueError: For a retrieval that is not found or ranks another bank.
    """
    net = None
    if retrieval is not None:
        from sar_zero123.model.retrieval import load_retrieval
        from sar_zero123.pretrained import resolve_retrieval

        bank = {"num_vehicles": num_vehicles, "first_seed": first_seed, "blur_sigma_px": blur_sigma_px,
                "render_seed": render_seed}  # fmt: skip
        net = load_retrieval(resolve_retrieval(retrieval), bank)
    return ProxyBank(num_vehicles, first_seed, blur_sigma_px, render_seed, max_shift_px, shortlist, net)


@functools.lru_cache(maxsize=1024)
def _fit(
    settings: tuple,
    chip_bytes: bytes,
    shape: tuple[int, int],
    azimuth_deg: float,
    depression_deg: float,
    resolve_heading: bool,
) -> tuple[int, float, tuple[int, int], float]:
    """The bank vehicle fitted to one chip at its pose: ``(index, fitted azimuth, shift, score)``,
    remembered for the process's last 1,024 chips and poses (an evaluation's rows share their pairs' fits).
    """
    bank = proxy_bank(*settings)
    chip = np.frombuffer(chip_bytes, dtype=np.float32).reshape(shape)
    headings = (azimuth_deg, azimuth_deg + 180.0) if resolve_heading else (azimuth_deg,)
    matches = [bank.retrieve(chip, azimuth, depression_deg) for azimuth in headings]
    best = max(range(len(headings)), key=lambda h: matches[h].score)  # the first heading wins a tie
    return matches[best].index, headings[best] % 360.0, matches[best].shift_px, float(matches[best].score)


#: A chip whose values span no more than this (normalised dB) holds nothing a proxy could be fitted to.
_FLAT_RANGE = 1e-6


def draft_target_views(
    images: torch.Tensor,
    input_azimuth_deg: torch.Tensor,
    input_depression_deg: torch.Tensor,
    d_az_deg: torch.Tensor,
    d_el_deg: torch.Tensor,
    proxy: Mapping[str, Any],
    resolve_heading: bool = False,
) -> tuple[torch.Tensor, np.ndarray]:
    """Each input chip's proxy, fitted at the chip's pose and rendered at the requested pose.

    Args:
        images: Input chips in normalised dB ``(B, 1 | 3, H, W)`` (square).
        input_azimuth_deg: Each chip's absolute azimuth ``(B,)``, from its metadata or estimated.
        input_depression_deg: Each chip's depression ``(B,)``.
        d_az_deg: Requested azimuth changes ``(B,)``.
        d_el_deg: Requested depression changes ``(B,)``.
        proxy: The pipeline's proxy settings (:func:`check_proxy_settings`).
        resolve_heading: Also fit at azimuth + 180 and keep the better (an estimate may swap front and
            back; the simulator tells them apart).

    Returns:
        ``(drafts (B, 1, H, W) float32 in [0, 1], fitted azimuth (B,))``.

    Raises:
        ValueError: For a target depression outside (0, 90) deg, or a chip with nothing to fit: every pixel
            the same value, or a best fit scoring below ``min_fit_score`` (clutter without a vehicle).
    """
    proxy = check_proxy_settings(proxy)
    # the bank's own arguments where no shortlist is recorded: one cached bank per settings
    fields = _FIT_FIELDS if proxy["retrieval"] is not None else _BANK_FIELDS
    settings = tuple(proxy[key] for key in fields)
    bank = proxy_bank(*settings)
    scaling = DecibelScaling(min_db=float(proxy["min_db"]), max_db=float(proxy["max_db"]))
    chips = images.detach().float().mean(dim=1).cpu().numpy()  # (B, H, W), any affine map of decibels
    size = chips.shape[-1]
    _refuse_flat(chips)
    drafts, fitted = [], []
    for k, chip in enumerate(chips):
        azimuth, depression = float(input_azimuth_deg[k]), float(input_depression_deg[k])
        target_depression = depression + float(d_el_deg[k])
        if not 0.0 < target_depression < 90.0:
            raise ValueError(
                "input_depression_deg + d_el: expected a target depression in (0, 90) deg, "
                f"got {target_depression}"
            )
        # many requests for one chip (generate, the demo's views and turntable) share one fit
        fit = _fit(settings, chip.tobytes(), chip.shape, azimuth, depression, resolve_heading)
        index, fitted_azimuth, shift, score = fit
        if score < proxy["min_fit_score"]:
            raise ValueError(
                f"image: input {k}: no simulator vehicle fits it (fit score {score:.3f}, below the floor "
                f"{proxy['min_fit_score']} between real vehicles and clutter); give a chip with its target "
                "in it, proxy_views, or a pipeline without a proxy"
            )
        render = bank.render(index, fitted_azimuth + float(d_az_deg[k]), target_depression, size, shift)
        drafts.append(scaling.normalize(render))
        fitted.append(fitted_azimuth)
    return torch.from_numpy(np.stack(drafts)[:, None].astype(np.float32)), np.asarray(fitted)


def fit_scores(
    images: torch.Tensor,
    input_azimuth_deg: torch.Tensor,
    input_depression_deg: torch.Tensor,
    proxy: Mapping[str, Any],
    resolve_heading: bool = False,
) -> np.ndarray:
    """How well each input's proxy fits it: the blurred correlation ``(B,)`` in [-1, 1] of the fitted
    vehicle with the chip at its pose, for the fits :func:`draft_target_views` ran (remembered, not rerun).

    Raises:
        ValueError: As :func:`draft_target_views`, for a chip with no structure to fit.
    """
    proxy = check_proxy_settings(proxy)
    fields = _FIT_FIELDS if proxy["retrieval"] is not None else _BANK_FIELDS
    settings = tuple(proxy[key] for key in fields)
    chips = images.detach().float().mean(dim=1).cpu().numpy()
    _refuse_flat(chips)
    poses = [(float(input_azimuth_deg[k]), float(input_depression_deg[k])) for k in range(len(chips))]
    fits = [
        _fit(settings, chip.tobytes(), chip.shape, *pose, resolve_heading) for chip, pose in zip(chips, poses)
    ]
    return np.asarray([fit[3] for fit in fits])


def _refuse_flat(chips: np.ndarray) -> None:
    flat = [k for k, chip in enumerate(chips) if float(chip.max() - chip.min()) <= _FLAT_RANGE]
    if flat:
        raise ValueError(
            f"image: input {flat[0]} has no structure to fit a simulator proxy to (every pixel "
            f"{float(chips[flat[0]].flat[0]):.4g}); give a chip with its target in it"
        )


def with_shortlist(
    proxy: Mapping[str, Any] | None, shortlist: int = DATASET_SHORTLIST
) -> dict[str, Any] | None:
    """A pipeline's proxy settings fitted in two stages (``shortlist``) where they record an exhaustive fit
    (0): for many chips, whose fits share pose buckets; ``None`` stays ``None``."""
    if proxy is None:
        return None
    checked = check_proxy_settings(proxy)
    if checked["shortlist"]:
        return checked
    return check_proxy_settings({**checked, "shortlist": min(shortlist, checked["num_vehicles"])})


# ------------------------------------------------------------------------------- a pipeline call's proxy
def proxy_drafts(
    images: torch.Tensor,
    d_az: Angles,
    d_el: Angles,
    input_azimuth_deg: torch.Tensor | None,
    input_depression_deg: Angles | None,
    proxy: Mapping[str, Any] | None,
    why: str = "start_from='proxy'",
) -> torch.Tensor:
    """Each input's simulator proxy at the requested pose, for a pipeline call (``why`` names which use).

    Args:
        input_azimuth_deg: One checked azimuth per input, or ``None``.
        proxy: ``pipe.config.proxy``, or ``None`` where it records none.

    Returns:
        ``(B, 1, H, W)`` float32 in [0, 1].

    Raises:
        ValueError: Naming what to pass, where the pipeline records no proxy, or an absolute angle is
            missing.
    """
    start = why.startswith("start_from")
    if proxy is None:
        raise ValueError(
            f"{why}: this pipeline records no proxy settings (pipe.config.proxy); build it with "
            "proxy=sar_zero123.model.proxy.DEFAULT_PROXY" + (", or start from 'input'" if start else "")
        )
    batch_size = images.shape[0]
    if input_depression_deg is None:
        raise ValueError(
            f"`input_depression_deg`: {why} fits a simulator vehicle at the input's pose; give the "
            "input chip's depression in degrees (its metadata)" + (", or start from 'input'" if start else "")
        )
    depression = per_input_angles(input_depression_deg, "input_depression_deg", batch_size)
    if input_azimuth_deg is None:
        # an estimated azimuth is no substitute: the bundled estimator is far off on unseen vehicles
        raise ValueError(
            f"`input_azimuth_deg`: {why} fits a simulator vehicle at the input's pose; give each "
            "input chip's absolute azimuth in degrees (its metadata, or an estimate you trust)"
            + (", or start from 'input'" if start else "")
        )
    d_az_values = as_angle_tensor(d_az, "d_az").expand(batch_size)
    d_el_values = as_angle_tensor(d_el, "d_el").expand(batch_size)
    drafts, _ = draft_target_views(images, input_azimuth_deg, depression, d_az_values, d_el_values, proxy)
    return drafts


@torch.no_grad()
def proxy_latents(
    vae: torch.nn.Module,
    request: ViewRequest,
    contrast_kinds: Sequence[str],
    proxy: Mapping[str, Any] | None,
    device: torch.device,
    form: str = "render",
) -> torch.Tensor:
    """The proxy pair (at the input's pose, at the branch's request) of the request and of each
    contrast branch (``"heading"``: ``d_az + 180``; ``"depression"``: ``d_el = 0``), one fit per input;
    given ``request.proxy_views``, every branch takes them. Each view is encoded in the model's ``form``
    (:func:`~sar_zero123.model.spatial_pose.proxy_condition_views`).

    Returns:
        ``(1 + len(contrast_kinds), B, 2C, h, w)``, unscaled latents.
    """
    if request.proxy_views is not None:
        views = request.proxy_views.to(device=device, dtype=torch.float32)
        pair = proxy_pair_latents(vae, views[:, :1], views[:, 1:2], form)
        flipped = pair
        if views.shape[1] == 3:  # the proxy at the flipped heading, for the heading contrast
            flipped = proxy_pair_latents(vae, views[:, :1], views[:, 2:3], form)
        return torch.stack([pair] + [flipped if kind == "heading" else pair for kind in contrast_kinds])
    batch_size = request.batch_size
    d_az_values = as_angle_tensor(request.d_az, "d_az").expand(batch_size)
    d_el_values = as_angle_tensor(request.d_el, "d_el").expand(batch_size)
    zeros = torch.zeros_like(d_el_values)
    requests = [(torch.zeros_like(d_az_values), zeros), (d_az_values, d_el_values)]  # input pose, request
    for kind in contrast_kinds:
        requests.append((d_az_values + 180.0, d_el_values) if kind == "heading" else (d_az_values, zeros))
    # one call, each chip's requests side by side: one fit per chip, one VAE encoding of every render
    count = len(requests)
    d_az_all = torch.stack([az for az, _ in requests], dim=1).reshape(-1)  # (B * R,), chip-major
    d_el_all = torch.stack([el for _, el in requests], dim=1).reshape(-1)
    input_depression_deg = request.input_depression_deg
    if input_depression_deg is not None:
        depression = per_input_angles(input_depression_deg, "input_depression_deg", batch_size)
        input_depression_deg = depression.repeat_interleave(count)
    input_azimuth_deg = request.input_azimuth_deg
    if input_azimuth_deg is not None:
        input_azimuth_deg = input_azimuth_deg.repeat_interleave(count)
    drafts = proxy_drafts(
        request.images.repeat_interleave(count, dim=0), d_az_all, d_el_all, input_azimuth_deg,
        input_depression_deg, proxy, "spatial_pose='proxy'",
    )  # fmt: skip
    latents = encode_condition_latents(vae, proxy_condition_views(drafts.to(device), form))
    latents = latents.reshape(batch_size, count, *latents.shape[1:])
    return torch.stack([torch.cat([latents[:, 0], latents[:, r]], dim=1) for r in range(1, count)])
