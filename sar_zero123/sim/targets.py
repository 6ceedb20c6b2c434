"""Procedural vehicle-like target classes: each a few 3-D primitives of clearly different shapes (tank,
tracked carrier, open-bed truck, bulldozer, self-propelled gun, radar truck, anti-aircraft gun, scout car).
Instances differ slightly (dimensions, yaws, stowage, details), deterministically from ``(class_name,
instance)``."""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sar_zero123.sim.primitives import Box, HorizontalCylinder, Primitive, VerticalCylinder, Wedge
from sar_zero123.sim.scatterers import ScattererSet, detail_scatterers, primitive_scatterers

__all__ = ["TARGET_CLASSES", "Target", "make_target"]


@dataclass(frozen=True)
class Target:
    """A simulated target: its solid shape and its scattering centres (vehicle frame).

    Attributes:
        primitives: Solids that cast shadow and occlude.
        radius_m: Radius of a vertical cylinder about the centre that contains the target (m).
    """

    class_name: str
    instance: int
    primitives: tuple[Primitive, ...]
    scatterers: ScattererSet
    radius_m: float

    @property
    def serial(self) -> str:
        """Serial number in the index, like MSTAR's (``sim00``, ``sim01``, ...)."""
        return f"sim{self.instance:02d}"

    @property
    def target_type(self) -> str:
        """Target type in the index, like MSTAR's ``t72_tank``."""
        return f"{self.class_name.lower()}_sim"


def _tracks(length: float, width: float, height: float = 0.85, track_w: float = 0.55) -> list[Primitive]:
    off = width / 2 - track_w / 2
    return [Box(0.0, s * off, length, track_w, 0.0, height) for s in (1.0, -1.0)]


