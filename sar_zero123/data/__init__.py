"""SAR data layer: MSTAR (raw and image folders), MSTAR-OOD splits, SAMPLE, dB scaling, view pairs.

Public names (see ``docs/ARCHITECTURE.md``)::

    read_mstar_raw(path) -> MSTARChip
    ChipRecord, load_index(root) -> list[ChipRecord], write_index(records, root)
    split_records(records, protocol, seed=0), prepare_splits(data, protocol, work_dir, seed=0)
    load_magnitude(path), center_crop_resize(image, size=128)
    DecibelScaling; to_decibels, from_decibels, unit_to_signed, signed_to_unit, center_crop,
    INDEX_COLUMNS (defined in sar_zero123.domain, re-exported here)
    ChipDataset, ViewPairDataset, wrap_azimuth_deg
    load_sample(root) -> list[SamplePair]
"""

from sar_zero123.domain import (
    INDEX_COLUMNS,
    INDEX_FILENAME,
    center_crop,
    from_decibels,
    signed_to_unit,
    to_decibels,
    unit_to_signed,
)

from .datasets import ChipDataset, load_chip, resolve_class_names
from .images import MIN_CHIP_SIZE, center_crop_resize, load_magnitude
from .index import ChipRecord, class_names_of, load_index, write_index
from .mstar_raw import MSTARChip, read_mstar_header, read_mstar_raw, target_class_from_type
from .sample import SamplePair, load_sample, parse_sample_name
from .scaling import (
    MSTAR_RAW_MAX_DB,
    SCALING_CHOICES,
    SCALING_FILE,
    UNIT_MAGNITUDE_MAX_DB,
    ZERO_MAGNITUDE_DB,
    DecibelScaling,
    check_magnitude,
)
from .splits import PROTOCOLS, check_protocol, ood_validation_intervals, prepare_splits, split_records
from .view_pairs import (
    MixedPairs,
    ViewPairDataset,
    subsample_objects,
    train_validation_pairs,
    wrap_azimuth_deg,
)

__all__ = [
    "INDEX_COLUMNS",
    "INDEX_FILENAME",
    "MIN_CHIP_SIZE",
    "MSTAR_RAW_MAX_DB",
    "PROTOCOLS",
    "UNIT_MAGNITUDE_MAX_DB",
    "ZERO_MAGNITUDE_DB",
    "check_magnitude",
    "check_protocol",
    "ChipDataset",
    "ChipRecord",
    "DecibelScaling",
    "SCALING_CHOICES",
    "SCALING_FILE",
    "MSTARChip",
    "SamplePair",
    "MixedPairs",
    "ViewPairDataset",
    "center_crop",
    "center_crop_resize",
    "class_names_of",
    "from_decibels",
    "load_chip",
    "load_index",
    "load_magnitude",
    "load_sample",
    "ood_validation_intervals",
    "parse_sample_name",
    "prepare_splits",
    "read_mstar_header",
    "read_mstar_raw",
    "resolve_class_names",
    "signed_to_unit",
    "split_records",
    "target_class_from_type",
    "to_decibels",
    "subsample_objects",
    "train_validation_pairs",
    "unit_to_signed",
    "wrap_azimuth_deg",
    "write_index",
]
