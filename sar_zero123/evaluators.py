"""Evaluator models that score generated views (paper Table III and Table IV).

Two networks exist only to measure generated images; they are trained on real chips of every class
(train split), so that on MSTAR-OOD the classifier still knows the held-out class:

* `SARClassifier`: a ResNet-18 (`SAREncoder`) trained from scratch plus a linear layer over the classes;
  it gives the classification accuracy of generated views.
* `AzimuthRegressor`: a ResNet-18 plus an MLP (256-256, sigmoid) predicting azimuth / 2pi; it gives the
  azimuth error, and its pre-head features (the 512-d pooled ResNet feature) give SFD. With a frozen
  SimCLR encoder and only the MLP trained it is a Table IV "probe".

Each model is saved as a folder with `evaluator.json` (kind, encoder config, class list, decibel scaling,
head sizes) and `model.safetensors`. Loading checks the class list so that an evaluator trained on other
classes is rejected with a clear error instead of silently scoring with mismatched labels.
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
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

from sar_zero123.data import DecibelScaling
from sar_zero123.encoder import SAREncoder, SAREncoderConfig
from sar_zero123.metrics import (
    CROP_SIZE,
    azimuth_error_deg,
    classification_accuracy,
    frechet_distance,
    kuan_ssim,
    ms_ssim,
)
from sar_zero123.paper_metrics import PAPER_SCORING_SIZE, paper_kuan_ssim, paper_ms_ssim

EVALUATOR_CONFIG_NAME = "evaluator.json"
EVALUATOR_WEIGHTS_NAME = "model.safetensors"
CLASSIFIER_DIR = "classifier"
REGRESSOR_DIR = "regressor"
PROBES_DIR = "probes"

__all__ = [
    "pose_following",
    "AzimuthRegressor",
    "Evaluators",
    "SARClassifier",
    "azimuth_regression_loss",
    "check_class_names",
    "load_evaluator",
    "load_evaluators",
    "resize_for_evaluator",
    "score_views",
]


def check_class_names(saved: Sequence[str], expected: Sequence[str] | None, source: str) -> None:
    """Rejects an evaluator whose class list differs from the data's.

    Args:
        saved: Class names the evaluator was trained with (label order).
        expected: Class names of the data being scored (label order), or `None` to skip the check.
        source: Where the evaluator came from, for the message.

    Raises:
        ValueError: If the lists differ (in content or order).
    """
    if expected is not None and list(saved) != list(expected):
        raise ValueError(
            f"evaluator {source} was trained on classes {list(saved)} but the data uses {list(expected)}; "
            f"train evaluators on this class list (train/train_evaluators.py)"
        )


def azimuth_regression_loss(predicted_fraction: torch.Tensor, azimuth_deg: torch.Tensor) -> torch.Tensor:
    """Circular regression loss `1 - cos(2pi (p - t))` on the sigmoid output `p` and target `t = az / 2pi`.

    The paper regresses azimuth / 2pi with a sigmoid head; a plain squared error would treat 359 deg and
    1 deg as 358 deg apart, so the periodic form is used (it equals `2 pi^2 (p - t)^2` for small errors).

    Args:
        predicted_fraction: Sigmoid outputs in (0, 1), read as azimuth / 360 deg.
        azimuth_deg: True azimuths in degrees (any real value; taken modulo 360).

    Returns:
        Per-sample loss in [0, 2].

    Shape:
        `(B,)`, `(B,)` -> `(B,)`.
    """
    target = torch.remainder(azimuth_deg, 360.0) / 360.0
    return 1.0 - torch.cos(2.0 * math.pi * (predicted_fraction - target))


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
        """Pre-head features: the encoder's pooled 512-d ResNet feature.

        Args:
            images: Normalised dB chips in [0, 1].

        Returns:
            Features `(B, D)`.

        Shape:
            `(B, 1, S, S)` -> `(B, D)` with `S = image_size`.
        """
        return self.encoder(images)

    def _head_config(self) -> dict[str, Any]:
        return {}

    def save_pretrained(self, directory: str | Path) -> Path:
        """Writes `evaluator.json` (kind, encoder config, classes, scaling, head, metrics) and the weights.

        Args:
            directory: Target folder, created if needed.

        Returns:
            The folder.
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
    """ResNet-18 classifier trained from scratch on real chips (Table III "Acc.").

    Args:
        encoder_config: Architecture of the ResNet-18 body.
        class_names: Class names in label order.
        scaling: Decibel scaling of the chips it was trained on (stored with the weights).
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
        """Class logits.

        Shape:
            `(B, 1, S, S)` -> `(B, K)`.
        """
        return self.head(self.features(images))


class AzimuthRegressor(_Evaluator):
    """ResNet-18 + MLP azimuth regressor with sigmoid output = azimuth / 2pi (Table III "Az. err.", SFD).

    Args:
        encoder_config: Architecture of the ResNet-18 body.
        class_names: Class names of the training data (stored to reject mismatched evaluation data).
        scaling: Decibel scaling of the training chips.
        hidden_sizes: MLP widths (256-256 in the paper).
    """

    kind = "azimuth_regressor"

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
        """Predicted azimuth / 360 deg in (0, 1).

        Shape:
            `(B, 1, S, S)` -> `(B,)`.
        """
        return self.head(self.features(images)).squeeze(1)

    def predict_azimuth_deg(self, images: torch.Tensor) -> torch.Tensor:
        """Predicted azimuth in degrees, [0, 360).

        Shape:
            `(B, 1, S, S)` -> `(B,)`.
        """
        return torch.remainder(self(images) * 360.0, 360.0)


def load_evaluator(
    directory: str | Path,
    class_names: Sequence[str] | None = None,
    device: str | torch.device = "cpu",
) -> SARClassifier | AzimuthRegressor:
    """Loads an evaluator folder written by `save_pretrained`, in eval mode.

    Args:
        directory: Folder with `evaluator.json` and `model.safetensors`.
        class_names: Class list of the data to score; a different saved list raises.
        device: Device for the weights.

    Returns:
        The classifier or regressor, in eval mode, with `metrics` restored.

    Raises:
        FileNotFoundError: If a file is missing.
        ValueError: For an unknown kind or a class-list mismatch.
    """
    directory = Path(directory)
    for path in (directory / EVALUATOR_CONFIG_NAME, directory / EVALUATOR_WEIGHTS_NAME):
        if not path.is_file():
            raise FileNotFoundError(f"evaluator checkpoint not found: {path}")
    payload = json.loads((directory / EVALUATOR_CONFIG_NAME).read_text())
    check_class_names(payload["class_names"], class_names, str(directory))
    encoder_config = SAREncoderConfig.from_dict(payload["encoder"])
    scaling = DecibelScaling.from_dict(payload["scaling"])
    model: SARClassifier | AzimuthRegressor
    if payload["kind"] == SARClassifier.kind:
        model = SARClassifier(encoder_config, payload["class_names"], scaling)
    elif payload["kind"] == AzimuthRegressor.kind:
        model = AzimuthRegressor(encoder_config, payload["class_names"], scaling, **payload["head"])
    else:
        raise ValueError(f"{directory}: unknown evaluator kind {payload['kind']!r}")
    model.load_state_dict(load_file(str(directory / EVALUATOR_WEIGHTS_NAME), device=str(device)))
    model.metrics = dict(payload.get("metrics", {}))
    return model.to(device).eval()


@dataclass
class Evaluators:
    """The evaluator set written by `train/train_evaluators.py`.

    Attributes:
        classifier: Scratch ResNet-18 classifier.
        regressor: Scratch ResNet-18 + MLP azimuth regressor (its features give SFD).
        probes: Extra azimuth regressors for Table IV (frozen SimCLR encoders + trained MLP), by name.
    """

    classifier: SARClassifier
    regressor: AzimuthRegressor
    probes: dict[str, AzimuthRegressor] = field(default_factory=dict)

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
    """Loads `DIR/classifier`, `DIR/regressor` and every `DIR/probes/<name>`.

    Args:
        directory: Output folder of `train/train_evaluators.py`.
        class_names: Class list of the data to score (checked against every model).
        device: Device for the weights.

    Returns:
        The evaluator set.

    Raises:
        FileNotFoundError: If the classifier or regressor is missing.
        ValueError: For a class-list mismatch, or evaluators with different class lists or image sizes.
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
    sizes = {model.image_size for model in (classifier, regressor, *probes.values())}
    if len(sizes) != 1:
        raise ValueError(f"{directory}: evaluators take different image sizes {sorted(sizes)}")
    return Evaluators(classifier=classifier, regressor=regressor, probes=probes)


