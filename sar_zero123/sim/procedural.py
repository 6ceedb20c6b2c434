"""A seeded family of distinct procedural vehicles: the multi-view prior's corpus.

Unlike the eight hand-built classes of :mod:`sar_zero123.sim.targets`, vehicles are drawn from ranges
covering MSTAR-like ground vehicles: hull sizes, tracks or 2-4 axles, sloped or blunt noses, turrets,
cabs with beds, covers, shelters, radar plates, blades or cranes, antennas, stowage and details. The same
physics images them, so a procedural vehicle looks like a named one but is never one (the named classes
are the prior's unseen test vehicles). ``make_procedural_target(seed)`` is independent of every other seed.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sar_zero123.sim.primitives import Box, HorizontalCylinder, Primitive, VerticalCylinder, Wedge
from sar_zero123.sim.scatterers import ScattererSet, detail_scatterers, primitive_scatterers
from sar_zero123.sim.targets import Target

__all__ = ["PROCEDURAL_CLASS", "PROCEDURAL_SEED_KEY", "make_procedural_target", "procedural_parts"]

#: ``class_name`` of every procedural vehicle (never one of the named ``TARGET_CLASSES``).
PROCEDURAL_CLASS = "PROCEDURAL"
#: First entry of every procedural vehicle's numpy seed sequence, so its stream differs from the named
#: classes' (which start with a CRC-32 of the class name).
PROCEDURAL_SEED_KEY = 0x5A123

_SUPERSTRUCTURES = ("round_turret", "box_turret", "open_bed", "covered_bed", "shelter", "radar", "deck")
# tracked vehicles carry turrets more often, wheeled ones beds and shelters (MSTAR's mix)
_TRACKED_WEIGHTS = np.array([0.32, 0.22, 0.04, 0.04, 0.1, 0.06, 0.22])
_WHEELED_WEIGHTS = np.array([0.12, 0.08, 0.2, 0.2, 0.2, 0.1, 0.1])


def _turret(
    rng: np.random.Generator, hull_l: float, hull_w: float, deck_z: float, round_turret: bool
) -> list[Primitive]:
    """A turret on the deck, somewhere along the hull, yawed, with its barrels."""
    position = rng.choice(["front", "centre", "rear"], p=[0.2, 0.5, 0.3])
    u = {"front": 0.22, "centre": -0.05, "rear": -0.28}[position] * hull_l + rng.uniform(-0.3, 0.3)
    # most turrets point forward; some are traversed (MSTAR's turrets are mostly forward)
    yaw = float(rng.uniform(-180.0, 180.0)) if rng.uniform() < 0.25 else float(rng.normal(0.0, 8.0))
    height = rng.uniform(0.5, 1.0)
    if round_turret:
        radius = min(rng.uniform(0.75, 1.45), hull_w / 2 + 0.3)  # may overhang the tracks a little
        parts: list[Primitive] = [VerticalCylinder(u, 0.0, radius, deck_z, height)]
        front = radius
    else:
        length, width = rng.uniform(1.4, 3.0), rng.uniform(0.8, 1.15) * hull_w
        parts = [Box(u, 0.0, length, width, deck_z, height, yaw)]
        front = length / 2
    n_barrels = int(rng.choice([0, 1, 1, 1, 1, 2, 4]))
    if n_barrels == 0:
        return parts
    barrel_l = rng.uniform(1.5, 5.5) if n_barrels == 1 else rng.uniform(1.2, 2.6)
    barrel_r = rng.uniform(0.06, 0.13) if n_barrels == 1 else rng.uniform(0.03, 0.06)
    y = np.deg2rad(yaw)
    reach = front + barrel_l / 2 - 0.1
    z = deck_z + height * rng.uniform(0.4, 0.8)
    spread = 0.0 if n_barrels == 1 else rng.uniform(0.25, 0.5)
    offsets = np.linspace(-spread, spread, n_barrels) if n_barrels > 1 else np.zeros(1)
    for off in offsets:
        parts.append(
            HorizontalCylinder(
                u + reach * np.cos(y) - off * np.sin(y),
                reach * np.sin(y) + off * np.cos(y),
                barrel_r,
                z,
                barrel_l,
                yaw,
            )
        )
    return parts


class _LoadBay(NamedTuple):
    """Where a superstructure sits: its length and centre along the hull, and its floor height."""

    length: float
    center_u: float
    floor_z: float


def _running_gear(
    rng: np.random.Generator, tracked: bool, hull_l: float, hull_w: float
) -> tuple[list[Primitive], float]:
    """Two tracks or 2-4 wheel axles, and the height of the hull's bottom above them."""
    if tracked:
        track_h, track_w = rng.uniform(0.6, 1.0), rng.uniform(0.4, 0.65)
        off = hull_w / 2 - track_w / 2
        parts: list[Primitive] = [Box(0.0, s * off, hull_l, track_w, 0.0, track_h) for s in (1.0, -1.0)]
        return parts, rng.uniform(0.35, 0.5)
    n_axles = int(rng.choice([2, 3, 4], p=[0.4, 0.4, 0.2]))
    wheel_r = rng.uniform(0.4, 0.6)
    spacing = (hull_l - 2 * wheel_r - 0.4) / max(n_axles - 1, 1)
    first = hull_l / 2 - wheel_r - 0.2
    parts = [
        HorizontalCylinder(first - i * spacing, 0.0, wheel_r, wheel_r, hull_w + 0.1, 90.0)
        for i in range(n_axles)
    ]
    return parts, wheel_r + rng.uniform(0.0, 0.3)


