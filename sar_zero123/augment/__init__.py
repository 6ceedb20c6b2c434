"""Augmentations for SAR chips (paper Sec. III, Table I), in two modules by the domain they act on.

* :mod:`~sar_zero123.augment.codomain`: **co-domain** transforms of the *magnitude* in [0, 1] that change
  only pixel values, never the geometry: the random monotonic map (Algorithm 1), Rayleigh speckle
  (Eq. 17-18) and additive Gaussian noise.
* :mod:`~sar_zero123.augment.views`: the **SimCLR baselines** on the *normalised dB* image (random
  resized crop, flip, brightness/contrast jitter, Gaussian blur), the Table I presets (:data:`PRESETS`),
  ``augment_batch`` (magnitude -> co-domain transforms -> normalised dB -> dB-domain transforms) and
  ``simclr_views`` (the two views of a SimCLR positive pair).

All are batched on ``(B, C, H, W)`` tensors, on any device, with an independent random draw per sample and
an explicit ``generator``; every public name is importable from ``sar_zero123.augment``.
"""

from .codomain import (
    SpeckleMode,
    additive_gaussian,
    apply_lookup_table,
    log_speckle_stats,
    random_monotonic,
    rayleigh_speckle,
    readd_speckle,
    sample_monotonic_map,
    sample_rayleigh,
    speckle_magnitude,
)
from .views import (
    PRESETS,
    AugmentationPreset,
    Scaling,
    augment_batch,
    color_jitter,
    random_gaussian_blur,
    random_resized_crop,
    simclr_views,
)

__all__ = [
    "PRESETS",
    "AugmentationPreset",
    "Scaling",
    "SpeckleMode",
    "additive_gaussian",
    "apply_lookup_table",
    "augment_batch",
    "color_jitter",
    "log_speckle_stats",
    "random_gaussian_blur",
    "random_monotonic",
    "random_resized_crop",
    "rayleigh_speckle",
    "readd_speckle",
    "sample_monotonic_map",
    "sample_rayleigh",
    "simclr_views",
    "speckle_magnitude",
]
