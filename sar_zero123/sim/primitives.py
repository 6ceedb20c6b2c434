"""3-D solid primitives that simulated targets are built from.

Every primitive lives in the *vehicle frame*: ``u`` forward, ``v`` to the left, ``z`` up, metres, origin
at the vehicle centre on the ground. Its ``footprint`` (bottom and top height above each ground point)
gives radar shadow and self-occlusion; its scattering centres are :mod:`sar_zero123.sim.scatterers`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Box", "Wedge", "VerticalCylinder", "HorizontalCylinder", "Primitive"]


def _to_local(
    u: np.ndarray, v: np.ndarray, center_u: float, center_v: float, yaw_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Express vehicle-frame points in a primitive's own frame (rotated by ``yaw_deg`` about z)."""
    yaw = np.deg2rad(yaw_deg)
    du, dv = u - center_u, v - center_v
    return du * np.cos(yaw) + dv * np.sin(yaw), -du * np.sin(yaw) + dv * np.cos(yaw)


@dataclass(frozen=True)
class Box:
    """Rectangular solid, axis-aligned in its own frame, yawed by ``yaw_deg`` (counter-clockwise) about z.

    Lengths and heights in metres; ``center_u``, ``center_v`` place the footprint's centre in the vehicle
    frame, ``z_bottom`` lifts the bottom face off the ground.
    """

    center_u: float
    center_v: float
    length: float
    width: float
    z_bottom: float
    height: float
    yaw_deg: float = 0.0

    def top_at(self, s: np.ndarray) -> np.ndarray:
        """Top height at local forward coordinate ``s`` (constant for a box)."""
        return np.full_like(s, self.z_bottom + self.height)

    def footprint(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground footprint of vehicle-frame points ``(u, v)`` (m): ``(inside, bottom, top)``, all shaped like
        ``u``; the heights (m) mean something only where ``inside``."""
        s, t = _to_local(u, v, self.center_u, self.center_v, self.yaw_deg)
        inside = (np.abs(s) <= self.length / 2) & (np.abs(t) <= self.width / 2)
        return inside, np.full_like(u, self.z_bottom), self.top_at(s)


@dataclass(frozen=True)
class Wedge(Box):
    """A box whose top slopes linearly along its forward axis (glacis plates, sloped noses).

    ``height`` is the top height above ``z_bottom`` at the rear end; ``front_height`` at the front.
    """

    front_height: float = 0.3

    def top_at(self, s: np.ndarray) -> np.ndarray:
        """Top height at local forward coordinate ``s``, linear from rear to front."""
        frac = np.clip(s / self.length + 0.5, 0.0, 1.0)
        return self.z_bottom + self.height + (self.front_height - self.height) * frac


@dataclass(frozen=True)
class VerticalCylinder:
    """Cylinder with a vertical axis at ``(center_u, center_v)`` (turrets, masts, fuel drums), metres."""

    center_u: float
    center_v: float
    radius: float
    z_bottom: float
    height: float

    def footprint(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """See :meth:`Box.footprint`."""
        inside = (u - self.center_u) ** 2 + (v - self.center_v) ** 2 <= self.radius**2
        return inside, np.full_like(u, self.z_bottom), np.full_like(u, self.z_bottom + self.height)


@dataclass(frozen=True)
class HorizontalCylinder:
    """Cylinder with a horizontal axis at height ``z_center`` (gun barrels, wheel axles), metres; ``yaw_deg``
    turns the axis counter-clockwise from the vehicle's forward axis."""

    center_u: float
    center_v: float
    radius: float
    z_center: float
    length: float
    yaw_deg: float = 0.0

    def footprint(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """See :meth:`Box.footprint`; the cross-section is a circle, so heights vary across it."""
        s, t = _to_local(u, v, self.center_u, self.center_v, self.yaw_deg)
        inside = (np.abs(s) <= self.length / 2) & (np.abs(t) <= self.radius)
        half_chord = np.sqrt(np.clip(self.radius**2 - t**2, 0.0, None))
        return inside, self.z_center - half_chord, self.z_center + half_chord


Primitive = Box | Wedge | VerticalCylinder | HorizontalCylinder
