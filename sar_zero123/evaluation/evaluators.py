"""Evaluator models that score generated views (paper Table III and Table IV).

Trained on real chips of every class (train split), so on MSTAR-OOD the classifier knows the held-out one:

* `SARClassifier`: a scratch ResNet-18 (`SAREncoder`) and a linear layer: the accuracy of views.
* `AzimuthRegressor`: a ResNet-18 and an MLP (256-256, sigmoid) predicting azimuth / 2pi: the azimuth
  error; its 512-d pooled features give SFD. On a frozen SimCLR encoder it is a Table IV probe.
* `DepressionRegressor` (optional): the same predicting depression / 90 deg, trained on chips at many
  depressions.

Each is saved as `evaluator.json` (kind, encoder config, classes, decibel scaling, head) and
`model.safetensors`; loading refuses an evaluator trained on other classes. Scoring is
:mod:`sar_zero123.evaluation.scoring`.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file
from torch import nn

from sar_zero123.config.json_io import read_json
from sar_zero123.data import DecibelScaling
from sar_zero123.encoder import SAREncoder, SAREncoderConfig
from sar_zero123.model.loading import load_weights_file

EVALUATOR_CONFIG_NAME = "evaluator.json"
EVALUATOR_WEIGHTS_NAME = "model.safetensors"
CLASSIFIER_DIR = "classifier"
REGRESSOR_DIR = "regressor"
PROBES_DIR = "probes"
DEPRESSION_REGRESSOR_DIR = "depression_regressor"
MAX_DEPRESSION_DEG = 90.0  # the depression regressor's sigmoid spans (0, 90) deg

__all__ = [
    "AzimuthRegressor",
    "DepressionRegressor",
    "Evaluators",
    "SARClassifier",
    "azimuth_regression_loss",
    "check_class_names",
    "depression_regression_loss",
    "load_evaluator",
    "load_evaluators",
]


def check_class_names(saved: Sequence[str], expected: Sequence[str] | None, source: str) -> None:
    """Rejects an evaluator whose class list (label order) differs from the data's (`None`: no check).

    Raises:
        ValueError: If the lists differ (in content or order), naming ``source``.
    """
    if expected is not None and list(saved) != list(expected):
        raise ValueError(
            f"evaluator {source} was trained on classes {list(saved)} but the data uses {list(expected)}; "
            f"train evaluators on this class list (train/train_evaluators.py)"
        )


def azimuth_regression_loss(predicted_fraction: torch.Tensor, azimuth_deg: torch.Tensor) -> torch.Tensor:
    """Circular regression loss `1 - cos(2pi (p - t))` on the sigmoid output `p` and target `t = az / 2pi`.

    A squared error would put 359 and 1 deg 358 deg apart; this is `2 pi^2 (p - t)^2` for small errors.

    Shape:
        `(B,)`, `(B,)` degrees (any real value) -> `(B,)` in [0, 2].
    """
    target = torch.remainder(azimuth_deg, 360.0) / 360.0
    return 1.0 - torch.cos(2.0 * math.pi * (predicted_fraction - target))


def depression_regression_loss(
    predicted_fraction: torch.Tensor, depression_deg: torch.Tensor
) -> torch.Tensor:
    """Squared error `(p - d / 90)^2` of the sigmoid output `p` against the depression `d` in degrees
    (depression is not periodic on (0, 90)). `(B,)`, `(B,)` -> `(B,)`.
    """
    return (predicted_fraction - depression_deg / MAX_DEPRESSION_DEG) ** 2


class _Evaluator(nn.Module):
    """Shared parts: the SAR encoder, the metadata and the folder format."""

    kind: str = ""

    def __init__(
        self,
        encoder_config: SAREncoderConfig,
        class_names: Sequence[str],
        scaling: DecibelScaling | None = None,
    ) -> None:
        super().__init__()
        if len(class_names) == 0 or len(set(class_names)) != len(class_names):
            raise ValueError(f"class_names must be non-empty and distinct, got {list(class_names)}")
        self.encoder = SAREncoder(encoder_config)
        self.class_names = list(class_names)
        self.scaling = scaling if scaling is not None else DecibelScaling.for_unit_magnitude()
        self.metrics: dict[str, float] = {}

    @property
    def image_size(self) -> int:
        """Side of the square chips the evaluator takes."""
        return self.encoder.config.image_size

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """Pre-head features: the encoder's pooled ResNet feature. `(B, 1, S, S)` in [0, 1] -> `(B, D)`."""
        return self.encoder(images)

    def _head_config(self) -> dict[str, Any]:
        return {}

    def save_pretrained(self, directory: str | Path) -> Path:
        """Writes `evaluator.json` (kind, encoder config, classes, scaling, head, metrics) and the weights to
        ``directory`` (created), returned.
        """
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().contiguous() for k, v in self.state_dict().items()}
        save_file(state, str(directory / EVALUATOR_WEIGHTS_NAME), metadata={"format": "pt"})
        payload = {
            "kind": self.kind,
            "encoder": self.encoder.config.to_dict(),
            "class_names": self.class_names,
            "scaling": self.scaling.to_dict(),
            "head": self._head_config(),
            "metrics": self.metrics,
        }
        (directory / EVALUATOR_CONFIG_NAME).write_text(json.dumps(payload, indent=2) + "\n")
        return directory


