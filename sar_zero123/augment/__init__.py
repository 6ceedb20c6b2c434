"""Augmentations for SAR chips (paper Sec. III, Table I), by the domain they act on: :mod:`.codomain`
(the magnitude's values: Algorithm 1, Eq. 17-18, Gaussian noise) and :mod:`.views` (the SimCLR baselines
on normalised dB, the presets, ``augment_batch``, ``simclr_views``). Batched ``(B, C, H, W)`` on any device,
one draw per sample, an explicit ``generator``; every public name is importable from here.
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