def _truck_chassis(
    rng: np.random.Generator, hull_l: float, hull_w: float, hull_bottom: float
) -> tuple[list[Primitive], _LoadBay]:
    """A chassis frame, a cab at the front (behind an engine hood or not), and the load bay behind."""
    cab_l = rng.uniform(1.4, 2.2)
    hood_l = rng.uniform(0.9, 1.4) if rng.uniform() < 0.6 else 0.0
    cab_u = hull_l / 2 - hood_l - cab_l / 2 - 0.1
    parts: list[Primitive] = [Box(0.0, 0.0, hull_l - 0.2, 1.0, hull_bottom, 0.35)]
    parts.append(Box(cab_u, 0.0, cab_l, hull_w - 0.1, hull_bottom, rng.uniform(1.2, 1.7)))
    if hood_l:
        parts.append(Box(hull_l / 2 - hood_l / 2 - 0.1, 0.0, hood_l, hull_w - 0.5, hull_bottom, 0.75))
    load_l = max(hull_l - hood_l - cab_l - 0.5, 1.8)
    return parts, _LoadBay(load_l, -hull_l / 2 + load_l / 2 + 0.1, hull_bottom + 0.35)


def _armoured_hull(
    rng: np.random.Generator, hull_l: float, body_w: float, body_h: float, hull_bottom: float, deck_z: float
) -> tuple[list[Primitive], _LoadBay]:
    """A hull body with a sloped nose or a blunt one; the load bay is on its deck."""
    nose = rng.uniform() < 0.65
    nose_l = rng.uniform(0.8, 1.8) if nose else 0.0
    parts: list[Primitive] = [Box(-nose_l / 2, 0.0, hull_l - nose_l, body_w, hull_bottom, body_h)]
    if nose:
        parts.append(
            Wedge(
                hull_l / 2 - nose_l / 2,
                0.0,
                nose_l,
                body_w,
                hull_bottom,
                body_h,
                front_height=rng.uniform(0.15, 0.5),
            )
        )
    return parts, _LoadBay(hull_l * 0.55, -hull_l * 0.18, deck_z)


def _open_bed(rng: np.random.Generator, hull_w: float, load: _LoadBay) -> list[Primitive]:
    """A flat bed with four low walls, sometimes carrying a few crates."""
    load_l, load_u, floor_z = load
    wall_h = rng.uniform(0.4, 1.0)
    bed_w = hull_w - 0.1
    parts: list[Primitive] = [
        Box(load_u, 0.0, load_l, bed_w, floor_z, 0.06),
        Box(load_u, bed_w / 2, load_l, 0.08, floor_z, wall_h),
        Box(load_u, -bed_w / 2, load_l, 0.08, floor_z, wall_h),
        Box(load_u - load_l / 2, 0.0, 0.08, bed_w, floor_z, wall_h),
        Box(load_u + load_l / 2, 0.0, 0.08, bed_w, floor_z, wall_h),
    ]
    if rng.uniform() < 0.4:  # cargo: a few crates
        for _ in range(int(rng.integers(1, 4))):
            parts.append(
                Box(
                    load_u + rng.uniform(-0.35, 0.35) * load_l,
                    rng.uniform(-0.5, 0.5),
                    rng.uniform(0.5, 1.2),
                    rng.uniform(0.5, 1.0),
                    floor_z,
                    rng.uniform(0.3, 0.8),
                    float(rng.uniform(-20, 20)),
                )
            )
    return parts


