"""Imaging geometry: pose, slant-plane projection with layover, radar shadow and occlusion.

Coordinates (all in metres):

- vehicle frame ``(u, v, z)``: ``u`` towards the nose, ``v`` to the left, ``z`` up;
- ground frame ``(x, y, z)``: ``x`` cross-range (image columns), ``y`` ground range increasing away from
  the radar, which is far away in the ``-y`` direction looking down at the depression angle ``psi``.

Target azimuth ``phi`` is the azimuth of the radar seen from the target, counter-clockwise (from above)
from the nose: at ``phi = 0`` the nose points at the radar, at ``phi = 90`` it sees the left side. With
the radar at the image's bottom this reproduces the MSTAR chips' look.

The chip is a slant-plane image like MSTAR's: rows are slant range ``r = y cos(psi) - z sin(psi)`` with
near range at the last row. A scatterer at height ``h`` is imaged ``h sin(psi)`` closer in slant range
than the ground below it (layover); an object of height ``h`` casts a ground shadow ``h / tan(psi)``
long behind it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sar_zero123.sim.primitives import Primitive

__all__ = ["vehicle_to_ground", "slant_range", "GroundGrid", "shadow_mask", "occluded"]


def vehicle_to_ground(points: np.ndarray, azimuth_deg: float) -> np.ndarray:
    """Rotate vehicle-frame points ``(..., 3)`` into the ground frame for a target azimuth.

    The nose direction in the ground frame is ``(-sin phi, -cos phi)`` and the left direction
    ``(cos phi, -sin phi)``, so the radar (at ``-y``) sits at azimuth ``phi`` in the vehicle frame.
    """
    phi = np.deg2rad(azimuth_deg)
    u, v, z = points[..., 0], points[..., 1], points[..., 2]
    x = -u * np.sin(phi) + v * np.cos(phi)
    y = -u * np.cos(phi) - v * np.sin(phi)
    return np.stack([x, y, z], axis=-1)


def slant_range(y: np.ndarray, z: np.ndarray, depression_deg: float) -> np.ndarray:
    """Slant range of ground-frame points: ``r = y cos(psi) - z sin(psi)`` (layover for ``z > 0``)."""
    psi = np.deg2rad(depression_deg)
    return y * np.cos(psi) - z * np.sin(psi)


class GroundGrid:
    """The ground under the chip, sampled so that ground cell ``(k, j)`` is image pixel ``(S-1-k, j)``.

    Cross-range samples are ``pixel_spacing_m`` apart, ground-range samples ``pixel_spacing_m / cos(psi)``,
    so a ground point of row ``k`` has slant range ``(k - c) * pixel_spacing_m`` with ``c = (S - 1) / 2``.
    """

    def __init__(self, size: int, pixel_spacing_m: float, depression_deg: float) -> None:
        c = (size - 1) / 2
        self.size = size
        self.tan_psi = float(np.tan(np.deg2rad(depression_deg)))
        self.dx = float(pixel_spacing_m)
        self.dy = float(pixel_spacing_m / np.cos(np.deg2rad(depression_deg)))
        self.x = (np.arange(size) - c) * self.dx  # (S,)
        self.y = (np.arange(size) - c) * self.dy  # (S,)

    def bounds(
        self, primitives: Sequence[Primitive], azimuth_deg: float, radius_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Running bounds of the solids in front of each ground cell, for shadow and occlusion.

        A ray towards the radar from height ``z`` above cell ``y`` is at height ``z + (y - y') tan(psi)``
        above an earlier cell ``y'``; it hits a convex solid with bottom ``b(y')`` and top ``t(y')`` there iff
        ``b(y') + y' tan(psi) <= z + y tan(psi) <= t(y') + y' tan(psi)``. Per primitive we keep the running
        maximum of ``t + y' tan(psi)`` and minimum of ``b + y' tan(psi)`` over ``y' <= y``, only for the cells
        within ``radius_m`` of the centre that can see a solid in front.

        Returns:
            ``(upper, lower)``, each ``(P, S, S)`` float32 indexed ``[primitive, k, j]``; ``-inf`` / ``+inf``
            where no part of that primitive lies in front.
        """
        upper = np.full((len(primitives), self.size, self.size), -np.inf, dtype=np.float32)
        lower = np.full_like(upper, np.inf)
        cols = np.flatnonzero(np.abs(self.x) <= radius_m + self.dx)
        rows = np.flatnonzero(self.y >= -radius_m - self.dy)
        if not len(cols) or not len(rows):
            return upper, lower
        gx, gy = np.meshgrid(self.x[cols], self.y[rows])  # (nk, nj) indexed [k, j]
        phi = np.deg2rad(azimuth_deg)
        # inverse of vehicle_to_ground: u = -x sin(phi) - y cos(phi), v = x cos(phi) - y sin(phi)
        u = -gx * np.sin(phi) - gy * np.cos(phi)
        v = gx * np.cos(phi) - gy * np.sin(phi)
        ramp = gy * self.tan_psi
        block = np.s_[:, rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        for i, primitive in enumerate(primitives):
            inside, bottom, top = primitive.footprint(u, v)
            upper[block][i] = np.where(inside, top + ramp, -np.inf)
            lower[block][i] = np.where(inside, bottom + ramp, np.inf)
        upper[block] = np.maximum.accumulate(upper[block], axis=1)
        lower[block] = np.minimum.accumulate(lower[block], axis=1)
        return upper, lower


def shadow_mask(grid: GroundGrid, upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Ground cells hidden from the radar, including the ground under the target: ``(S, S)`` boolean indexed
    like the **image** (row 0 = far range)."""
    q = (grid.y * grid.tan_psi)[None, :, None]  # ground point: z = 0
    # 1 mm slack: the bounds are float32 and the first cell of a footprint sits exactly on them
    hidden = np.any((upper >= q - 1e-3) & (lower <= q + 1e-3), axis=0)
    return hidden[::-1]


def occluded(
    grid: GroundGrid, upper: np.ndarray, lower: np.ndarray, points: np.ndarray, margin_cells: int = 2
) -> np.ndarray:
    """Whether scatterers ``(N, 3)`` (ground frame) are hidden from the radar by the target's solids:
    ``(N,)``.

    Only solids at least ``margin_cells`` ground cells nearer the radar count, so a point on a surface does
    not occlude itself.
    """
    j = np.rint(points[:, 0] / grid.dx + (grid.size - 1) / 2).astype(np.int64)
    k = np.rint(points[:, 1] / grid.dy + (grid.size - 1) / 2).astype(np.int64) - margin_cells
    valid = (j >= 0) & (j < grid.size) & (k >= 0) & (k < grid.size)
    jc, kc = np.clip(j, 0, grid.size - 1), np.clip(k, 0, grid.size - 1)
    q = points[:, 2] + points[:, 1] * grid.tan_psi  # (N,)
    hit = np.any((upper[:, kc, jc] >= q) & (lower[:, kc, jc] <= q), axis=0)
    return hit & valid