class SARClassifier(_Evaluator):
    """ResNet-18 classifier trained from scratch on real chips (Table III "Acc."); ``scaling`` is its
    training chips' decibel scaling, stored with the weights.
    """

    kind = "classifier"

    def __init__(
        self,
        encoder_config: SAREncoderConfig,
        class_names: Sequence[str],
        scaling: DecibelScaling | None = None,
    ) -> None:
        super().__init__(encoder_config, class_names, scaling)
        if len(self.class_names) == 1:
            warnings.warn(
                f"classifier of a single class {self.class_names}: its accuracy is 100% whatever the input; "
                "train it on every class of the data (is the held-out class the only one in the split?)",
                stacklevel=2,
            )
        self.head = nn.Linear(self.encoder.feature_dim, len(self.class_names))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Class logits. `(B, 1, S, S)` -> `(B, K)`."""
        return self.head(self.features(images))


class _MLPRegressor(_Evaluator):
    """Shared parts of the regressors: the ResNet-18 body and an MLP head (``hidden_sizes``) ending in a
    sigmoid.
    """

    def __init__(
        self,
        encoder_config: SAREncoderConfig,
        class_names: Sequence[str],
        scaling: DecibelScaling | None = None,
        hidden_sizes: Sequence[int] = (256, 256),
    ) -> None:
        super().__init__(encoder_config, class_names, scaling)
        if len(hidden_sizes) == 0 or min(hidden_sizes) < 1:
            raise ValueError(f"hidden_sizes must be non-empty positive widths, got {list(hidden_sizes)}")
        self.hidden_sizes = [int(width) for width in hidden_sizes]
        layers: list[nn.Module] = []
        width = self.encoder.feature_dim
        for hidden in self.hidden_sizes:
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        layers += [nn.Linear(width, 1), nn.Sigmoid()]
        self.head = nn.Sequential(*layers)

    def _head_config(self) -> dict[str, Any]:
        return {"hidden_sizes": self.hidden_sizes}

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """The sigmoid output in (0, 1): the predicted angle as a fraction of its range. `(B, 1, S, S)` ->
        `(B,)`."""
        return self.head(self.features(images)).squeeze(1)


class AzimuthRegressor(_MLPRegressor):
    """ResNet-18 + MLP azimuth regressor with sigmoid output = azimuth / 2pi (Table III "Az. err.", SFD)."""

    kind = "azimuth_regressor"

    def predict_azimuth_deg(self, images: torch.Tensor) -> torch.Tensor:
        """Predicted azimuth in degrees, [0, 360). `(B, 1, S, S)` -> `(B,)`."""
        return torch.remainder(self(images) * 360.0, 360.0)


class DepressionRegressor(_MLPRegressor):
    """ResNet-18 + MLP depression regressor, sigmoid output = depression / 90 deg ("Dep. err."): every
    prediction lies in (0, 90) deg, the only depressions a chip can have.
    """

    kind = "depression_regressor"

    def predict_depression_deg(self, images: torch.Tensor) -> torch.Tensor:
        """Predicted depression in degrees, (0, 90). `(B, 1, S, S)` -> `(B,)`."""
        return self(images) * MAX_DEPRESSION_DEG


EVALUATOR_KINDS = {model.kind: model for model in (SARClassifier, AzimuthRegressor, DepressionRegressor)}


def load_evaluator(
    directory: str | Path,
    class_names: Sequence[str] | None = None,
    device: str | torch.device = "cpu",
) -> SARClassifier | AzimuthRegressor | DepressionRegressor:
    """Loads an evaluator folder written by `save_pretrained`, in eval mode, with `metrics` restored.

    Raises:
        FileNotFoundError: If a file is missing.
        ValueError: For an unknown kind, a class list other than ``class_names``, an `evaluator.json` that
            is not valid JSON or lacks a field, or weights that are unreadable or do not fit (naming the
            file).
    """
    directory = Path(directory)
    for path in (directory / EVALUATOR_CONFIG_NAME, directory / EVALUATOR_WEIGHTS_NAME):
        if not path.is_file():
            raise FileNotFoundError(f"evaluator checkpoint not found: {path}")
    config_path = directory / EVALUATOR_CONFIG_NAME
    fields = ("kind", "encoder", "class_names", "scaling", "head")
    payload = read_json(config_path, what=f"an evaluator description {list(fields)}")
    if not isinstance(payload, dict) or any(key not in payload for key in fields):
        found = sorted(payload) if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(f"{config_path}: expected a JSON object with the fields {list(fields)}, got {found}")
    check_class_names(payload["class_names"], class_names, str(directory))
    if payload["kind"] not in EVALUATOR_KINDS:
        raise ValueError(f"{directory}: unknown evaluator kind {payload['kind']!r}")
    try:
        encoder_config = SAREncoderConfig.from_dict(payload["encoder"])
        scaling = DecibelScaling.from_dict(payload["scaling"])
        model = EVALUATOR_KINDS[payload["kind"]](
            encoder_config, payload["class_names"], scaling, **payload["head"]
        )
    except (AttributeError, TypeError, ValueError) as error:
        raise ValueError(f"{config_path}: not a valid evaluator description ({error})") from None
    weights_path = directory / EVALUATOR_WEIGHTS_NAME
    load_weights_file(model, weights_path, f"the evaluator in {str(directory)!r}", device)
    model.metrics = dict(payload.get("metrics", {}))
    return model.to(device).eval()


@dataclass
class Evaluators:
    """The evaluator set written by `train/train_evaluators.py`.

    Attributes:
        classifier: Scratch ResNet-18 classifier.
        regressor: Scratch azimuth regressor (its features give SFD).
        probes: Table IV azimuth regressors on frozen SimCLR encoders, by name.
        depression_regressor: Or None where trained without chips at several depressions.
    """

    classifier: SARClassifier
    regressor: AzimuthRegressor
    probes: dict[str, AzimuthRegressor] = field(default_factory=dict)
    depression_regressor: DepressionRegressor | None = None

    @property
    def class_names(self) -> list[str]:
        """Class names in label order."""
        return self.classifier.class_names

    @property
    def image_size(self) -> int:
        """Chip side the evaluators take."""
        return self.classifier.image_size

    def azimuth_regressors(self) -> dict[str, AzimuthRegressor]:
        """All azimuth regressors for Table IV: `"scratch"` first, then the probes."""
        return {"scratch": self.regressor, **self.probes}


def load_evaluators(
    directory: str | Path,
    class_names: Sequence[str] | None = None,
    device: str | torch.device = "cpu",
) -> Evaluators:
    """Loads `DIR/classifier`, `DIR/regressor`, every `DIR/probes/<name>` and `DIR/depression_regressor`.

    The depression regressor is optional and may come from another chip folder (its class list is not
    checked), but its decibel scaling must be the classifier's: it scores the same views.

    Raises:
        FileNotFoundError: If the classifier or regressor is missing.
        ValueError: For a class-list mismatch, evaluators with different class lists, image sizes or (the
            depression regressor) decibel scalings.
    """
    directory = Path(directory)
    classifier = load_evaluator(directory / CLASSIFIER_DIR, class_names, device)
    regressor = load_evaluator(directory / REGRESSOR_DIR, classifier.class_names, device)
    if not isinstance(classifier, SARClassifier) or not isinstance(regressor, AzimuthRegressor):
        raise ValueError(
            f"{directory}: expected a classifier in {CLASSIFIER_DIR}/ and a regressor in {REGRESSOR_DIR}/"
        )
    probes: dict[str, AzimuthRegressor] = {}
    probes_dir = directory / PROBES_DIR
    if probes_dir.is_dir():
        for probe_dir in sorted(p for p in probes_dir.iterdir() if (p / EVALUATOR_CONFIG_NAME).is_file()):
            probe = load_evaluator(probe_dir, classifier.class_names, device)
            if not isinstance(probe, AzimuthRegressor):
                raise ValueError(f"{probe_dir}: a probe must be an azimuth regressor")
            probes[probe_dir.name] = probe
    depression_regressor = None
    if (directory / DEPRESSION_REGRESSOR_DIR / EVALUATOR_CONFIG_NAME).is_file():
        depression_regressor = load_evaluator(directory / DEPRESSION_REGRESSOR_DIR, device=device)
        if not isinstance(depression_regressor, DepressionRegressor):
            raise ValueError(f"{directory}: expected a depression regressor in {DEPRESSION_REGRESSOR_DIR}/")
        if depression_regressor.scaling.to_dict() != classifier.scaling.to_dict():
            raise ValueError(
                f"{directory}: the depression regressor was trained with decibel scaling "
                f"{depression_regressor.scaling.to_dict()} but the classifier with "
                f"{classifier.scaling.to_dict()}; train both in one train/train_evaluators.py run"
            )
    others = (*probes.values(), *([depression_regressor] if depression_regressor is not None else []))
    sizes = {model.image_size for model in (classifier, regressor, *others)}
    if len(sizes) != 1:
        raise ValueError(f"{directory}: evaluators take different image sizes {sorted(sizes)}")
    return Evaluators(classifier, regressor, probes, depression_regressor)