def _radar(rng: np.random.Generator, hull_w: float, load: _LoadBay) -> list[Primitive]:
    """An equipment box with a mast carrying a yawed radar plate."""
    load_l, load_u, floor_z = load
    parts: list[Primitive] = [Box(load_u, 0.0, load_l * 0.8, hull_w - 0.2, floor_z, rng.uniform(1.0, 1.6))]
    mast_h = rng.uniform(0.6, 1.6)
    parts.append(VerticalCylinder(load_u, 0.0, 0.15, floor_z + 1.0, mast_h))
    parts.append(
        Box(
            load_u,
            0.0,
            0.12,
            rng.uniform(2.0, 3.6),
            floor_z + 1.0 + mast_h,
            rng.uniform(1.0, 1.8),
            float(rng.uniform(-90, 90)),
        )
    )
    return parts


def _engine_deck(
    rng: np.random.Generator, hull_l: float, hull_w: float, body_w: float, deck_z: float
) -> list[Primitive]:
    """A low deck with an engine box, and a blade, a crane arm, a superstructure block or nothing."""
    parts: list[Primitive] = [
        Box(
            -hull_l * rng.uniform(0.1, 0.3),
            0.0,
            rng.uniform(1.2, 2.4),
            rng.uniform(0.6, 1.0) * body_w,
            deck_z,
            rng.uniform(0.3, 0.9),
        )
    ]
    extra = rng.choice(["blade", "crane", "cabin", "none"])
    if extra == "blade":
        parts.append(
            Box(
                hull_l / 2 + 0.5,
                0.0,
                0.25,
                hull_w + rng.uniform(0.2, 1.2),
                0.0,
                rng.uniform(0.9, 1.6),
                float(rng.uniform(-8, 8)),
            )
        )
    elif extra == "crane":
        yaw = float(rng.uniform(-180, 180))
        arm_l = rng.uniform(2.5, 5.0)
        y = np.deg2rad(yaw)
        parts.append(VerticalCylinder(0.0, 0.0, 0.5, deck_z, 0.8))
        parts.append(
            HorizontalCylinder(arm_l / 2 * np.cos(y), arm_l / 2 * np.sin(y), 0.15, deck_z + 1.0, arm_l, yaw)
        )
    elif extra == "cabin":
        parts.append(
            Box(
                hull_l * rng.uniform(0.0, 0.3),
                rng.uniform(-0.5, 0.5),
                rng.uniform(1.2, 2.0),
                rng.uniform(1.2, 1.8),
                deck_z,
                rng.uniform(0.8, 1.5),
            )
        )
    return parts


def _superstructure(
    rng: np.random.Generator,
    superstructure: str,
    truck_like: bool,
    hull_l: float,
    hull_w: float,
    body_w: float,
    deck_z: float,
    load: _LoadBay,
) -> list[Primitive]:
    """The solids of one of :data:`_SUPERSTRUCTURES`: on the deck, or in the load bay of a truck."""
    if superstructure in ("round_turret", "box_turret") and not truck_like:
        return _turret(rng, hull_l, body_w, deck_z, superstructure == "round_turret")
    if superstructure == "open_bed":
        return _open_bed(rng, hull_w, load)
    if superstructure in ("covered_bed", "shelter"):
        top = rng.uniform(1.0, 1.4) if superstructure == "covered_bed" else rng.uniform(1.4, 2.0)
        return [Box(load.center_u, 0.0, load.length, hull_w - 0.1, load.floor_z, top)]
    if superstructure == "radar":
        return _radar(rng, hull_w, load)
    return _engine_deck(rng, hull_l, hull_w, body_w, deck_z)


