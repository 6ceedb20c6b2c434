"""Template-matched readings of generated views: an azimuth that a footprint turned in place cannot fool.

A learned regressor can be satisfied by a body on the right axis with front and back swapped. Where the
true vehicle is known, each view is correlated (both blurred, Pearson, blind to any affine map of
decibels) with its renders on an azimuth grid at the requested depression (its *turntable*); the best
grid azimuth is the view's reading. Per view:

- ``azimuth_error_deg``: the reading's angular distance to the requested azimuth, in [0, 180];
- ``front_back_right``: the reading lies nearer the request than the request turned by 180 deg;
- ``identity_kept``: over every candidate vehicle's turntable, the best match is the true vehicle's;
- ``turned_and_kept``: the view keeps its vehicle and reads within :data:`TURNED_WITHIN_DEG` of the
  request (the input copy keeps every vehicle and turns none).

``gap_closed`` places a row's mean error between a floor (the input copy) and a ceiling (the true view
with another speckle draw): 0 at the floor, 1 at the ceiling.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

__all__ = [
    "TURNED_WITHIN_DEG",
    "TemplateReadings",
    "gap_closed",
    "identity_by_proxy",
    "read_chip_templates",
    "read_templates",
    "summarise_readings",
    "turned_and_kept",
]

#: A view is turned when its template reading lies within this many degrees of the request.
TURNED_WITHIN_DEG = 30.0


def _normalised(images: np.ndarray, blur_sigma_px: float) -> np.ndarray:
    """Blurred, mean-free, unit-norm rows ``(N, S * S)`` (a constant image gives a zero row)."""
    images = np.asarray(images, dtype=np.float64)
    if blur_sigma_px > 0:
        images = gaussian_filter(images, (0.0, blur_sigma_px, blur_sigma_px))
    rows = images.reshape(len(images), -1)
    rows = rows - rows.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(rows, axis=1, keepdims=True)
    return np.where(norm > 0, rows / np.maximum(norm, 1e-300), 0.0)


def _angle_between(a_deg: np.ndarray, b_deg: np.ndarray) -> np.ndarray:
    """Angular distance in [0, 180] degrees."""
    return np.abs((np.asarray(a_deg) - np.asarray(b_deg) + 180.0) % 360.0 - 180.0)


@dataclass(frozen=True)
class TemplateReadings:
    """Per-view template readings (:func:`read_templates`); every field is ``(N,)``."""

    matched_azimuth_deg: np.ndarray
    azimuth_error_deg: np.ndarray
    front_back_right: np.ndarray
    identity_kept: np.ndarray


def read_templates(
    views: np.ndarray,
    turntables: np.ndarray,
    turntable_azimuths_deg: Sequence[float],
    vehicle: Sequence[int],
    requested_azimuth_deg: Sequence[float],
    blur_sigma_px: float = 1.5,
) -> TemplateReadings:
    """Read each view's azimuth and identity off the candidate vehicles' turntables.

    Args:
        views: Generated views ``(N, S, S)``.
        turntables: Every candidate vehicle's renders ``(V, K, S, S)`` at ``turntable_azimuths_deg`` and the
            requested depression (one for all views).
        vehicle: Each view's true vehicle, an index into ``turntables`` ``(N,)``.
        requested_azimuth_deg: Each view's requested absolute azimuth ``(N,)``.
        blur_sigma_px: Gaussian blur of views and templates before they are correlated.

    Raises:
        ValueError: For shapes that do not match, or a vehicle index outside ``[0, V)``.
    """
    views = np.asarray(views)
    turntables = np.asarray(turntables)
    grid = np.asarray(turntable_azimuths_deg, dtype=np.float64)
    vehicle = np.asarray(vehicle, dtype=np.int64)
    requested = np.asarray(requested_azimuth_deg, dtype=np.float64)
    if views.ndim != 3 or turntables.ndim != 4 or turntables.shape[2:] != views.shape[1:]:
        raise ValueError(
            "views (N, S, S) and turntables (V, K, S, S) must share S, "
            f"got {views.shape} and {turntables.shape}"
        )
    n, (v, k) = len(views), turntables.shape[:2]
    if grid.shape != (k,):
        raise ValueError(f"turntable_azimuths_deg: expected {k} azimuths, got shape {grid.shape}")
    if vehicle.shape != (n,) or requested.shape != (n,):
        raise ValueError(
            f"vehicle and requested_azimuth_deg: expected ({n},), got {vehicle.shape}, {requested.shape}"
        )
    if n and (vehicle.min() < 0 or vehicle.max() >= v):
        raise ValueError(f"vehicle: expected indices in [0, {v}), got [{vehicle.min()}, {vehicle.max()}]")
    templates = _normalised(turntables.reshape(v * k, *turntables.shape[2:]), blur_sigma_px)
    correlation = (_normalised(views, blur_sigma_px) @ templates.T).reshape(n, v, k)  # (N, V, K)
    own = correlation[np.arange(n), vehicle]  # (N, K)
    matched = grid[np.argmax(own, axis=1)]
    error = _angle_between(matched, requested)
    identity = np.argmax(correlation.max(axis=2), axis=1) == vehicle
    return TemplateReadings(
        matched_azimuth_deg=matched,
        azimuth_error_deg=error,
        front_back_right=error < 90.0,
        identity_kept=identity,
    )


def read_chip_templates(
    views: np.ndarray,
    templates: np.ndarray,
    template_azimuth_deg: Sequence[float],
    candidates: np.ndarray,
    requested_azimuth_deg: Sequence[float],
    blur_sigma_px: float = 1.5,
) -> TemplateReadings:
    """Read each view's azimuth off a data folder's own chips of its vehicle (real or simulated).

    Without renders of the true vehicle, its other chips at the requested depression are the turntable:
    the reading is the azimuth of the candidate chip correlating best. With the target chip left out, the
    true view reads its nearest neighbour's azimuth (the ceiling), the input copy its own (the floor).
    ``identity_kept`` is all True (every template is the view's vehicle).

    Args:
        views: Generated views ``(N, S, S)``.
        templates: Chips ``(M, S, S)`` and their azimuths ``template_azimuth_deg`` ``(M,)``.
        candidates: ``(N, M)`` bool: the chips each view may be read against (at least one per view).
        requested_azimuth_deg: Each view's requested absolute azimuth ``(N,)``.

    Raises:
        ValueError: For shapes that do not match, or a view without a candidate chip.
    """
    views, templates = np.asarray(views), np.asarray(templates)
    azimuths = np.asarray(template_azimuth_deg, dtype=np.float64)
    candidates = np.asarray(candidates, dtype=bool)
    requested = np.asarray(requested_azimuth_deg, dtype=np.float64)
    if views.ndim != 3 or templates.ndim != 3 or templates.shape[1:] != views.shape[1:]:
        raise ValueError(
            f"views (N, S, S) and templates (M, S, S) must share S, got {views.shape} and {templates.shape}"
        )
    n, m = len(views), len(templates)
    if azimuths.shape != (m,) or candidates.shape != (n, m) or requested.shape != (n,):
        raise ValueError(
            f"template_azimuth_deg ({m},), candidates ({n}, {m}) and requested_azimuth_deg ({n},) expected, "
            f"got {azimuths.shape}, {candidates.shape} and {requested.shape}"
        )
    if n and not candidates.any(axis=1).all():
        raise ValueError(f"candidates: view {int(np.argmin(candidates.any(axis=1)))} has no candidate chip")
    correlation = _normalised(views, blur_sigma_px) @ _normalised(templates, blur_sigma_px).T  # (N, M)
    matched = azimuths[np.argmax(np.where(candidates, correlation, -np.inf), axis=1)]
    error = _angle_between(matched, requested)
    return TemplateReadings(
        matched_azimuth_deg=matched,
        azimuth_error_deg=error,
        front_back_right=error < 90.0,
        identity_kept=np.ones(n, dtype=bool),
    )


def gap_closed(error: float, floor_error: float, ceiling_error: float) -> float:
    """Share of the gap from the floor's mean error to the ceiling's that a row closes (0 floor, 1 ceiling).

    Raises:
        ValueError: If the floor is not above the ceiling (the gap is empty: nothing to close).
    """
    if not floor_error > ceiling_error:
        raise ValueError(f"floor_error {floor_error!r} must exceed ceiling_error {ceiling_error!r}")
    return float((floor_error - error) / (floor_error - ceiling_error))


def _mean_se(values: np.ndarray) -> tuple[float, float]:
    x = np.asarray(values, dtype=np.float64)
    se = float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")
    return float(x.mean()), se


def turned_and_kept(
    azimuth_error_deg: np.ndarray, kept: np.ndarray, within_deg: float = TURNED_WITHIN_DEG
) -> np.ndarray:
    """Per view: it keeps its vehicle (``kept``) and its template azimuth error is at most ``within_deg``.

    Shape:
        ``(N,)``, ``(N,)`` -> ``(N,)`` bool.
    """
    error, kept = np.asarray(azimuth_error_deg, dtype=np.float64), np.asarray(kept, dtype=bool)
    if error.shape != kept.shape:
        raise ValueError(f"kept: expected one value per view {error.shape}, got {kept.shape}")
    return kept & (error <= within_deg)


def identity_by_proxy(kept: np.ndarray, proxy_kept: np.ndarray) -> dict[str, float]:
    """A row's identity kept, split by whether the proxy it was given keeps the vehicle itself.

    ``kept`` is the row's per-view identity, ``proxy_kept`` the proxy alone's on the same pairs. Where the
    proxy is right a view may copy it; where it is wrong only what the view carries of the input keeps the
    vehicle. The row's share is ``p * right + (1 - p) * wrong``, with ``p`` the proxy's own share.

    Returns:
        ``proxy_right_share``, ``kept_proxy_right`` and ``kept_proxy_wrong`` (each ``nan`` on an empty group),
        with the standard errors ``kept_proxy_right_se`` and ``kept_proxy_wrong_se``.
    """
    kept, proxy_kept = np.asarray(kept, dtype=bool), np.asarray(proxy_kept, dtype=bool)
    if kept.ndim != 1 or kept.shape != proxy_kept.shape:
        raise ValueError(f"proxy_kept: expected one value per view {kept.shape}, got {proxy_kept.shape}")
    summary = {"proxy_right_share": float(proxy_kept.mean()) if len(kept) else float("nan")}
    for name, group in (("kept_proxy_right", kept[proxy_kept]), ("kept_proxy_wrong", kept[~proxy_kept])):
        summary[name], summary[f"{name}_se"] = _mean_se(group) if len(group) else (float("nan"), float("nan"))
    return summary


def summarise_readings(
    readings: TemplateReadings, floor: TemplateReadings | None = None, ceiling: TemplateReadings | None = None
) -> dict[str, float]:
    """Means and standard errors of a row's readings; with a floor and a ceiling, its gap closed.

    Returns:
        ``n``, ``azimuth_error_deg`` (+ ``_se``), ``front_back_right`` (+ ``_se``), ``identity_kept``
        (+ ``_se``), ``turned_and_kept`` (+ ``_se``; identity kept and turned) and, given both bounds,
        ``gap_closed``.
    """
    summary: dict[str, float] = {"n": int(len(readings.azimuth_error_deg))}
    for name in ("azimuth_error_deg", "front_back_right", "identity_kept"):
        summary[name], summary[f"{name}_se"] = _mean_se(getattr(readings, name))
    joint = turned_and_kept(readings.azimuth_error_deg, readings.identity_kept)
    summary["turned_and_kept"], summary["turned_and_kept_se"] = _mean_se(joint)
    if floor is not None and ceiling is not None:
        summary["gap_closed"] = gap_closed(
            summary["azimuth_error_deg"],
            float(np.mean(floor.azimuth_error_deg)),
            float(np.mean(ceiling.azimuth_error_deg)),
        )
    return summary
