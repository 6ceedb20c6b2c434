"""Scoring with the evaluator models: the metrics of generated views (Tables III and IV,
:func:`score_views`), pose following (:func:`pose_following`), an evaluator's own test metrics
(:func:`score_on_split`), and :func:`closer_to_target_depression`, which needs no trained model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import gaussian_filter
from torch.utils.data import DataLoader

from sar_zero123.evaluation.evaluators import AzimuthRegressor, DepressionRegressor, Evaluators, SARClassifier
from sar_zero123.evaluation.metrics import (
    CROP_SIZE,
    axis_error_deg,
    azimuth_error_deg,
    classification_accuracy,
    frechet_distance,
    kuan_ssim,
    ms_ssim,
)
from sar_zero123.evaluation.paper_metrics import PAPER_SCORING_SIZE, paper_kuan_ssim, paper_ms_ssim

MAX_POSE_REQUESTS = 64  # most d_az requests `pose_following` samples, as one batch

__all__ = [
    "MAX_POSE_REQUESTS",
    "blur_views",
    "closer_to_target_depression",
    "pose_following",
    "resize_for_evaluator",
    "score_on_split",
    "score_views",
    "standard_error",
]


def resize_for_evaluator(images: torch.Tensor, size: int) -> torch.Tensor:
    """Resizes `(B, 1, H, W)` images to the evaluators' `size` (bilinear, anti-aliased); no-op when equal."""
    if images.shape[-2:] == (size, size):
        return images
    resized = F.interpolate(images, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return resized.clamp(0.0, 1.0)


def standard_error(values: torch.Tensor) -> float:
    """Standard error of the mean: sample standard deviation / sqrt(n); NaN for n < 2. `(N,)` -> scalar."""
    n = values.numel()
    return values.double().std(correction=1).item() / math.sqrt(n) if n > 1 else float("nan")


@torch.no_grad()
def score_views(
    generated: torch.Tensor,
    targets: torch.Tensor,
    labels: torch.Tensor,
    target_azimuth_deg: torch.Tensor,
    evaluators: Evaluators,
    *,
    target_depression_deg: torch.Tensor | None = None,
    input_depression_deg: torch.Tensor | None = None,
    crop_size: int | None = CROP_SIZE,
    paper_scoring_size: int | None = PAPER_SCORING_SIZE,
    batch_size: int = 64,
    device: str | torch.device = "cpu",
    return_per_sample: bool = False,
) -> dict[str, float] | tuple[dict[str, float], dict[str, torch.Tensor]]:
    """All five Table III metrics of generated views against their targets, plus Table IV errors.

    Accuracy: the classifier on the view against the object's class. Azimuth error: the regressor on the
    view against the target's true azimuth (circular). SFD: Frechet distance of the regressor's features of
    generated and target views. `ms_ssim` and `kuan_ssim` are the paper-comparable values on 8-bit views
    resized to `paper_scoring_size`; `*_corrected` the corrected variants at the generated resolution.
    Depression error (a depression regressor and `target_depression_deg`): |predicted - true|. Depression
    overshoot (with `input_depression_deg`, over pairs with a depression change):
    `(predicted - target) * sign(target - input)`: above 0 past the request, below 0 short of it (at
    `-|target - input|` it stayed at the input's), which the unsigned error cannot tell apart.

    Args:
        labels: Class indices (in `evaluators.class_names` order).
        target_azimuth_deg: True azimuth of each target view.
        crop_size: Centre crop for MS-SSIM and Kuan+SSIM (`None` only for the corrected variants).
        paper_scoring_size: Side before the paper-comparable crop (`None`: the generated resolution).
        batch_size: Images per evaluator forward pass.

    Returns:
        `{"accuracy": %, "azimuth_error_deg", "axis_error_deg", "sfd", "ms_ssim", "kuan_ssim",
        "ms_ssim_corrected", "kuan_ssim_corrected", "n", "azimuth_error_deg/<regressor>"...,
        "depression_error_deg", "depression_overshoot_deg", "predicted/<class>"...}` means, and
        `<metric>_se`. `predicted/<class>` is the share of views (%) given each class, showing where a lost
        class went. With `return_per_sample`, also each view's terms `(N,)` float64 by metric.

    Shape:
        generated, targets `(N, 1, H, W)` in [0, 1]; labels, target_azimuth_deg, target_depression_deg `(N,)`.

    Raises:
        ValueError: For mismatched sizes or counts, or images outside [0, 1].
    """
    n = generated.shape[0]
    if labels.shape != (n,) or target_azimuth_deg.shape != (n,):
        raise ValueError(
            f"labels {tuple(labels.shape)} and target_azimuth_deg {tuple(target_azimuth_deg.shape)} must be "
            f"({n},) to match generated {tuple(generated.shape)}"
        )
    if target_depression_deg is not None and target_depression_deg.shape != (n,):
        raise ValueError(
            f"target_depression_deg {tuple(target_depression_deg.shape)} must be ({n},) to match generated"
        )
    if input_depression_deg is not None and (
        target_depression_deg is None or input_depression_deg.shape != (n,)
    ):
        raise ValueError(
            f"input_depression_deg needs target_depression_deg and the shape ({n},), got "
            f"{tuple(input_depression_deg.shape)}"
        )
    depression_regressor = evaluators.depression_regressor if target_depression_deg is not None else None
    # Image metrics first: they validate sizes and ranges of both sets.
    structural = {name: [] for name in ("ms_ssim", "kuan_ssim", "ms_ssim_corrected", "kuan_ssim_corrected")}
    paper_crop = {"scoring_size": paper_scoring_size, "crop_size": crop_size or CROP_SIZE}
    predictions: dict[str, list[torch.Tensor]] = {"class": []}
    regressors = evaluators.azimuth_regressors()
    for name in regressors:
        predictions[name] = []
    predictions["depression"] = []
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
        if depression_regressor is not None:
            predictions["depression"].append(depression_regressor.predict_depression_deg(fake_eval).cpu())
        generated_features.append(evaluators.regressor.features(fake_eval).cpu())
        target_features.append(evaluators.regressor.features(real_eval).cpu())
    target_azimuth_deg = target_azimuth_deg.double().cpu()
    predicted_azimuth_deg = torch.cat(predictions["scratch"]).double()
    per_sample = {
        "accuracy": 100.0 * (torch.cat(predictions["class"]) == labels.cpu()).double(),
        "azimuth_error_deg": azimuth_error_deg(predicted_azimuth_deg, target_azimuth_deg),
        "axis_error_deg": axis_error_deg(predicted_azimuth_deg, target_azimuth_deg),
        **{name: torch.cat(values).double() for name, values in structural.items()},
    }
    if depression_regressor is not None:
        predicted_depression_deg = torch.cat(predictions["depression"]).double()
        per_sample["depression_error_deg"] = (
            predicted_depression_deg - target_depression_deg.double().cpu()
        ).abs()
    scores = {
        "accuracy": 100.0 * classification_accuracy(torch.cat(predictions["class"]), labels.cpu()),
        "azimuth_error_deg": per_sample["azimuth_error_deg"].mean().item(),
        "axis_error_deg": per_sample["axis_error_deg"].mean().item(),
        "sfd": frechet_distance(torch.cat(generated_features), torch.cat(target_features)),
        **{name: per_sample[name].mean().item() for name in structural},
        "n": float(n),
    }
    if depression_regressor is not None:
        scores["depression_error_deg"] = per_sample["depression_error_deg"].mean().item()
        if input_depression_deg is not None:
            change = target_depression_deg.double().cpu() - input_depression_deg.double().cpu()
            moved = change != 0
            if moved.any():
                overshoot = (predicted_depression_deg - target_depression_deg.double().cpu())[moved]
                overshoot = overshoot * torch.sign(change[moved])
                scores["depression_overshoot_deg"] = overshoot.mean().item()
                scores["depression_overshoot_deg_se"] = standard_error(overshoot)
                scores["depression_overshoot_deg_n"] = float(overshoot.numel())
    predicted_classes = torch.bincount(torch.cat(predictions["class"]), minlength=len(evaluators.class_names))
    for name, count in zip(evaluators.class_names, predicted_classes.tolist()):
        scores[f"predicted/{name}"] = 100.0 * count / n
    # SFD has no per-sample terms, hence no standard error
    for name, values in per_sample.items():
        scores[f"{name}_se"] = standard_error(values)
    for name in regressors:
        error = azimuth_error_deg(torch.cat(predictions[name]).double(), target_azimuth_deg)
        scores[f"azimuth_error_deg/{name}"] = error.mean().item()
    if return_per_sample:
        return scores, per_sample
    return scores


def closer_to_target_depression(
    generated: torch.Tensor | np.ndarray,
    targets: torch.Tensor | np.ndarray,
    input_depression_views: torch.Tensor | np.ndarray,
    sigma_px: float = 1.5,
) -> torch.Tensor:
    """Whether each blurred generated view correlates more with the requested depression's truth.

    A view for a change `d_el != 0` should look like the target (target azimuth and depression) more than
    like the view at the target azimuth and the input's depression, which a model ignoring `d_el` returns.
    All three are blurred by `sigma_px` first, so speckle that no generator can reproduce does not decide;
    Pearson correlation decides (a constant view correlates 0).

    Returns:
        `(N,)` bool: `corr(generated, targets) > corr(generated, input_depression_views)` (ties: False).

    Shape:
        `(N, 1, H, W)` each -> `(N,)`.

    Raises:
        ValueError: For views of different shapes, not `(N, 1, H, W)`, or a negative `sigma_px`.
    """
    views = [
        np.asarray(torch.as_tensor(v).detach().cpu(), dtype=np.float64)
        for v in (generated, targets, input_depression_views)
    ]
    if views[0].ndim != 4 or views[0].shape[1] != 1 or any(v.shape != views[0].shape for v in views):
        raise ValueError(
            f"generated, targets and input_depression_views must share one (N, 1, H, W) shape, got "
            f"{[v.shape for v in views]}"
        )
    if sigma_px < 0:
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    generated_blurred, target_blurred, input_depression_blurred = (blur_views(v, sigma_px) for v in views)
    to_target = _pearson(generated_blurred, target_blurred)
    return torch.from_numpy(to_target > _pearson(generated_blurred, input_depression_blurred))


def blur_views(views: np.ndarray, sigma_px: float) -> np.ndarray:
    """Views `(N, C, H, W)` blurred in the image plane by a Gaussian of `sigma_px` pixels (scipy's
    `gaussian_filter`, reflected border); channels and views are not mixed."""
    return gaussian_filter(views, sigma=(0.0, 0.0, sigma_px, sigma_px))


def _pearson(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pearson correlation of each pair of views, 0 where one is constant. Shape: `(N, ...)` x2 -> `(N,)`."""
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    norms = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    covariance = (a * b).sum(axis=1)
    return np.divide(covariance, norms, out=np.zeros_like(covariance), where=norms > 0)


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
    input_depression_deg: float | None = None,
) -> dict[str, Any]:
    """Does a pipeline's output turn with the requested pose? One input view, several ``d_az``.

    The regressor reads each view's azimuth; a model that follows the pose returns ``input_azimuth_deg +
    d_az``, one that ignores it the input's azimuth (error near the mean ``|d_az|``: the floor). Every
    request uses the same seed, so only the pose differs.

    Args:
        image: The input view ``(1, 1, S, S)`` in [0, 1].
        input_depression_deg: For a pipeline whose pose carries it.

    Returns:
        ``{"requested_deg", "predicted_deg", "error_deg" (per request), "mean_error_deg", "floor_deg"}``.

    Raises:
        ValueError: If ``image`` is not one ``(1, 1, S, S)`` view, or ``d_az_deg`` holds no request or more
            than :data:`MAX_POSE_REQUESTS`.
    """
    if image.ndim != 4 or image.shape[:2] != (1, 1):
        raise ValueError(f"image must be one view of shape (1, 1, S, S), got {tuple(image.shape)}")
    requests = torch.tensor([float(d) for d in d_az_deg], dtype=torch.float64)
    count = requests.numel()
    if not 1 <= count <= MAX_POSE_REQUESTS:
        raise ValueError(f"d_az_deg: expected 1 to {MAX_POSE_REQUESTS} requests (one batch), got {count}")
    generated = pipe(
        image.expand(count, -1, -1, -1).to(pipe.device),
        d_az=requests.float(),
        d_el=torch.zeros(count),
        input_depression_deg=input_depression_deg,
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


@torch.no_grad()
def score_on_split(
    model: SARClassifier | AzimuthRegressor | DepressionRegressor, loader: DataLoader, device: torch.device
) -> dict[str, float]:
    """Test accuracy (classifier), mean/median circular azimuth error (azimuth regressor) or mean/median
    absolute depression error (depression regressor) on a split."""
    model.eval()
    outputs, truths = [], []
    for batch in loader:
        images = batch["image"].to(device)
        if isinstance(model, SARClassifier):
            outputs.append(model(images).argmax(dim=1).cpu())
            truths.append(batch["label"])
        elif isinstance(model, DepressionRegressor):
            outputs.append(model.predict_depression_deg(images).cpu())
            truths.append(batch["depression_deg"].float())
        else:
            outputs.append(model.predict_azimuth_deg(images).cpu())
            truths.append(batch["azimuth_deg"].float())
    predictions, truth = torch.cat(outputs), torch.cat(truths)
    if isinstance(model, SARClassifier):
        return {"test_accuracy": classification_accuracy(predictions, truth), "n_test": len(predictions)}
    if isinstance(model, DepressionRegressor):
        name, errors = "depression", (predictions - truth).abs()
    else:
        name, errors = "azimuth", azimuth_error_deg(predictions, truth)
    return {
        f"test_{name}_error_deg": errors.mean().item(),
        f"test_{name}_error_median_deg": errors.median().item(),
        "n_test": len(predictions),
    }
