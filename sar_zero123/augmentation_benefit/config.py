"""The augmentation-benefit protocol's settings (:class:`AugmentationBenefitConfig`) and the record that
keeps a resumed folder to them (:func:`check_settings`)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.pretrained import SIM_PRIOR_ROTATED
from sar_zero123.runs.folder import field_defaults

__all__ = [
    "ARM_SELECTION_FIELDS",
    "QUICK",
    "RESULT_FILE",
    "TEST_DEPRESSION_DEG",
    "TRAIN_DEPRESSION_DEG",
    "VIEW_FILTERS",
    "AugmentationBenefitConfig",
    "check_settings",
]

#: The depression of the training chips and of the test chips.
TRAIN_DEPRESSION_DEG = 17.0

TEST_DEPRESSION_DEG = 15.0

#: Each arm's record, in its folder: an arm whose record exists is not run again.
RESULT_FILE = "result.json"


#: Fields that only add or drop arms: a resumed benchmark may change them; any other change is refused.
ARM_SELECTION_FIELDS = (
    "data", "out", "ks", "sectors", "unseen_class", "unseen_k", "strength",
    "same_azimuth_control", "eoc1_data", "eoc1_ks", "eoc1_all", "eoc1_views_per_chip", "heading_guidance",
    "view_filters", "validation_chips_per_class", "depression_guidance",
)  # fmt: skip


#: Ways of keeping fewer generated views (AugmentationBenefitConfig.view_filters).
VIEW_FILTERS = ("confident", "ratio1")


#: The reduced configuration: two K, no sector or unseen-class arms (about 30 min on 2 CPU cores, estimated).
QUICK = {"ks": [12, 48], "sectors": False, "unseen_class": None}


@dataclass
class AugmentationBenefitConfig:
    """The whole protocol; the defaults are its full configuration, ``QUICK`` the reduced one."""

    data: str = ""  # dataset folder with index.csv holding 17 and 15 deg chips
    out: str = ""  # benchmark folder: one sub-folder per arm and generator, results.json
    ks: list[int] = field(default_factory=lambda: [12, 24, 48])  # kept 17 deg chips per class
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])  # classifier seeds per arm
    sectors: bool = True  # also the missing-sector arms
    sector_deg: float = 90.0  # width of the kept azimuth sector (from 0 deg)
    unseen_class: str | None = "T72"  # class the unseen-class generator never sees (None: no variant)
    unseen_k: int = 12  # K of the unseen-class variant
    views_per_chip: int = 3  # generated views per kept chip, evenly between it and its neighbours
    # pretrained pipeline each generator is fine-tuned from: the prior that also sees the input turned by
    # d_az, whose views help by their pose where the retired sim-prior's did not (docs/results/README.md)
    pipeline: str = SIM_PRIOR_ROTATED
    finetune_steps: int = 3000  # fine-tune steps per generator (400 and 1,000 keep too little identity)
    finetune_batch_size: int = 16  # pairs per fine-tune step
    finetune_learning_rate: float = 1e-3  # AdamW learning rate of the fine-tune
    num_inference_steps: int = 10  # DDIM steps per generated view
    guidance_scale: float = 3.0  # classifier-free guidance of the generated views
    image_size: int = 64  # classifier input: centre crop in pixels at the native spacing
    classifier_steps: int = 1000  # optimisation steps per classifier (the same in every arm)
    classifier_batch_size: int = 32  # chips per classifier step
    classifier_learning_rate: float = 2e-3  # AdamW peak learning rate (cosine decay to 0)
    classifier_weight_decay: float = 5e-4  # AdamW weight decay
    max_shift_px: int = 4  # training augmentation: random shifts up to this many pixels
    quality_chips_per_class: int = 50  # 15 deg chips per class for the VAE round-trip bound
    strength: float | None = None  # also arms whose views start from the kept chip's noised latent (SDEdit)
    same_azimuth_control: bool = False  # also the plain (and strength) views at d_az = 0: what the pose adds
    heading_guidance: float | None = None  # also arms of the plain views at this heading guidance; None: no
    # also arms of the plain views filtered (VIEW_FILTERS): "confident" keeps the views the real-only
    # classifier of the same chips reads as their class, "ratio1" one view per kept chip (of views_per_chip)
    view_filters: list[str] = field(default_factory=list)
    validation_chips_per_class: int = 50  # 17 deg chips left out of an arm's K, for its validation accuracy
    # a prior corpus (write_prior_corpus, e.g. train/pretrain_prior.py's corpus/) mixed into every generator's
    # fine-tune (FinetuneConfig.rehearsal_data); None: the kept chips only. The EOC-1 arms need it
    rehearsal_data: str | None = None
    rehearsal_fraction: float = 0.25  # share of each generator's training pairs drawn from rehearsal_data
    eoc1_data: str | None = None  # folder of EOC-1's test chips (one depression): adds the EOC-1 arms
    eoc1_ks: list[int] = field(default_factory=lambda: [24])  # EOC-1 arms with K chips/class, beside all
    eoc1_all: bool = True  # also the EOC-1 arms with every 17 deg chip of the four serials
    # views per kept chip in the EOC-1 arms: 1 (at d_az = 0) or N > 1, which adds the arms ..._views{N} (at
    # d_az = 0 and N - 1 offsets spread evenly in the azimuth gap to the chip's neighbours)
    eoc1_views_per_chip: int = 1
    # also EOC-1 arms whose depression views are sampled with this depression guidance (SARZero123Pipeline's
    # pull away from the same request at the chip's own depression), ..._depression{G}; their d_el = 0
    # control is the plain one (the guidance leaves d_el = 0 requests unchanged). None: no such arms
    depression_guidance: float | None = None

    def __post_init__(self) -> None:
        for name in ("ks", "eoc1_ks"):
            if any(k < 2 for k in getattr(self, name)):
                raise ValueError(f"{name} must hold values >= 2, got {getattr(self, name)}")
        if not self.seeds:
            raise ValueError("seeds must not be empty")
        for name in ("views_per_chip", "eoc1_views_per_chip"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.sector_deg < 360.0:
            raise ValueError(f"sector_deg must lie in (0, 360), got {self.sector_deg}")
        for name in ("finetune_steps", "classifier_steps", "classifier_batch_size", "num_inference_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.strength is not None and not 0.0 < self.strength < 1.0:
            raise ValueError(f"strength must be None or in (0, 1), got {self.strength}")
        for name in ("heading_guidance", "depression_guidance"):
            value = getattr(self, name)
            if value is not None and not 0.0 < value <= 100.0:
                raise ValueError(f"{name} must be None or in (0, 100], got {value}")
        unknown = sorted(set(self.view_filters) - set(VIEW_FILTERS))
        if unknown:
            raise ValueError(f"view_filters must be among {VIEW_FILTERS}, got {unknown}")
        if not 0.0 <= self.rehearsal_fraction < 1.0:
            raise ValueError(f"rehearsal_fraction must lie in [0, 1), got {self.rehearsal_fraction}")
        if self.eoc1_data is not None and (self.rehearsal_data is None or self.rehearsal_fraction == 0.0):
            raise ValueError(
                "rehearsal_data: the EOC-1 arms ask for views at another depression, which a generator "
                "fine-tuned on 17 deg chips alone never paired; give a prior corpus "
                "(train/pretrain_prior.py's corpus/) and a rehearsal_fraction above 0"
            )


def check_settings(config: AugmentationBenefitConfig, out: Path) -> None:
    """Records the settings in ``out/settings.json``, or refuses a resume whose settings differ there.

    Raises:
        ValueError: Naming each field (outside :data:`ARM_SELECTION_FIELDS`) that differs from the record.
    """
    settings = {k: v for k, v in asdict(config).items() if k not in ARM_SELECTION_FIELDS}
    record = out / "settings.json"
    if record.is_file():
        # a setting the record lacks was made with its default (a folder written before the setting existed)
        defaults = {k: v for k, v in field_defaults(AugmentationBenefitConfig).items() if k in settings}
        recorded = {**defaults, **json.loads(record.read_text())}
        changed = sorted(k for k in settings.keys() | recorded.keys() if settings.get(k) != recorded.get(k))
        if changed:
            details = ", ".join(f"{k}: {recorded.get(k)!r} -> {settings.get(k)!r}" for k in changed)
            raise ValueError(f"out: {out} holds a benchmark with other settings ({details}); use another out")
        return
    write_json_atomic(settings, record)