def _tank(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    hull_l, hull_w = 6.4 * k(0.03), 3.3 * k(0.03)
    turret_u = -0.4 * k(0.1)
    turret_yaw = float(rng.choice([0.0, 0.0, -6.0, 6.0]))
    barrel_l = 4.6 * k(0.03)
    yaw = np.deg2rad(turret_yaw)
    reach = 1.1 + barrel_l / 2
    parts: list[Primitive] = [
        *_tracks(hull_l, hull_w),
        Box(-0.4, 0.0, hull_l - 0.8, hull_w - 1.1, 0.4, 1.0),
        Wedge(hull_l / 2 - 0.6, 0.0, 1.2, hull_w - 1.1, 0.4, 1.0, front_height=0.35),
        VerticalCylinder(turret_u, 0.0, 1.15 * k(0.03), 1.4, 0.75),
        HorizontalCylinder(
            turret_u + reach * np.cos(yaw), reach * np.sin(yaw), 0.09, 1.85, barrel_l, turret_yaw
        ),
    ]
    if rng.uniform() < 0.6:  # external fuel drums on the rear deck
        parts += [VerticalCylinder(-hull_l / 2 + 0.5, s * 0.7, 0.3, 1.4, 0.85) for s in (1.0, -1.0)]
    return parts


def _apc(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    hull_l, hull_w = 6.7 * k(0.03), 3.1 * k(0.03)
    return [
        *_tracks(hull_l, hull_w, 0.8, 0.5),
        Box(-0.9, 0.0, hull_l - 1.8, hull_w - 0.9, 0.4, 1.3),
        Wedge(hull_l / 2 - 0.9, 0.0, 1.8, hull_w - 0.9, 0.4, 1.3, front_height=0.2),
        VerticalCylinder(0.2 * k(0.2), 0.0, 0.75, 1.7, 0.5),
        HorizontalCylinder(0.2 + 0.75 + 1.0, 0.0, 0.05, 2.0, 2.0 * k(0.05), 0.0),
        Box(-hull_l / 2 + 0.2, 0.0, 0.4, 1.4, 0.5, 0.9 * k(0.1)),  # rear doors
    ]


def _truck(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    length = 7.0 * k(0.03)
    bed_l = 3.9 * k(0.04)
    bed_u = -length / 2 + bed_l / 2 + 0.1
    bed_w = 2.4 * k(0.02)
    bed_h = 0.8 * k(0.1)
    parts: list[Primitive] = [
        Box(0.0, 0.0, length - 0.2, 1.0, 0.6, 0.35),  # chassis frame
        Box(length / 2 - 2.2, 0.0, 1.7, 2.3, 0.9, 1.3),  # cab
        Box(length / 2 - 0.7, 0.0, 1.3, 1.9, 0.9, 0.7),  # engine hood
        Box(bed_u, 0.0, bed_l, bed_w, 1.1, 0.06),  # cargo floor
        Box(bed_u, bed_w / 2, bed_l, 0.08, 1.16, bed_h),  # open bed: side walls, front wall, tailgate
        Box(bed_u, -bed_w / 2, bed_l, 0.08, 1.16, bed_h),
        Box(bed_u + bed_l / 2, 0.0, 0.08, bed_w, 1.16, bed_h),
        Box(bed_u - bed_l / 2, 0.0, 0.08, bed_w, 1.16, bed_h * 0.8),
    ]
    parts += [HorizontalCylinder(u, 0.0, 0.5, 0.5, 2.3, 90.0) for u in (length / 2 - 1.0, -0.6, -1.9)]
    if rng.uniform() < 0.5:  # canvas cover over the bed
        parts.append(Box(bed_u, 0.0, bed_l, bed_w, 1.2, 1.3))
    return parts


def _dozer(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    body_l, body_w = 4.4 * k(0.03), 2.6 * k(0.03)
    blade_w = 4.2 * k(0.04)
    blade_yaw = float(rng.uniform(-4.0, 4.0))  # angled blade
    return [
        *_tracks(body_l, body_w + 0.8, 0.9, 0.6),
        Box(0.1, 0.0, body_l - 0.2, body_w - 0.4, 0.5, 1.3),
        Box(-0.9, 0.0, 1.7, 1.7, 1.8, 1.5),  # cab
        Box(body_l / 2 + 0.9, 0.0, 0.25, blade_w, 0.0, 1.4 * k(0.05), blade_yaw),  # blade
        Box(body_l / 2 + 0.4, body_w / 2, 1.0, 0.15, 0.5, 0.25),  # push arms
        Box(body_l / 2 + 0.4, -body_w / 2, 1.0, 0.15, 0.5, 0.25),
        Box(-body_l / 2 - 0.5, 0.0, 0.8, 0.3, 0.2, 1.2),  # rear ripper
        VerticalCylinder(1.2, 0.5, 0.12, 1.8, 0.9),  # exhaust stack
    ]


def _spg(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    hull_l, hull_w = 7.3 * k(0.03), 2.9 * k(0.03)
    turret_l = 2.7 * k(0.04)
    turret_u = -hull_l / 2 + turret_l / 2 + 0.6
    barrel_l = 4.4 * k(0.03)
    return [
        *_tracks(hull_l, hull_w, 0.8, 0.5),
        Box(0.0, 0.0, hull_l - 1.0, hull_w - 0.9, 0.4, 1.0),
        Wedge(hull_l / 2 - 0.5, 0.0, 1.0, hull_w - 0.9, 0.4, 1.0, front_height=0.4),
        Box(turret_u, 0.0, turret_l, 2.5 * k(0.03), 1.4, 0.95),
        HorizontalCylinder(turret_u + turret_l / 2 + barrel_l / 2, 0.0, 0.1, 1.95, barrel_l, 0.0),
    ]


def _radar(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    length = 6.2 * k(0.03)
    antenna_yaw = float(rng.uniform(-30.0, 30.0))  # where the antenna happens to point
    shelter_u = -0.8
    return [
        Box(0.0, 0.0, length - 0.2, 1.0, 0.6, 0.35),
        Box(length / 2 - 1.0, 0.0, 1.7, 2.3, 0.9, 1.4),  # cab
        Box(shelter_u, 0.0, 3.2 * k(0.04), 2.4, 1.0, 1.6),  # equipment shelter
        VerticalCylinder(shelter_u, 0.0, 0.15, 2.6, 0.8),  # mast
        Box(shelter_u, 0.0, 0.12, 3.4 * k(0.05), 3.3, 1.6, antenna_yaw),  # antenna plate
        *[HorizontalCylinder(u, 0.0, 0.45, 0.45, 2.3, 90.0) for u in (length / 2 - 1.0, -1.2, -2.3)],
    ]


def _aagun(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    hull_l, hull_w = 6.5 * k(0.03), 3.1 * k(0.03)
    turret_u = 0.0
    yaw = float(rng.choice([0.0, 10.0, -10.0]))
    y = np.deg2rad(yaw)
    reach = 1.3 + 1.0
    parts: list[Primitive] = [
        *_tracks(hull_l, hull_w, 0.8, 0.5),
        Box(0.0, 0.0, hull_l - 0.6, hull_w - 0.9, 0.4, 1.0),
        Box(turret_u, 0.0, 2.6 * k(0.03), 2.9, 1.4, 0.8, yaw),  # wide flat turret
        Box(turret_u - 1.2 * np.cos(y), -1.2 * np.sin(y), 0.1, 1.2, 2.2, 0.8, yaw + 5.0),  # radar dish
    ]
    for off in (-0.65, -0.35, 0.35, 0.65):  # four guns
        parts.append(
            HorizontalCylinder(
                turret_u + reach * np.cos(y) - off * np.sin(y),
                reach * np.sin(y) + off * np.cos(y),
                0.04,
                2.0,
                2.0,
                yaw,
            )
        )
    return parts


def _scout(k: Callable[[float], float], rng: np.random.Generator) -> list[Primitive]:
    length, width = 5.8 * k(0.03), 2.4 * k(0.03)
    return [
        Box(-0.5, 0.0, length - 1.2, width, 0.5, 1.2),
        Wedge(length / 2 - 0.6, 0.0, 1.2, width, 0.5, 1.2, front_height=0.3),  # boat nose
        VerticalCylinder(0.1, 0.0, 0.55, 1.7, 0.5),
        HorizontalCylinder(0.1 + 0.55 + 0.7, 0.0, 0.04, 2.0, 1.4, 0.0),
        *[HorizontalCylinder(u, 0.0, 0.55, 0.55, width + 0.1, 90.0) for u in (1.5, -1.6)],
    ]


_BUILDERS: dict[str, Callable[[Callable[[float], float], np.random.Generator], list[Primitive]]] = {
    "TANK": _tank,
    "APC": _apc,
    "TRUCK": _truck,
    "DOZER": _dozer,
    "SPG": _spg,
    "RADAR": _radar,
    "AAGUN": _aagun,
    "SCOUT": _scout,
}

TARGET_CLASSES: tuple[str, ...] = tuple(_BUILDERS)
"""Names of the simulated classes, upper case like MSTAR's."""

_DETAILS_PER_CLASS = {
    "TANK": 18,
    "APC": 15,
    "TRUCK": 12,
    "DOZER": 12,
    "SPG": 18,
    "RADAR": 14,
    "AAGUN": 18,
    "SCOUT": 10,
}


def make_target(class_name: str, instance: int = 0) -> Target:
    """Build a target of a class (case-insensitive); deterministic for ``(class_name, instance)``.

    Raises:
        ValueError: If ``class_name`` is unknown or ``instance`` is negative.
    """
    name = str(class_name).upper()
    if name not in _BUILDERS:
        raise ValueError(f"class_name: unknown class {class_name!r}; expected one of {TARGET_CLASSES}")
    if int(instance) != instance or instance < 0:
        raise ValueError(f"instance: expected an integer >= 0, got {instance!r}")
    # zlib.crc32, not hash(): str hashes are salted per process
    rng = np.random.default_rng([zlib.crc32(name.encode()), int(instance)])

    def k(rel_std: float) -> float:
        """Per-instance scale factor ~ 1 + N(0, rel_std), clipped to 2 sigma."""
        return float(1.0 + rel_std * np.clip(rng.standard_normal(), -2.0, 2.0))

    primitives = tuple(_BUILDERS[name](k, rng))
    scatterers = ScattererSet.concat(
        [primitive_scatterers(p, rng) for p in primitives]
        + [detail_scatterers(list(primitives), _DETAILS_PER_CLASS[name], rng)]
    )
    # every solid has scatterers on its outline, so they bound its footprint
    radius_m = float(np.max(np.hypot(scatterers.position[:, 0], scatterers.position[:, 1]))) + 0.3
    return Target(
        class_name=name,
        instance=int(instance),
        primitives=primitives,
        scatterers=scatterers,
        radius_m=radius_m,
    )