def resize_for_evaluator(images: torch.Tensor, size: int) -> torch.Tensor:
    """Resizes `(B, 1, H, W)` images to the evaluators' `size` (bilinear, anti-aliased); no-op when equal."""
    if images.shape[-2:] == (size, size):
        return images
    resized = F.interpolate(images, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return resized.clamp(0.0, 1.0)


@torch.no_grad()
def score_views(
    generated: torch.Tensor,
    targets: torch.Tensor,
    labels: torch.Tensor,
    target_azimuth_deg: torch.Tensor,
    evaluators: Evaluators,
    *,
    crop_size: int | None = CROP_SIZE,
    paper_scoring_size: int | None = PAPER_SCORING_SIZE,
    batch_size: int = 64,
    device: str | torch.device = "cpu",
) -> dict[str, float]:
    """All five Table III metrics of generated views against their targets, plus Table IV errors.

    Accuracy: the classifier's prediction on the generated view against the object's class. Azimuth error:
    the regressor's prediction on the generated view against the target view's true azimuth (circular).
    SFD: Frechet distance between the regressor's pre-head features of generated and of target views.
    MS-SSIM and Kuan+SSIM: generated against target on the centre crop. `ms_ssim` and `kuan_ssim` are the
    paper-comparable values (`sar_zero123.paper_metrics`: the authors' calls on 8-bit views resized to
    `paper_scoring_size`); `ms_ssim_corrected` and `kuan_ssim_corrected` are the corrected variants
    (`sar_zero123.metrics`) at the generated resolution.

    Args:
        generated: Generated views in [0, 1].
        targets: The real target views in [0, 1], same shape.
        labels: Class indices of the objects (in `evaluators.class_names` order).
        target_azimuth_deg: True azimuth of each target view in degrees.
        evaluators: The evaluator set (classifier, regressor, probes).
        crop_size: Centre crop for MS-SSIM and Kuan+SSIM (64 in the paper; `None` only for the corrected
            variants, the paper-comparable ones then use 64).
        paper_scoring_size: Side the views are resized to before the paper-comparable crop (256, the
            authors' resolution; `None` scores them at the generated resolution).
        batch_size: Images per evaluator forward pass.
        device: Device of the evaluator models.

    Returns:
        `{"accuracy": %, "azimuth_error_deg", "sfd", "ms_ssim", "kuan_ssim", "ms_ssim_corrected",
        "kuan_ssim_corrected", "n",
        "azimuth_error_deg/<regressor>"...}` with the means over the samples.

    Shape:
        generated, targets `(N, 1, H, W)`; labels, target_azimuth_deg `(N,)`.

    Raises:
        ValueError: For mismatched sizes or counts, or images outside [0, 1].
    """
    n = generated.shape[0]
    if labels.shape != (n,) or target_azimuth_deg.shape != (n,):
        raise ValueError(
            f"labels {tuple(labels.shape)} and target_azimuth_deg {tuple(target_azimuth_deg.shape)} must be "
            f"({n},) to match generated {tuple(generated.shape)}"
        )
    # Image metrics first: they validate sizes and ranges of both sets.
    structural = {name: [] for name in ("ms_ssim", "kuan_ssim", "ms_ssim_corrected", "kuan_ssim_corrected")}
    paper_crop = {"scoring_size": paper_scoring_size, "crop_size": crop_size or CROP_SIZE}
    predictions: dict[str, list[torch.Tensor]] = {"class": []}
    regressors = evaluators.azimuth_regressors()
    for name in regressors:
        predictions[name] = []
    generated_features, target_features = [], []
    for start in range(0, n, batch_size):
        fake = generated[start : start + batch_size].float().cpu()
        real = targets[start : start + batch_size].float().cpu()
        structural["ms_ssim"].append(paper_ms_ssim(fake, real, **paper_crop))
        structural["kuan_ssim"].append(paper_kuan_ssim(fake, real, **paper_crop))
        structural["ms_ssim_corrected"].append(ms_ssim(fake, real, crop_size=crop_size))
        structural["kuan_ssim_corrected"].append(kuan_ssim(fake, real, crop_size=crop_size))
        fake_eval = resize_for_evaluator(fake, evaluators.image_size).to(device)
        real_eval = resize_for_evaluator(real, evaluators.image_size).to(device)
        predictions["class"].append(evaluators.classifier(fake_eval).argmax(dim=1).cpu())
        for name, regressor in regressors.items():
            predictions[name].append(regressor.predict_azimuth_deg(fake_eval).cpu())
        generated_features.append(evaluators.regressor.features(fake_eval).cpu())
        target_features.append(evaluators.regressor.features(real_eval).cpu())
    target_azimuth_deg = target_azimuth_deg.double().cpu()
    predicted_azimuth_deg = torch.cat(predictions["scratch"]).double()
    per_sample = {
        "accuracy": 100.0 * (torch.cat(predictions["class"]) == labels.cpu()).double(),
        "azimuth_error_deg": azimuth_error_deg(predicted_azimuth_deg, target_azimuth_deg),
        **{name: torch.cat(values).double() for name, values in structural.items()},
    }
    scores = {
        "accuracy": 100.0 * classification_accuracy(torch.cat(predictions["class"]), labels.cpu()),
        "azimuth_error_deg": per_sample["azimuth_error_deg"].mean().item(),
        "sfd": frechet_distance(torch.cat(generated_features), torch.cat(target_features)),
        **{name: per_sample[name].mean().item() for name in structural},
        "n": float(n),
    }
    # standard error of each mean (sample standard deviation / sqrt(n)); SFD has no per-sample terms
    for name, values in per_sample.items():
        scores[f"{name}_se"] = values.std(correction=1).item() / math.sqrt(n) if n > 1 else float("nan")
    for name in regressors:
        error = azimuth_error_deg(torch.cat(predictions[name]).double(), target_azimuth_deg)
        scores[f"azimuth_error_deg/{name}"] = error.mean().item()
    return scores


@torch.no_grad()
def pose_following(
    pipe,
    image: torch.Tensor,
    input_azimuth_deg: float,
    regressor: AzimuthRegressor,
    *,
    d_az_deg: Sequence[float] = (-135.0, -90.0, -45.0, 0.0, 45.0, 90.0, 135.0, 180.0),
    num_inference_steps: int = 20,
    guidance_scale: float = 3.0,
    seed: int = 0,
) -> dict[str, Any]:
    """Does a pipeline's output turn with the requested pose? One input view, several ``d_az``.

    The regressor reads the azimuth of each generated view; a model that follows the pose returns views at
    ``input_azimuth_deg + d_az`` (error near the regressor's own), one that ignores it returns the input's
    azimuth for every request (error near the mean ``|d_az|`` of the request list, here the floor).

    Args:
        pipe: A :class:`~sar_zero123.pipeline.SARZero123Pipeline`.
        image: The input view ``(1, 1, S, S)`` in [0, 1].
        input_azimuth_deg: Its true azimuth.
        regressor: The evaluator azimuth regressor.
        d_az_deg: Requested azimuth changes.
        num_inference_steps: Sampler steps.
        guidance_scale: Classifier-free guidance weight.
        seed: Seed of the generator of every request (the same noise for each, so only the pose differs).

    Returns:
        ``{"requested_deg", "predicted_deg", "error_deg" (per request), "mean_error_deg", "floor_deg"}``.

    Raises:
        ValueError: If ``image`` is not one ``(1, 1, S, S)`` view.
    """
    if image.ndim != 4 or image.shape[:2] != (1, 1):
        raise ValueError(f"image must be one view of shape (1, 1, S, S), got {tuple(image.shape)}")
    requests = torch.tensor([float(d) for d in d_az_deg], dtype=torch.float64)
    count = requests.numel()
    generated = pipe(
        image.expand(count, -1, -1, -1).to(pipe.device),
        d_az=requests.float(),
        d_el=torch.zeros(count),
        num_inference_steps=num_inference_steps,
        guidance_scale=guidance_scale,
        generator=[torch.Generator().manual_seed(seed) for _ in range(count)],
        output_type="pt",
    ).images.float()
    device = next(regressor.parameters()).device
    views = resize_for_evaluator(generated.cpu(), regressor.image_size).to(device)
    predicted = regressor.predict_azimuth_deg(views)
    wanted = (input_azimuth_deg + requests) % 360.0
    error = azimuth_error_deg(predicted.double().cpu(), wanted)
    floor = azimuth_error_deg(torch.full_like(wanted, input_azimuth_deg), wanted)
    return {
        "requested_deg": requests.tolist(),
        "predicted_deg": predicted.double().cpu().tolist(),
        "error_deg": error.tolist(),
        "mean_error_deg": error.mean().item(),
        "floor_deg": floor.mean().item(),
    }