def _fittings(
    rng: np.random.Generator,
    hull_l: float,
    hull_w: float,
    body_w: float,
    body_h: float,
    hull_bottom: float,
    deck_z: float,
) -> list[Primitive]:
    """Antennas, stowage (boxes, drums), and sometimes a rear door or stowage rack."""
    parts: list[Primitive] = []
    for _ in range(int(rng.choice([0, 0, 1, 1, 2, 3]))):
        parts.append(
            VerticalCylinder(
                rng.uniform(-0.45, 0.1) * hull_l,
                rng.uniform(-0.4, 0.4) * hull_w,
                rng.uniform(0.03, 0.06),
                deck_z,
                rng.uniform(1.0, 2.8),
            )
        )
    for _ in range(int(rng.integers(0, 4))):
        u, v = rng.uniform(-0.45, 0.45) * hull_l, rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.45) * body_w
        if rng.uniform() < 0.5:
            parts.append(VerticalCylinder(u, v, rng.uniform(0.2, 0.35), deck_z, rng.uniform(0.4, 0.9)))
        else:
            parts.append(
                Box(u, v, rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.7), deck_z, rng.uniform(0.2, 0.5))
            )
    if rng.uniform() < 0.4:
        parts.append(
            Box(
                -hull_l / 2 - 0.1,
                0.0,
                0.3,
                rng.uniform(0.5, 1.0) * body_w,
                hull_bottom,
                rng.uniform(0.4, body_h),
            )
        )
    return parts


def procedural_parts(seed: int) -> tuple[list[Primitive], int]:
    """``(primitives, detail_count)`` of procedural vehicle ``seed``, from one numpy stream keyed by it.

    The helpers draw in a fixed order (running gear, hull, superstructure, fittings, detail count);
    changing it changes every procedural vehicle, and with them the prior's training corpus.
    """
    rng = np.random.default_rng([PROCEDURAL_SEED_KEY, int(seed)])
    tracked = rng.uniform() < 0.55
    hull_l = rng.uniform(4.2, 8.2)
    hull_w = rng.uniform(2.2, 3.6)
    # 1. running gear
    parts, hull_bottom = _running_gear(rng, tracked, hull_l, hull_w)
    # 2. hull, with a sloped nose or a blunt one (or a truck's chassis and cab)
    body_w = hull_w - (rng.uniform(0.6, 1.2) if tracked else rng.uniform(0.0, 0.3))
    body_h = rng.uniform(0.6, 1.5)
    deck_z = hull_bottom + body_h
    superstructure = str(rng.choice(_SUPERSTRUCTURES, p=(_TRACKED_WEIGHTS if tracked else _WHEELED_WEIGHTS)))
    truck_like = superstructure in ("open_bed", "covered_bed", "shelter", "radar") and not tracked
    if truck_like:
        hull, load = _truck_chassis(rng, hull_l, hull_w, hull_bottom)
    else:
        hull, load = _armoured_hull(rng, hull_l, body_w, body_h, hull_bottom, deck_z)
    parts += hull
    # 3. superstructure
    parts += _superstructure(rng, superstructure, truck_like, hull_l, hull_w, body_w, deck_z, load)
    # 4. antennas, stowage (boxes, drums), and a rear door or stowage rack
    parts += _fittings(rng, hull_l, hull_w, body_w, body_h, hull_bottom, deck_z)
    detail_count = int(rng.integers(8, 22))
    return parts, detail_count


def make_procedural_target(seed: int) -> Target:
    """Procedural vehicle number ``seed`` (an integer >= 0), deterministic in it and independent of every
    other.

    Returns:
        A :class:`~sar_zero123.sim.targets.Target` with ``class_name`` :data:`PROCEDURAL_CLASS`,
        ``instance = seed`` and serial ``proc<seed>``.

    Raises:
        ValueError: If ``seed`` is not an integer >= 0.
    """
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    primitives, detail_count = procedural_parts(int(seed))
    # scatterer draws come from their own stream, so that the shape does not depend on them
    rng = np.random.default_rng([PROCEDURAL_SEED_KEY, int(seed), 1])
    scatterers = ScattererSet.concat(
        [primitive_scatterers(p, rng) for p in primitives]
        + [detail_scatterers(primitives, detail_count, rng)]
    )
    radius_m = float(np.max(np.hypot(scatterers.position[:, 0], scatterers.position[:, 1]))) + 0.3
    return Target(
        class_name=PROCEDURAL_CLASS,
        instance=int(seed),
        primitives=tuple(primitives),
        scatterers=scatterers,
        radius_m=radius_m,
    )
