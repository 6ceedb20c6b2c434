"""Render a target at a pose into a complex SAR scene and a normalised magnitude chip."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from sar_zero123.sim.geometry import GroundGrid, occluded, shadow_mask, slant_range, vehicle_to_ground
from sar_zero123.sim.imaging import (
    PIXEL_SPACING_M,
    RESOLUTION_M,
    WAVELENGTH_M,
    PointSpreadFunction,
    form_image,
)
from sar_zero123.sim.scatterers import aspect_gain
from sar_zero123.sim.targets import Target

__all__ = [
    "CALIBRATION_AMPLITUDE",
    "CLUTTER_DB",
    "NOISE_DB",
    "Scene",
    "render_scene",
    "render_chip",
    "normalize_magnitude",
]

# Fixed calibration for normalization="calibrated": the amplitude mapped to 1 (a unit scatterer
# images to 1/4), above nearly every chip peak, so only rare broadside flashes clip.
CALIBRATION_AMPLITUDE = 4.0
# Clutter and receiver-noise power per pixel relative to a unit scatterer's peak power (dB): peak-normalised
# chips then have the MSTAR chips' median level.
CLUTTER_DB = -29.5
NOISE_DB = -42.0
_MIN_GAIN = 1e-4  # scatterers weaker than this (relative to their peak) are skipped


@dataclass(frozen=True)
class Scene:
    """A rendered complex scene.

    Attributes:
        image: ``(S, S)`` complex128 slant-plane image (row 0 = far range, radar at the bottom).
        shadow: ``(S, S)`` bool, ground hidden from the radar (shadow and under the target).
        clutter_power: Mean clutter power per pixel after the PSF (linear).
        noise_power: Mean receiver-noise power per pixel after the PSF (linear).
    """

    image: np.ndarray
    shadow: np.ndarray
    clutter_power: float
    noise_power: float


def _check_pose(azimuth_deg: float, depression_deg: float, size: int) -> None:
    if not np.isfinite(azimuth_deg):
        raise ValueError(f"azimuth_deg: expected a finite angle, got {azimuth_deg!r}")
    if not 0.0 < depression_deg < 90.0:
        raise ValueError(f"depression_deg: expected a value in (0, 90), got {depression_deg!r}")
    if int(size) != size or size < 16:
        raise ValueError(f"size: expected an integer >= 16, got {size!r}")


def render_scene(
    target: Target | None,
    azimuth_deg: float,
    depression_deg: float,
    size: int = 128,
    generator: np.random.Generator | None = None,
    *,
    pixel_spacing_m: float = PIXEL_SPACING_M,
    resolution_m: float = RESOLUTION_M,
    clutter_db: float = CLUTTER_DB,
    noise_db: float = NOISE_DB,
) -> Scene:
    """Render the complex slant-plane image of a target (None: clutter only) on a clutter background.

    Stages: (1) place the target at the pose; (2) shadow and occlusion from its solids; (3)
    aspect-dependent scatterer amplitudes with the two-way phase ``-4 pi r / lambda`` of their slant
    range ``r`` (layover included); (4) Rayleigh clutter on the visible ground plus receiver noise
    everywhere; (5) coherent summation through the PSF (:func:`form_image`).

    Args:
        azimuth_deg: Target azimuth (deg); any finite value, used modulo 360.
        generator: Source of the clutter and noise; None draws fresh entropy.
        resolution_m: Nominal resolution, 1 / bandwidth (m).
        clutter_db: Mean clutter power per pixel relative to a unit scatterer's peak power (dB).
        noise_db: Mean receiver-noise power per pixel, same reference (dB).

    Raises:
        ValueError: For a non-finite azimuth, a depression outside (0, 90) or a bad size.
    """
    # 1. check inputs and set up the grids
    _check_pose(azimuth_deg, depression_deg, size)
    size = int(size)
    rng = generator if generator is not None else np.random.default_rng()
    psf = PointSpreadFunction.build(size, pixel_spacing_m, resolution_m)
    grid = GroundGrid(size, pixel_spacing_m, depression_deg)
    center = (size - 1) / 2

    # 2. shadow and occlusion from the target's solids
    if target is not None and target.primitives:
        upper, lower = grid.bounds(target.primitives, azimuth_deg, target.radius_m)
        shadow = shadow_mask(grid, upper, lower)
    else:
        shadow = np.zeros((size, size), dtype=bool)

    # 3. scatterers seen at this aspect
    rows = cols = np.zeros(0)
    amplitudes = np.zeros(0, dtype=np.complex128)
    if target is not None and len(target.scatterers):
        scat = target.scatterers
        gain = aspect_gain(scat, azimuth_deg, depression_deg) * scat.amplitude
        keep = gain > _MIN_GAIN * scat.amplitude.max()
        ground = vehicle_to_ground(scat.position[keep], azimuth_deg)
        visible = ~occluded(grid, upper, lower, ground) if target.primitives else np.ones(len(ground), bool)
        ground, gain = ground[visible], gain[keep][visible]
        r = slant_range(ground[:, 1], ground[:, 2], depression_deg)
        rows = center - r / pixel_spacing_m  # far range at the top
        cols = center + ground[:, 0] / pixel_spacing_m
        amplitudes = gain * np.exp(1j * (scat.phase[keep][visible] - 4 * np.pi * r / WAVELENGTH_M))

    # 4. clutter on the visible ground (complex Gaussian -> Rayleigh amplitude) and receiver noise,
    # scaled so their powers after the PSF are the requested levels
    gain_2d = psf.noise_gain()
    clutter_power, noise_power = 10 ** (clutter_db / 10), 10 ** (noise_db / 10)
    white = rng.standard_normal((4, size, size), dtype=np.float32)
    clutter_scale = np.where(shadow, 0.0, np.sqrt(clutter_power / (2 * gain_2d))).astype(np.float32)
    noise_scale = np.float32(np.sqrt(noise_power / (2 * gain_2d)))
    field = (white[0] * clutter_scale + white[2] * noise_scale) + 1j * (
        white[1] * clutter_scale + white[3] * noise_scale
    )

    # 5. coherent summation through the PSF
    image = form_image(psf, rows, cols, amplitudes, background=field)
    return Scene(image=image, shadow=shadow, clutter_power=clutter_power, noise_power=noise_power)


def normalize_magnitude(
    magnitude: np.ndarray,
    normalization: Literal["peak", "calibrated"] = "peak",
    calibration: float = CALIBRATION_AMPLITUDE,
) -> np.ndarray:
    """Map a magnitude image ``(S, S)`` to float32 [0, 1].

    ``"peak"`` divides by the chip's maximum, like the MSTAR JPEGs (absolute brightness lost);
    ``"calibrated"`` divides by the fixed ``calibration`` and clips at 1, so brightness compares across chips.

    Raises:
        ValueError: For an unknown ``normalization`` or a non-positive ``calibration``.
    """
    if normalization == "peak":
        peak = float(magnitude.max())
        scaled = magnitude / peak if peak > 0 else magnitude
    elif normalization == "calibrated":
        if not calibration > 0:
            raise ValueError(f"calibration: expected a positive amplitude, got {calibration!r}")
        scaled = np.minimum(magnitude / calibration, 1.0)
    else:
        raise ValueError(f"normalization: expected 'peak' or 'calibrated', got {normalization!r}")
    return scaled.astype(np.float32)


def render_chip(
    target: Target,
    azimuth_deg: float,
    depression_deg: float,
    size: int = 128,
    generator: np.random.Generator | None = None,
    *,
    normalization: Literal["peak", "calibrated"] = "peak",
    calibration: float = CALIBRATION_AMPLITUDE,
    pixel_spacing_m: float = PIXEL_SPACING_M,
    resolution_m: float = RESOLUTION_M,
    clutter_db: float = CLUTTER_DB,
    noise_db: float = NOISE_DB,
) -> np.ndarray:
    """Render a normalised magnitude chip ``(size, size)`` of a target, centred, radar at the bottom.

    See :func:`render_scene` for the physics and its arguments, :func:`normalize_magnitude` for the mapping
    to [0, 1]. The same generator state gives the same bytes.

    Raises:
        ValueError: For bad pose, size or normalization arguments.
    """
    scene = render_scene(
        target,
        azimuth_deg,
        depression_deg,
        size,
        generator,
        pixel_spacing_m=pixel_spacing_m,
        resolution_m=resolution_m,
        clutter_db=clutter_db,
        noise_db=noise_db,
    )
    return normalize_magnitude(np.abs(scene.image), normalization, calibration)
