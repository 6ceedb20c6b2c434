"""What one pipeline call asks for, checked once under the call's own argument names: the input chips and
the relative pose (scalars or one per chip, in degrees) as the pose vector the model reads. A request
outside the pose projection's trained ranges is refused rather than extrapolated.
A target depression (the input's plus ``d_el``) outside (0, 90) degrees is refused too.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from sar_zero123.model.conditioning import as_angle_tensor, embed_pose
from sar_zero123.model.spatial_pose import takes_proxy

__all__ = [
    "MAX_ABS_D_AZ_DEG", "MAX_ABS_D_EL_DEG", "Angles", "ViewRequest", "broadcast_pose", "check_proxy_views",
    "check_delta_bounds", "check_real_angles", "check_target_depression", "per_input_angles",
    "pose_with_depression", "view_request",
]  # fmt: skip

#: A depression delta is the difference of two depression angles in (0, 90) degrees: |d_el| < 90.
MAX_ABS_D_EL_DEG = 90.0
#: Azimuth deltas beyond this many degrees (~2,800 turns) are almost surely a unit error, and float64
#: loses the angle's fraction of a degree long before 1e15.
MAX_ABS_D_AZ_DEG = 1e6

#: Angles in degrees: a scalar for the whole batch, or one per input chip.
Angles = float | Sequence[float] | torch.Tensor


@dataclass
class ViewRequest:
    """One call's checked request.

    Args:
        images: The input chips in the normalised dB domain, on the CPU ``(B, 1 | 3, H, W)``.
        d_az: The azimuth change as the call gave it (checked: real, finite, 1 or ``B`` values).
        d_el: The depression change as the call gave it (checked, and within the trained range).
        pose: The pose vectors the model reads ``(B, 1, 4)``.
        input_azimuth_deg: Each input's absolute azimuth ``(B,)`` float64, or ``None`` where not given.
        input_depression_deg: Each input's absolute depression as the call gave it (checked), or ``None``.
        proxy_views: Each input's simulator proxy given by the call (:func:`check_proxy_views`), or ``None``.
    """

    images: torch.Tensor
    d_az: Angles
    d_el: Angles
    pose: torch.Tensor
    input_azimuth_deg: torch.Tensor | None
    input_depression_deg: Angles | None
    proxy_views: torch.Tensor | None

    @property
    def batch_size(self) -> int:
        """The number of input chips ``B``."""
        return self.images.shape[0]


def view_request(
    images: torch.Tensor,
    d_az: Angles,
    d_el: Angles,
    input_depression_deg: Angles | None,
    input_azimuth_deg: Angles | None,
    proxy_views: Any,
    pose_projection: torch.nn.Module,
) -> ViewRequest:
    """A call's angles and proxy views checked against its checked ``images`` and the model's pose projection.

    Raises:
        ValueError: Naming the argument, for angles that are not real numbers, out of range or of another
            count than 1 or the batch, a depression outside the trained range or missing where the pose
            carries it, or proxy views of another shape or domain (or given to a pipeline that takes none).
    """
    batch_size = images.shape[0]
    pose = broadcast_pose(d_az, d_el, batch_size)  # (B, 1, 4)
    pose = pose_with_depression(pose, d_el, input_depression_deg, pose_projection.config)
    if input_azimuth_deg is not None:  # checked whether or not this call's start uses it
        input_azimuth_deg = per_input_angles(input_azimuth_deg, "input_azimuth_deg", batch_size)
    if proxy_views is not None:
        proxy_views = check_proxy_views(proxy_views, images, pose_projection)
    return ViewRequest(images, d_az, d_el, pose, input_azimuth_deg, input_depression_deg, proxy_views)


def check_proxy_views(
    proxy_views: Any, images: torch.Tensor, pose_projection: torch.nn.Module
) -> torch.Tensor:
    """``proxy_views`` checked as ``image`` is: a real tensor or array of normalised dB views, one set per
    input, of the input's size.

    Returns:
        ``(B, 2 | 3, H, W)`` float32 on the CPU.

    Raises:
        ValueError: Naming ``proxy_views`` and what was expected.
    """
    if not takes_proxy(pose_projection):
        raise ValueError(
            "`proxy_views`: this pipeline's UNet takes no proxy (pose_projection.config.spatial_pose="
            f"{getattr(pose_projection.config, 'spatial_pose', None)!r}); leave it out"
        )
    expected = (images.shape[0], 2, *images.shape[-2:])
    what = (
        f"`proxy_views` must be real normalised dB views in [0, 1] of shape {expected}: each input's "
        "proxy at the input's pose, then at the requested pose (and, as a third, at the flipped heading "
        "d_az + 180 for heading guidance)"
    )
    if isinstance(proxy_views, np.ndarray):
        proxy_views = torch.from_numpy(proxy_views)
    if not isinstance(proxy_views, torch.Tensor):
        raise ValueError(f"{what}; got a {type(proxy_views).__name__}")
    if proxy_views.is_complex() or proxy_views.dtype == torch.bool or proxy_views.is_meta:
        raise ValueError(f"{what}; got a {proxy_views.dtype} tensor")
    shape = tuple(proxy_views.shape)
    if shape not in (expected, (expected[0], 3, *expected[2:])):
        raise ValueError(f"{what}; got shape {shape}")
    views = proxy_views.detach().to("cpu", torch.float32)
    if not torch.isfinite(views).all() or float(views.min()) < 0.0 or float(views.max()) > 1.0:
        raise ValueError(f"{what}; got values outside [0, 1] or not finite")
    return views


def broadcast_pose(d_az: Angles, d_el: Angles, batch_size: int) -> torch.Tensor:
    """Pose vectors for a batch, checking that each angle is a scalar or has one value per image, real,
    and physically possible.

    Shape:
        ``(batch_size, 1, 4)``.
    """
    for name, value in (("d_az", d_az), ("d_el", d_el)):
        check_real_angles(value, name)
        count = as_angle_tensor(value, name).numel()  # checked under the pipeline's own argument names
        if count not in (1, batch_size):
            raise ValueError(f"`{name}` has {count} values; expected 1 or one per input image ({batch_size})")
    pose = embed_pose(d_az, d_el)  # (1 | B, 1, 4); cannot fail on angles that passed the checks above
    check_delta_bounds(d_az, d_el)
    return pose.expand(batch_size, -1, -1) if pose.shape[0] == 1 else pose


def check_delta_bounds(d_az: Angles, d_el: Angles) -> None:
    """``|d_el| < 90`` (no input depression in (0, 90) reaches a target in (0, 90) from further) and
    ``|d_az| <=`` :data:`MAX_ABS_D_AZ_DEG`: the one bound of the call, ``generate`` and ``augment`` (which
    check it before loading a pipeline). Empty angles pass.

    Raises:
        ValueError: Naming the angle, its bound and the largest magnitude given.
    """
    for name, value in (("d_el", d_el), ("d_az", d_az)):
        magnitudes = torch.as_tensor(value, dtype=torch.float64).abs()
        largest = float(magnitudes.max()) if magnitudes.numel() else 0.0
        if name == "d_el" and largest >= MAX_ABS_D_EL_DEG:
            raise ValueError(
                f"`d_el` must lie in (-{MAX_ABS_D_EL_DEG:g}, {MAX_ABS_D_EL_DEG:g}) degrees (a difference of "
                f"two depression angles in (0, 90)), got {largest:g}"
            )
        if name == "d_az" and largest > MAX_ABS_D_AZ_DEG:
            raise ValueError(
                f"`d_az` must lie in [-{MAX_ABS_D_AZ_DEG:g}, {MAX_ABS_D_AZ_DEG:g}] degrees (larger values "
                f"lose the angle's precision: a unit error?), got {largest:g}"
            )


def pose_with_depression(
    pose: torch.Tensor, d_el: Angles, input_depression_deg: Angles | None, config: Any
) -> torch.Tensor:
    """``pose`` with the input's depression in its fourth entry when the pipeline takes it, after
    checking the request against the ranges the pipeline was trained on.

    Args:
        config: The pose projection's config (``input_depression``, ``trained_d_el_deg``,
            ``trained_depression_deg``).

    Raises:
        ValueError: naming the argument, for a missing, non-finite or mis-sized input depression, a target
            depression outside (0, 90) degrees (:func:`check_target_depression`), or a ``d_el``, input
            depression or target depression outside the trained range.
    """
    batch_size = pose.shape[0]
    # on the CPU, as as_angle_tensor's angles: an evaluation's pair batch arrives on the accelerator
    d_el_values = torch.as_tensor(d_el, dtype=torch.float64).cpu().reshape(-1).expand(batch_size)
    depression = None
    if input_depression_deg is not None:
        check_real_angles(input_depression_deg, "input_depression_deg")
        depression = as_angle_tensor(input_depression_deg, "input_depression_deg").double().reshape(-1)
        if depression.numel() not in (1, batch_size):
            raise ValueError(
                f"`input_depression_deg` has {depression.numel()} values; expected 1 or one per input "
                f"image ({batch_size})"
            )
        if float(depression.min()) <= 0.0 or float(depression.max()) >= 90.0:
            raise ValueError(f"`input_depression_deg` must lie in (0, 90) degrees, got {depression.tolist()}")
        depression = depression.expand(batch_size)
        check_target_depression(depression, d_el_values)
    elif getattr(config, "input_depression", False):
        raise ValueError(
            "`input_depression_deg`: this pipeline's pose carries the input chip's absolute depression "
            "(pose_projection.config.input_depression); give it in degrees, from the chip's metadata"
        )
    trained_d_el = getattr(config, "trained_d_el_deg", None)
    if trained_d_el is not None:
        low, high = float(trained_d_el[0]), float(trained_d_el[1])
        if float(d_el_values.min()) < low - 1e-6 or float(d_el_values.max()) > high + 1e-6:
            raise ValueError(
                f"`d_el` must lie in the trained range [{low:g}, {high:g}] degrees "
                f"(pose_projection.config.trained_d_el_deg), got {sorted(set(d_el_values.tolist()))}"
            )
    trained_depression = getattr(config, "trained_depression_deg", None)
    if trained_depression is not None and depression is not None:
        low, high = float(trained_depression[0]), float(trained_depression[1])
        for name, values in (
            ("input_depression_deg", depression),
            ("input_depression_deg + d_el", depression + d_el_values),
        ):
            if float(values.min()) < low - 1e-6 or float(values.max()) > high + 1e-6:
                raise ValueError(
                    f"`{name}` must lie in the trained depression range [{low:g}, {high:g}] degrees "
                    f"(pose_projection.config.trained_depression_deg), got {sorted(set(values.tolist()))}"
                )
    if not getattr(config, "input_depression", False):
        return pose
    pose = pose.clone()
    pose[:, 0, 3] = torch.deg2rad(depression).to(pose.dtype)
    return pose


def check_target_depression(input_depression_deg: torch.Tensor, d_el: torch.Tensor) -> None:
    """Each view's target depression, ``input_depression_deg + d_el``, lies in (0, 90) degrees: a radar looks
    down at a target on the ground, so no ``d_el`` may carry a view past the horizon or the nadir, whatever
    ranges the pipeline records.

    Args:
        input_depression_deg: Each input's depression ``(B,)``, checked in (0, 90).
        d_el: Each view's depression change ``(B,)``.

    Raises:
        ValueError: Naming ``d_el``, the input depression and the bound, for the first view outside it.
    """
    target = input_depression_deg + d_el
    outside = ((target <= 0.0) | (target >= 90.0)).nonzero()
    if len(outside):
        k = int(outside[0])
        raise ValueError(
            f"`d_el` {float(d_el[k]):g} from an input depression of {float(input_depression_deg[k]):g} deg "
            f"asks for a target depression of {float(target[k]):g} deg; input_depression_deg + d_el must lie "
            "in (0, 90) degrees"
        )


def per_input_angles(value: Any, name: str, batch_size: int) -> torch.Tensor:
    """Angles given as a scalar or one per input image, checked and broadcast to ``(batch_size,)`` float64.

    Raises:
        ValueError: Naming ``name``, for non-real or non-finite angles or a count other than 1 or the batch.
    """
    check_real_angles(value, name)
    tensor = as_angle_tensor(value, name)
    if tensor.numel() not in (1, batch_size):
        raise ValueError(f"`{name}` has {tensor.numel()} values; expected 1 or one per input ({batch_size})")
    return tensor.expand(batch_size)


def check_real_angles(value: Any, name: str) -> None:
    """Angles are real numbers (a scalar, a sequence of them, or a real tensor/array).

    Raises:
        ValueError: naming the argument, for strings, ``None``, booleans, complex numbers and the like (as
            diffusers' ``check_inputs`` refuses a wrong type).
    """
    if isinstance(value, torch.Tensor):
        if value.dtype == torch.bool or value.dtype.is_complex:
            raise ValueError(f"`{name}` must hold real angles in degrees, got dtype {value.dtype}")
        return
    if isinstance(value, np.ndarray):
        if not (np.issubdtype(value.dtype, np.integer) or np.issubdtype(value.dtype, np.floating)):
            raise ValueError(f"`{name}` must hold real angles in degrees, got dtype {value.dtype}")
        return
    items = list(value) if isinstance(value, list | tuple) else [value]
    for item in items:
        if isinstance(item, bool) or not isinstance(item, numbers.Real):
            raise ValueError(
                f"`{name}` must be a real number of degrees or a list of them, got {type(item).__name__} "
                f"{item!r}"
            )
