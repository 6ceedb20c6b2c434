"""3-D solid primitives that simulated targets are built from.

Every primitive lives in the *vehicle frame*: ``u`` forward (towards the nose), ``v`` to the left,
``z`` up, metres, origin at the vehicle centre on the ground. A primitive knows two things:

- its footprint on the ground with the bottom and top height of the solid above each ground
  point (``footprint``), which the renderer uses for radar shadow and self-occlusion;
- the scattering centres on its surfaces, edges and corners (``scatterers``), see
  :mod:`sar_zero123.sim.scatterers`.
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
    """Axis-aligned (in its own yawed frame) rectangular solid.

    Attributes:
        center_u: Footprint centre along the vehicle's forward axis (m).
        center_v: Footprint centre along the vehicle's left axis (m).
        length: Extent along the primitive's own forward axis (m).
        width: Extent across it (m).
        z_bottom: Height of the bottom face above the ground (m).
        height: Vertical extent (m).
        yaw_deg: Rotation of the primitive about z relative to the vehicle, counter-clockwise.
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
        """Ground footprint with the solid's bottom and top height above each point.

        Args:
            u: Vehicle-frame forward coordinates of ground points (m).
            v: Vehicle-frame left coordinates, same shape as ``u``.

        Returns:
            ``(inside, bottom, top)``: boolean mask and heights (m), all shaped like ``u``;
            heights are only meaningful where ``inside``.
        """
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
    """Cylinder with a vertical axis (turrets, masts, fuel drums).

    Attributes:
        center_u: Axis position along the vehicle's forward axis (m).
        center_v: Axis position along the vehicle's left axis (m).
        radius: Radius (m).
        z_bottom: Height of the bottom disc (m).
        height: Length of the axis (m).
    """

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
    """Cylinder with a horizontal axis (gun barrels, wheel axles).

    Attributes:
        center_u: Centre of the axis along the vehicle's forward axis (m).
        center_v: Centre of the axis along the vehicle's left axis (m).
        radius: Radius (m).
        z_center: Height of the axis above the ground (m).
        length: Length of the axis (m).
        yaw_deg: Direction of the axis, counter-clockwise from the vehicle's forward axis.
    """

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
