"""Scattering centres of the simulated targets and their aspect-dependent strength.

A target's signature is a set of point scattering centres (the attributed-scattering-centre view):

- ``DIHEDRAL``: the fold between a vertical face and the ground or deck; it retro-reflects over all
  elevations, but only near broadside of the face in azimuth (the "broadside flash").
- ``CURVED``: the specular line of a horizontal cylinder, lit perpendicular to its axis.
- ``EDGE``: diffraction from top edges, weaker and broader in aspect.
- ``CORNER``: corners and small concave details, bright over a wide cone.
- ``SURFACE``: weak diffuse points on top surfaces with random amplitude and phase (texture).

A face is sampled as points spaced well below the resolution, so their coherent sum behaves like the
face (bright at broadside, speckle-like off it); the azimuth lobe adds the aperture integration of the
flash that point sampling alone misses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sar_zero123.sim.primitives import Box, HorizontalCylinder, Primitive, VerticalCylinder, Wedge

__all__ = [
    "DIHEDRAL",
    "CURVED",
    "EDGE",
    "CORNER",
    "SURFACE",
    "FLASH_LOBE_DEG",
    "ScattererSet",
    "aspect_gain",
    "sinc_envelope",
    "primitive_scatterers",
    "detail_scatterers",
]

DIHEDRAL, CURVED, EDGE, CORNER, SURFACE = 0, 1, 2, 3, 4

# Lobe width (first null of the sinc) of the azimuth flash of a long face or barrel. A 0.3 m resolution
# at X band (wavelength 3.1 cm) needs about lambda / (2 * 0.3 m) = 3 deg of synthetic aperture, and
# the image of a face integrates its flash over that aperture.
FLASH_LOBE_DEG = 3.0
_POINT_SPACING_M = 0.25  # face and barrel sampling, below the 0.3 m resolution
_EDGE_SPACING_M = 0.5
_SURFACE_DENSITY_PER_M2 = 20.0
_FOLD_TO_GROUND_BELOW_M = 0.8  # faces starting lower than this form a dihedral with the ground
# Amplitudes (a scatterer of amplitude 1 images to a peak of 1): dihedrals and concave details > edges >
# diffuse surface; the diffuse and detail levels match peak-normalised chips to MSTAR's dB statistics.
_SURFACE_AMPLITUDE = 0.17  # Rayleigh scale of the diffuse top-surface points
_EDGE_AMPLITUDE = 0.25
_CONVEX_CORNER_AMPLITUDE = 0.5
_DETAIL_AMPLITUDE = 2.0


@dataclass(frozen=True)
class ScattererSet:
    """Point scattering centres in the vehicle frame (``u`` forward, ``v`` left, ``z`` up).

    Attributes:
        position: ``(N, 3)`` positions (m).
        normal_az_deg: ``(N,)`` azimuth of the strongest return, counter-clockwise from the nose (deg).
        normal_el_deg: ``(N,)`` its elevation above the horizon (deg).
        lobe_az_deg: ``(N,)`` azimuth lobe width (first null, :func:`aspect_gain`); ``inf``: isotropic.
        lobe_el_deg: ``(N,)`` elevation lobe width, likewise.
        amplitude: ``(N,)`` peak amplitude (linear).
        phase: ``(N,)`` intrinsic phase (rad), added to the two-way propagation phase.
        kind: ``(N,)`` one of ``DIHEDRAL``, ``CURVED``, ``EDGE``, ``CORNER``, ``SURFACE``.
    """

    position: np.ndarray
    normal_az_deg: np.ndarray
    normal_el_deg: np.ndarray
    lobe_az_deg: np.ndarray
    lobe_el_deg: np.ndarray
    amplitude: np.ndarray
    phase: np.ndarray
    kind: np.ndarray

    def __len__(self) -> int:
        return int(self.amplitude.shape[0])

    def subset(self, index: np.ndarray) -> ScattererSet:
        """The scatterers selected by an integer or boolean index array."""
        return ScattererSet(*(getattr(self, f)[index] for f in ScattererSet.__dataclass_fields__))

    @staticmethod
    def build(
        position: np.ndarray,
        normal_az_deg: np.ndarray | float,
        normal_el_deg: np.ndarray | float,
        lobe_az_deg: np.ndarray | float,
        lobe_el_deg: np.ndarray | float,
        amplitude: np.ndarray | float,
        phase: np.ndarray | float,
        kind: int,
    ) -> ScattererSet:
        """Build a set from per-point arrays or scalars broadcast to ``len(position)``."""
        position = np.asarray(position, dtype=np.float64).reshape(-1, 3)
        n = position.shape[0]

        def full(x: np.ndarray | float) -> np.ndarray:
            return np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)).copy()

        return ScattererSet(
            position=position,
            normal_az_deg=full(normal_az_deg),
            normal_el_deg=full(normal_el_deg),
            lobe_az_deg=full(lobe_az_deg),
            lobe_el_deg=full(lobe_el_deg),
            amplitude=full(amplitude),
            phase=full(phase),
            kind=np.full(n, kind, dtype=np.int8),
        )

    @staticmethod
    def concat(sets: list[ScattererSet]) -> ScattererSet:
        """Concatenate sets (order kept)."""
        return ScattererSet(
            *(np.concatenate([getattr(s, f) for s in sets]) for f in ScattererSet.__dataclass_fields__)
        )


def sinc_envelope(x: np.ndarray) -> np.ndarray:
    """``|sinc(x)|`` on the main lobe (``|x| <= 1/2``), its sidelobe envelope ``1 / (pi |x|)`` beyond.

    The image integrates a face's sinc-shaped return over about one lobe of aperture, filling the nulls;
    both pieces equal ``2 / pi`` at ``|x| = 1/2``.
    """
    ax = np.abs(x)
    return np.where(ax <= 0.5, np.abs(np.sinc(x)), 1.0 / (np.pi * np.maximum(ax, 0.5)))


def aspect_gain(scatterers: ScattererSet, radar_az_deg: float, depression_deg: float) -> np.ndarray:
    """Amplitude factor ``(N,)`` in [0, 1] of each scatterer seen from a radar at the given aspect.

    ``gain = g(d_az / lobe_az) * g(d_el / lobe_el)`` with ``g`` = :func:`sinc_envelope`, ``d_az`` the wrapped
    angle between the radar's azimuth (the chip's target azimuth) and the normal, ``d_el`` between the
    depression and the normal's elevation. Scatterers facing away (``|d_az| >= 90 deg``) return nothing
    unless isotropic in azimuth.
    """
    d_az = (radar_az_deg - scatterers.normal_az_deg + 180.0) % 360.0 - 180.0
    d_el = depression_deg - scatterers.normal_el_deg
    isotropic = ~np.isfinite(scatterers.lobe_az_deg)
    lobe_az = np.where(isotropic, 1.0, scatterers.lobe_az_deg)
    g_az = np.where(isotropic, 1.0, sinc_envelope(d_az / lobe_az) * (np.abs(d_az) < 90.0))
    return g_az * sinc_envelope(d_el / scatterers.lobe_el_deg)


def _line(start: np.ndarray, end: np.ndarray, spacing: float) -> np.ndarray:
    """Points from ``start`` to ``end`` (inclusive) at most ``spacing`` apart, ``(n, 3)``."""
    n = max(2, int(np.ceil(np.linalg.norm(end - start) / spacing)) + 1)
    return start + np.linspace(0.0, 1.0, n)[:, None] * (end - start)


def _rotate(s: np.ndarray, t: np.ndarray, yaw_deg: float) -> tuple[np.ndarray, np.ndarray]:
    yaw = np.deg2rad(yaw_deg)
    return s * np.cos(yaw) - t * np.sin(yaw), s * np.sin(yaw) + t * np.cos(yaw)


def _top_surface(
    area: float, sample: np.ndarray, rng: np.random.Generator, amplitude: float = _SURFACE_AMPLITUDE
) -> ScattererSet:
    """Diffuse points: ``sample`` holds candidate (n, 3) positions drawn uniformly on the surface."""
    n = int(rng.poisson(_SURFACE_DENSITY_PER_M2 * area))
    pts = sample[:n]
    return ScattererSet.build(
        pts,
        0.0,
        90.0,
        np.inf,
        150.0,
        amplitude * rng.rayleigh(1.0, len(pts)),
        rng.uniform(0.0, 2 * np.pi, len(pts)),
        SURFACE,
    )


def _box_scatterers(box: Box, rng: np.random.Generator) -> ScattererSet:
    half_l, half_w = box.length / 2, box.width / 2
    front_h = box.front_height if isinstance(box, Wedge) else box.height
    fold_z = 0.0 if box.z_bottom < _FOLD_TO_GROUND_BELOW_M else box.z_bottom
    sets = []
    # 1. the four vertical faces: (face centre s, t), direction along the face, normal, length, height
    faces = [
        ((half_l, 0.0), (0.0, 1.0), 0.0, box.width, front_h),
        ((-half_l, 0.0), (0.0, 1.0), 180.0, box.width, box.height),
        ((0.0, half_w), (1.0, 0.0), 90.0, box.length, max(front_h, box.height)),
        ((0.0, -half_w), (1.0, 0.0), -90.0, box.length, max(front_h, box.height)),
    ]
    for (cs, ct), (ds, dt), normal, length, face_h in faces:
        offs = np.arange(-length / 2, length / 2 + 1e-9, _POINT_SPACING_M)
        s, t = _rotate(cs + ds * offs, ct + dt * offs, box.yaw_deg)
        u, v = box.center_u + s, box.center_v + t
        # 1a. dihedral with the ground/deck, imaged at the fold line; strength grows with the
        # face height until the face is taller than the resolution cell
        base = np.stack([u, v, np.full_like(u, fold_z)], axis=1)
        sets.append(
            ScattererSet.build(
                base, normal + box.yaw_deg, 0.0, FLASH_LOBE_DEG, 90.0, min(face_h, 1.5), 0.0, DIHEDRAL
            )
        )
        # 1b. diffraction from the top edge of the face
        ends = np.arange(-length / 2, length / 2 + 1e-9, _EDGE_SPACING_M)
        local_s = cs + ds * ends
        s, t = _rotate(local_s, ct + dt * ends, box.yaw_deg)
        top = box.top_at(local_s)
        edge = np.stack([box.center_u + s, box.center_v + t, top], axis=1)
        sets.append(
            ScattererSet.build(
                edge,
                normal + box.yaw_deg,
                45.0,
                15.0,
                60.0,
                _EDGE_AMPLITUDE,
                rng.uniform(0, 2 * np.pi, len(edge)),
                EDGE,
            )
        )
    # 2. the four top corners: convex corners diffract over a wide cone around the diagonal
    cs = np.array([half_l, half_l, -half_l, -half_l])
    ct = np.array([half_w, -half_w, half_w, -half_w])
    s, t = _rotate(cs, ct, box.yaw_deg)
    corners = np.stack([box.center_u + s, box.center_v + t, box.top_at(cs)], axis=1)
    diag = np.rad2deg(np.arctan2(ct, cs)) + box.yaw_deg
    sets.append(
        ScattererSet.build(
            corners, diag, 45.0, 60.0, 90.0, _CONVEX_CORNER_AMPLITUDE, rng.uniform(0, 2 * np.pi, 4), CORNER
        )
    )
    # 3. diffuse top surface
    area = box.length * box.width
    n_max = int(_SURFACE_DENSITY_PER_M2 * area * 2 + 10)
    ls, lt = rng.uniform(-half_l, half_l, n_max), rng.uniform(-half_w, half_w, n_max)
    s, t = _rotate(ls, lt, box.yaw_deg)
    cand = np.stack([box.center_u + s, box.center_v + t, box.top_at(ls)], axis=1)
    sets.append(_top_surface(area, cand, rng))
    return ScattererSet.concat(sets)


def _vertical_cylinder_scatterers(cyl: VerticalCylinder, rng: np.random.Generator) -> ScattererSet:
    n = max(12, int(np.ceil(2 * np.pi * cyl.radius / _POINT_SPACING_M)))
    az = np.arange(n) * 360.0 / n
    # the facing generator line always lights up: lobe a little wider than the point spacing
    lobe = 1.5 * 360.0 / n
    cu = cyl.center_u + cyl.radius * np.cos(np.deg2rad(az))
    cv = cyl.center_v + cyl.radius * np.sin(np.deg2rad(az))
    fold_z = 0.0 if cyl.z_bottom < _FOLD_TO_GROUND_BELOW_M else cyl.z_bottom
    # a cylinder standing on a plane is a dihedral for every azimuth
    base = np.stack([cu, cv, np.full(n, fold_z)], axis=1)
    rim = np.stack([cu, cv, np.full(n, cyl.z_bottom + cyl.height)], axis=1)
    strength = min(cyl.height, 1.5) * np.sqrt(cyl.radius / 1.0) * 0.7
    area = np.pi * cyl.radius**2
    r = cyl.radius * np.sqrt(rng.uniform(0, 1, int(area * _SURFACE_DENSITY_PER_M2 * 2 + 10)))
    a = rng.uniform(0, 2 * np.pi, r.shape[0])
    cand = np.stack(
        [
            cyl.center_u + r * np.cos(a),
            cyl.center_v + r * np.sin(a),
            np.full_like(r, cyl.z_bottom + cyl.height),
        ],
        axis=1,
    )
    return ScattererSet.concat(
        [
            ScattererSet.build(base, az, 0.0, lobe, 90.0, strength, 0.0, DIHEDRAL),
            ScattererSet.build(rim, az, 45.0, 3 * lobe, 60.0, 0.1, rng.uniform(0, 2 * np.pi, n), EDGE),
            _top_surface(area, cand, rng),
        ]
    )


def _horizontal_cylinder_scatterers(cyl: HorizontalCylinder, rng: np.random.Generator) -> ScattererSet:
    axis = np.array([np.cos(np.deg2rad(cyl.yaw_deg)), np.sin(np.deg2rad(cyl.yaw_deg)), 0.0])
    center = np.array([cyl.center_u, cyl.center_v, cyl.z_center])
    line = _line(center - axis * cyl.length / 2, center + axis * cyl.length / 2, _POINT_SPACING_M)
    # specular line of a cylinder: narrow in azimuth (perpendicular to the axis), wide in elevation
    strength = 0.6 * np.sqrt(min(cyl.radius, 0.6) / 0.1)
    ends = np.stack([center + axis * cyl.length / 2, center - axis * cyl.length / 2])
    return ScattererSet.concat(
        [
            ScattererSet.build(line, cyl.yaw_deg + 90.0, 0.0, FLASH_LOBE_DEG, 90.0, strength, 0.0, CURVED),
            ScattererSet.build(line, cyl.yaw_deg - 90.0, 0.0, FLASH_LOBE_DEG, 90.0, strength, 0.0, CURVED),
            ScattererSet.build(
                ends,
                np.array([cyl.yaw_deg, cyl.yaw_deg + 180.0]),
                0.0,
                20.0,
                60.0,
                0.4 * strength,
                rng.uniform(0, 2 * np.pi, 2),
                CORNER,
            ),
        ]
    )


def primitive_scatterers(primitive: Primitive, rng: np.random.Generator) -> ScattererSet:
    """Scattering centres on one primitive's faces, edges, corners and top surface (vehicle frame).

    ``rng`` draws the random phases and diffuse points, seeded per target instance.

    Raises:
        TypeError: For an unknown primitive type.
    """
    if isinstance(primitive, Box):
        return _box_scatterers(primitive, rng)
    if isinstance(primitive, VerticalCylinder):
        return _vertical_cylinder_scatterers(primitive, rng)
    if isinstance(primitive, HorizontalCylinder):
        return _horizontal_cylinder_scatterers(primitive, rng)
    raise TypeError(f"unknown primitive type {type(primitive).__name__}")


def detail_scatterers(
    primitives: list[Primitive], count: int, rng: np.random.Generator, strength: float = _DETAIL_AMPLITUDE
) -> ScattererSet:
    """``count`` small bright ``CORNER`` details on the top faces of the ``Box`` primitives (fewer without
    boxes), amplitudes uniform in ``[0.3, 1] * strength``: each instance its own pattern of bright points,
    as real vehicles of one class differ by equipment."""
    boxes = [p for p in primitives if isinstance(p, Box)]
    if not boxes or count <= 0:
        return ScattererSet.build(np.zeros((0, 3)), 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, CORNER)
    areas = np.array([b.length * b.width for b in boxes])
    pick = rng.choice(len(boxes), size=count, p=areas / areas.sum())
    pts = []
    for i in pick:
        b = boxes[i]
        ls = rng.uniform(-0.45, 0.45) * b.length
        lt = rng.uniform(-0.45, 0.45) * b.width
        s, t = _rotate(np.array([ls]), np.array([lt]), b.yaw_deg)
        pts.append([b.center_u + s[0], b.center_v + t[0], float(b.top_at(np.array([ls]))[0])])
    return ScattererSet.build(
        np.array(pts),
        rng.uniform(0.0, 360.0, count),
        rng.uniform(10.0, 40.0, count),
        rng.uniform(40.0, 80.0, count),
        90.0,
        strength * rng.uniform(0.3, 1.0, count),
        rng.uniform(0, 2 * np.pi, count),
        CORNER,
    )
