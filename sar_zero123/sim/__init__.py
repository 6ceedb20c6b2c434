"""Built-in SAR target simulator: procedural vehicles, physical scattering, coherent imaging.

The embedded default dataset for the quick-start and the tests, and a source of exact ground truth
at any pose. numpy (and scipy's Taylor window) only; from the rest of the package it imports only the
domain conventions (:mod:`sar_zero123.domain`: the ``index.csv`` columns, decibels, the centre crop).

Example:
    >>> import numpy as np
    >>> from sar_zero123.sim import make_target, render_chip
    >>> chip = render_chip(make_target("TANK"), azimuth_deg=30.0, depression_deg=17.0,
    ...                    generator=np.random.default_rng(0))
    >>> chip.shape, chip.dtype, float(chip.max())
    ((128, 128), dtype('float32'), 1.0)
"""

from sar_zero123.domain import INDEX_COLUMNS
from sar_zero123.sim.dataset import chip_generator, simulate_dataset
from sar_zero123.sim.imaging import PIXEL_SPACING_M, RESOLUTION_M, WAVELENGTH_M, PointSpreadFunction
from sar_zero123.sim.render import (
    CALIBRATION_AMPLITUDE,
    Scene,
    normalize_magnitude,
    render_chip,
    render_scene,
)
from sar_zero123.sim.targets import TARGET_CLASSES, Target, make_target

__all__ = [
    "TARGET_CLASSES",
    "Target",
    "make_target",
    "render_chip",
    "render_scene",
    "Scene",
    "normalize_magnitude",
    "CALIBRATION_AMPLITUDE",
    "simulate_dataset",
    "chip_generator",
    "INDEX_COLUMNS",
    "PointSpreadFunction",
    "PIXEL_SPACING_M",
    "RESOLUTION_M",
    "WAVELENGTH_M",
]
