"""Analysis by synthesis: a simulator vehicle that images like a given chip, re-rendered at another pose.

A generator that has never seen a vehicle cannot know where its front is; the simulator can. A
:class:`ProxyBank` is a fixed family of procedural vehicles (seeds far from every prior corpus's).
:meth:`ProxyBank.retrieve` renders each at the chip's own pose and keeps the one whose render correlates
best with the chip (both blurred, so speckle does not decide; Pearson in decibels, so any affine map of
them scores the same). :meth:`ProxyBank.render` draws it at any pose: shadow, layover and lit faces move
as the physics says, which a footprint turned in the image plane cannot show. The proxy brings the
geometry of a view; the input chip must bring the identity.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter

from sar_zero123.domain import to_decibels
from sar_zero123.sim.procedural import make_procedural_target
from sar_zero123.sim.render import render_chip
from sar_zero123.sim.targets import Target

__all__ = [
    "POSE_BUCKET_DEG", "PROXY_FIRST_SEED", "ProxyBank", "ProxyMatch", "blurred_correlation",
    "shifted_correlation",
]  # fmt: skip

#: First procedural seed of the default bank: above every seed a prior corpus of this package draws
#: (``write_prior_corpus`` numbers its vehicles from 0), so a bank vehicle is never a training vehicle.
PROXY_FIRST_SEED = 1_000_000
_MAX_BANK = 100_000
#: Largest bank fitted without a learned shortlist: each fit renders every vehicle, so its time grows with
#: the bank; a larger bank needs a ``retrieval``.
MAX_RENDERED_BANK = 10_000
#: Largest fit blur: a quarter of a 64-pixel chip (a wider blur leaves no structure to fit, and its filter
#: grows with it).
MAX_BLUR_SIGMA_PX = 16.0
#: A shortlisting bank renders every vehicle once per pose bucket of this many degrees (azimuth and
#: depression) and keeps the renders for the chips near that pose.
POSE_BUCKET_DEG = 5.0
#: Pose buckets kept per bank (each about 2 MB for 1,000 vehicles at 64 px), the least recently used dropped.
_MAX_POSE_BUCKETS = 64


def blurred_correlation(chip: np.ndarray, renders: np.ndarray, blur_sigma_px: float) -> np.ndarray:
    """Pearson correlation of one image ``(S, S)`` with each of a stack ``(N, S, S)``, all blurred first.

    Returns:
        ``(N,)`` float64 correlations in [-1, 1] (0 for a constant image).

    Raises:
        ValueError: If the shapes do not match or the blur is negative.
    """
    chip = np.asarray(chip, dtype=np.float64)
    renders = np.asarray(renders, dtype=np.float64)
    if chip.ndim != 2 or renders.ndim != 3 or renders.shape[1:] != chip.shape:
        raise ValueError(
            f"chip (S, S) and renders (N, S, S) must match, got {chip.shape} and {renders.shape}"
        )
    if not blur_sigma_px >= 0.0:
        raise ValueError(f"blur_sigma_px: expected a value >= 0, got {blur_sigma_px!r}")
    if blur_sigma_px > 0:
        chip = gaussian_filter(chip, blur_sigma_px)
        renders = gaussian_filter(renders, (0.0, blur_sigma_px, blur_sigma_px))
    a = (chip - chip.mean()).ravel()
    b = renders.reshape(len(renders), -1)
    b = b - b.mean(axis=1, keepdims=True)
    norm = np.sqrt((a * a).sum() * (b * b).sum(axis=1))
    return np.where(norm > 0, b @ a / np.maximum(norm, 1e-300), 0.0)


def shifted_correlation(
    chip: np.ndarray, renders: np.ndarray, blur_sigma_px: float, max_shift_px: int
) -> tuple[np.ndarray, np.ndarray]:
    """The best Pearson correlation of a blurred image with each blurred render circularly shifted by up to
    ``max_shift_px`` along each axis, and that shift.

    A real chip's target need not sit at its centre. A circular shift keeps an image's mean and norm, so every
    shift's correlation is one FFT cross-correlation of the mean-free images over the two norms.

    Returns:
        ``(scores, shifts)``: ``(N,)`` correlations and ``(N, 2)`` integer ``(rows, columns)`` shifts; a
        render ``np.roll``-ed by its shift (axes 0, 1) correlates with the chip by its score.

    Raises:
        ValueError: If the shapes do not match, the blur is negative or the shift is not in [0, S / 4].
    """
    largest = np.shape(chip)[-1] // 4
    whole = not isinstance(max_shift_px, bool) and int(max_shift_px) == max_shift_px
    if not (whole and 0 <= max_shift_px <= largest):
        raise ValueError(f"max_shift_px: expected an integer in [0, {largest}], got {max_shift_px!r}")
    if max_shift_px == 0:
        scores = blurred_correlation(chip, renders, blur_sigma_px)
        return scores, np.zeros((len(scores), 2), dtype=np.int64)
    blurred_correlation(chip, renders[:1], blur_sigma_px)  # the same checks
    a = np.asarray(chip, dtype=np.float64)
    b = np.asarray(renders, dtype=np.float64)
    if blur_sigma_px > 0:
        a = gaussian_filter(a, blur_sigma_px)
        b = gaussian_filter(b, (0.0, blur_sigma_px, blur_sigma_px))
    a = a - a.mean()
    b = b - b.mean(axis=(1, 2), keepdims=True)
    norm = np.sqrt((a * a).sum() * (b * b).sum(axis=(1, 2)))  # (N,)
    # c[n, dy, dx] = sum_y,x a[y, x] * b[n, y - dy, x - dx]: the render rolled by (dy, dx) against the chip
    cross = np.fft.irfft2(np.fft.rfft2(a)[None] * np.conj(np.fft.rfft2(b)), s=a.shape)
    offsets = np.arange(-max_shift_px, max_shift_px + 1)
    window = cross[:, offsets % a.shape[0]][:, :, offsets % a.shape[1]]  # (N, 2k + 1, 2k + 1)
    flat = window.reshape(len(b), -1)
    best = np.argmax(flat, axis=1)
    scores = np.where(norm > 0, flat[np.arange(len(b)), best] / np.maximum(norm, 1e-300), 0.0)
    shifts = np.stack([offsets[best // len(offsets)], offsets[best % len(offsets)]], axis=1)
    return scores, shifts.astype(np.int64)


@dataclass(frozen=True)
class ProxyMatch:
    """The bank vehicle retrieved for one chip.

    Attributes:
        index: Its position in the bank.
        seed: Its procedural seed (``first_seed + index``).
        score: Its blurred correlation with the chip.
        shift_px: ``(rows, columns)`` by which its renders are rolled onto the chip's target.
    """

    index: int
    seed: int
    score: float
    shift_px: tuple[int, int] = (0, 0)


class ProxyBank:
    """A family of procedural vehicles to fit to a chip (:meth:`retrieve`) and re-render (:meth:`render`).

    Args:
        num_vehicles: Vehicles in the bank: more fit a chip better and cost one render each per fit.
        first_seed: Procedural seed of vehicle 0; vehicle ``k`` is ``first_seed + k``.
        render_seed: Seed of the clutter under every render, so a proxy is the same bytes on every call.
        max_shift_px: Largest shift per axis of a render onto the chip's target (:func:`shifted_correlation`).
        shortlist: 0 fits exhaustively at the chip's exact pose. ``k > 0``: every vehicle is rendered once per
            pose bucket (:data:`POSE_BUCKET_DEG`, kept), the ``k`` best by a coarse correlation are rendered
            at the exact pose and scored; the others score ``-inf``.
        retrieval: A learned shortlist for this bank (``model.retrieval.ProxyRetrievalNet``): with
            ``shortlist = k`` its ``k`` best-ranked vehicles are scored, and no pose bucket is rendered.

    Raises:
        ValueError: Naming the argument, for a size outside [1, 100000], a negative seed or blur, or a
            shortlist outside [0, num_vehicles].
    """

    def __init__(
        self,
        num_vehicles: int = 1000,
        first_seed: int = PROXY_FIRST_SEED,
        blur_sigma_px: float = 1.5,
        render_seed: int = 0,
        max_shift_px: int = 0,
        shortlist: int = 0,
        retrieval: Any = None,
    ) -> None:
        if isinstance(max_shift_px, bool) or int(max_shift_px) != max_shift_px or not 0 <= max_shift_px <= 16:
            raise ValueError(f"max_shift_px: expected an integer in [0, 16], got {max_shift_px!r}")
        if (
            isinstance(num_vehicles, bool)
            or int(num_vehicles) != num_vehicles
            or not 1 <= num_vehicles <= _MAX_BANK
        ):
            raise ValueError(f"num_vehicles: expected an integer in [1, {_MAX_BANK}], got {num_vehicles!r}")
        if isinstance(first_seed, bool) or int(first_seed) != first_seed or first_seed < 0:
            raise ValueError(f"first_seed: expected an integer >= 0, got {first_seed!r}")
        if not (np.isfinite(blur_sigma_px) and 0.0 <= blur_sigma_px <= MAX_BLUR_SIGMA_PX):
            raise ValueError(
                f"blur_sigma_px: expected a value in [0, {MAX_BLUR_SIGMA_PX:g}] pixels, got {blur_sigma_px!r}"
            )
        if isinstance(render_seed, bool) or int(render_seed) != render_seed or render_seed < 0:
            raise ValueError(f"render_seed: expected an integer >= 0, got {render_seed!r}")
        self.num_vehicles = int(num_vehicles)
        self.first_seed = int(first_seed)
        self.blur_sigma_px = float(blur_sigma_px)
        self.render_seed = int(render_seed)
        if isinstance(shortlist, bool) or int(shortlist) != shortlist or not 0 <= shortlist <= num_vehicles:
            raise ValueError(
                f"shortlist: expected an integer in [0, num_vehicles = {num_vehicles}], got {shortlist!r}"
            )
        self.max_shift_px = int(max_shift_px)
        self.shortlist = int(shortlist)
        if retrieval is not None:
            ranked = getattr(retrieval, "bank", None)
            mine = {"num_vehicles": self.num_vehicles, "first_seed": self.first_seed,
                    "blur_sigma_px": self.blur_sigma_px, "render_seed": self.render_seed}  # fmt: skip
            if ranked != mine:
                raise ValueError(f"retrieval: ranks the bank {ranked}, not this bank {mine}")
        self.retrieval = retrieval
        self._targets: dict[int, Target] = {}
        self._buckets: OrderedDict[tuple[int, int, int], np.ndarray] = OrderedDict()

    def target(self, index: int) -> Target:
        """Bank vehicle ``index`` (built on first use, then kept)."""
        if isinstance(index, bool) or int(index) != index or not 0 <= index < self.num_vehicles:
            raise ValueError(f"index: expected an integer in [0, {self.num_vehicles}), got {index!r}")
        index = int(index)
        if index not in self._targets:
            self._targets[index] = make_procedural_target(self.first_seed + index)
        return self._targets[index]

    def render(
        self,
        index: int,
        azimuth_deg: float,
        depression_deg: float,
        size: int = 64,
        shift_px: tuple[int, int] = (0, 0),
    ) -> np.ndarray:
        """Bank vehicle ``index`` at a pose: a peak-normalised magnitude chip ``(size, size)`` in [0, 1].

        The clutter is drawn from ``render_seed``; the chip is rolled by a fit's ``shift_px`` (the target's
        place in the scene does not turn with its heading).
        """
        return self.render_target(self.target(index), azimuth_deg, depression_deg, size, shift_px)

    def render_target(
        self,
        target: Target,
        azimuth_deg: float,
        depression_deg: float,
        size: int = 64,
        shift_px: tuple[int, int] = (0, 0),
    ) -> np.ndarray:
        """Any vehicle rendered as the bank renders its own (:meth:`render`): a perfect proxy of it."""
        generator = np.random.default_rng(self.render_seed)
        chip = render_chip(target, float(azimuth_deg) % 360.0, float(depression_deg), size, generator)
        return np.roll(chip, tuple(int(v) for v in shift_px), axis=(0, 1)) if any(shift_px) else chip

    def scores(
        self,
        chip_decibels: np.ndarray,
        azimuth_deg: float,
        depression_deg: float,
        exclude: Sequence[int] = (),
    ) -> np.ndarray:
        """Every bank vehicle's blurred correlation ``(num_vehicles,)`` with a chip, each rendered at the
        chip's pose and shifted onto its target.

        Args:
            chip_decibels: The chip ``(S, S)`` in decibels or any affine map of them.
            exclude: Bank indices never to retrieve (scored ``-inf``): a leave-one-out draw.

        Raises:
            ValueError: For a chip that is not square, 2-D and finite.
        """
        return self.scores_and_shifts(chip_decibels, azimuth_deg, depression_deg, exclude)[0]

    def scores_and_shifts(
        self,
        chip_decibels: np.ndarray,
        azimuth_deg: float,
        depression_deg: float,
        exclude: Sequence[int] = (),
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`scores` and each vehicle's ``(rows, columns)`` shift onto the chip ``(num_vehicles, 2)``."""
        chip = np.asarray(chip_decibels, dtype=np.float64)
        if chip.ndim != 2 or chip.shape[0] != chip.shape[1] or not np.isfinite(chip).all():
            raise ValueError(f"chip_decibels: expected a finite square (S, S) image, got shape {chip.shape}")
        size = chip.shape[0]
        excluded = [int(k) for k in exclude if 0 <= int(k) < self.num_vehicles]
        candidates = np.arange(self.num_vehicles)
        if self.shortlist and self.retrieval is not None:  # the learned shortlist, then the exact fit
            ranked = self.retrieval.rank(chip, azimuth_deg, depression_deg)
            ranked = ranked[~np.isin(ranked, excluded)]
            candidates = np.sort(ranked[: self.shortlist])
        elif self.shortlist:  # the vehicles that fit best near this pose, then the exact fit among them
            features = self.bucket_features(azimuth_deg, depression_deg, size)
            coarse = features @ self.coarse_features(chip[None])[0]
            coarse[excluded] = -np.inf
            candidates = np.sort(np.argsort(-coarse, kind="stable")[: self.shortlist])
        renders = np.stack(
            [to_decibels(self.render(int(k), azimuth_deg, depression_deg, size)) for k in candidates]
        )
        found, found_shifts = shifted_correlation(chip, renders, self.blur_sigma_px, self.max_shift_px)
        scores = np.full(self.num_vehicles, -np.inf)
        shifts = np.zeros((self.num_vehicles, 2), dtype=np.int64)
        scores[candidates], shifts[candidates] = found, found_shifts
        scores[excluded] = -np.inf
        return scores, shifts

    def coarse_features(self, images: np.ndarray) -> np.ndarray:
        """Blurred, 2 x 2 pooled, mean-free, unit-norm images ``(N, S * S / 4)`` float32, whose dot products
        are the pooled images' Pearson correlations."""
        images = np.asarray(images, dtype=np.float64)
        if self.blur_sigma_px > 0:
            images = gaussian_filter(images, (0.0, self.blur_sigma_px, self.blur_sigma_px))
        n, size = images.shape[0], images.shape[-1] // 2 * 2
        pooled = images[:, :size, :size].reshape(n, size // 2, 2, size // 2, 2).mean(axis=(2, 4))
        pooled = pooled.reshape(n, -1)
        pooled -= pooled.mean(axis=1, keepdims=True)
        norm = np.linalg.norm(pooled, axis=1, keepdims=True)
        return np.where(norm > 0, pooled / np.maximum(norm, 1e-300), 0.0).astype(np.float32)

    def bucket_features(self, azimuth_deg: float, depression_deg: float, size: int) -> np.ndarray:
        """Every vehicle's coarse features at the centre of the pose's bucket (rendered once, then kept)."""
        turns = int(round(360.0 / POSE_BUCKET_DEG))
        key = (int(round(float(azimuth_deg) / POSE_BUCKET_DEG)) % turns,
               int(round(float(depression_deg) / POSE_BUCKET_DEG)), int(size))  # fmt: skip
        if key in self._buckets:
            self._buckets.move_to_end(key)
            return self._buckets[key]
        azimuth = key[0] * POSE_BUCKET_DEG
        depression = min(max(key[1] * POSE_BUCKET_DEG, 1.0), 89.0)
        renders = np.stack(
            [to_decibels(self.render(k, azimuth, depression, size)) for k in range(self.num_vehicles)]
        )
        self._buckets[key] = self.coarse_features(renders)
        while len(self._buckets) > _MAX_POSE_BUCKETS:
            self._buckets.popitem(last=False)
        return self._buckets[key]

    def retrieve(
        self,
        chip_decibels: np.ndarray,
        azimuth_deg: float,
        depression_deg: float,
        exclude: Sequence[int] = (),
    ) -> ProxyMatch:
        """The bank vehicle whose render at the chip's pose correlates best with the chip (:meth:`scores`)."""
        scores, shifts = self.scores_and_shifts(chip_decibels, azimuth_deg, depression_deg, exclude)
        best = int(np.argmax(scores))
        shift = (int(shifts[best, 0]), int(shifts[best, 1]))
        return ProxyMatch(index=best, seed=self.first_seed + best, score=float(scores[best]), shift_px=shift)
