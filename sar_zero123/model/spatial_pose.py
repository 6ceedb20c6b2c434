"""The spatial pose modes: what the UNet sees of the input view besides its latent.

``None`` (zero-1-to-3): the input's latent alone; ``"rotated_input"``: also that latent turned in the
image plane by the requested azimuth change; ``"proxy"``: also the input's simulator proxy at the input's
and the requested pose. Training and sampling build the UNet's input with :func:`unet_condition_latents`.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import gaussian_filter

from sar_zero123.model.conditioning import (
    POSE_DIM,
    PROXY_FORMS,
    SPATIAL_POSE_MODES,
    encode_condition_latents,
)

__all__ = [
    "check_turn_inputs",
    "condition_channels",
    "GEOMETRY_BLUR_PX",
    "GEOMETRY_THRESHOLD",
    "proxy_condition_views",
    "proxy_form",
    "proxy_geometry",
    "proxy_pair_latents",
    "use_proxy_geometry",
    "rotate_condition_latents",
    "takes_proxy",
    "unet_condition_latents",
    "widen_for_proxy",
]


def condition_channels(spatial_pose: str | None, latent_channels: int) -> int:
    """Channels of the UNet's condition input: ``1``, ``2`` or ``4`` times ``latent_channels``.

    Raises:
        ValueError: If ``spatial_pose`` is not one of :data:`SPATIAL_POSE_MODES`.
    """
    if spatial_pose not in SPATIAL_POSE_MODES:
        raise ValueError(f"`spatial_pose` must be one of {SPATIAL_POSE_MODES}, got {spatial_pose!r}")
    return latent_channels * {None: 1, "rotated_input": 2, "proxy": 4}[spatial_pose]


def takes_proxy(pose_projection: torch.nn.Module) -> bool:
    """Whether the model's UNet takes the simulator proxy pair (``spatial_pose == "proxy"``)."""
    config = getattr(pose_projection, "module", pose_projection).config
    return getattr(config, "spatial_pose", None) == "proxy"


#: Gaussian blur (pixels) a proxy view takes before its masks are drawn: the bank's fit blur, which
#: averages the speckle of one render away.
GEOMETRY_BLUR_PX = 1.5
#: A blurred pixel is lit (shadow) where it lies this many robust standard deviations (1.4826 x the median
#: absolute deviation) above (below) the view's median, the ground clutter's level.
GEOMETRY_THRESHOLD = 2.0
#: The spread below which a view is flat (all ground): a constant view has no geometry.
_MIN_SPREAD = 1e-6


def proxy_geometry(views: torch.Tensor) -> torch.Tensor:
    """A proxy view's geometry without its intensities: shadow 0, ground 0.5, lit 1.

    Each view (normalised dB, any affine map of decibels) is blurred by :data:`GEOMETRY_BLUR_PX` (scipy's
    ``gaussian_filter``, reflected border); pixels more than :data:`GEOMETRY_THRESHOLD` robust standard
    deviations from its median are lit or shadow, the rest ground. Where the proxy vehicle is wrong in its
    scatterers but right in its footprint and shadow, only what is right reaches the UNet, and the input
    must supply the intensities (a real chip's, not the simulator's).

    Shape:
        ``(B, 1 | 3, H, W) -> (B, 1, H, W)``, float32 on the views' device.

    Raises:
        ValueError: If ``views`` is not 4-D or not finite.
    """
    if views.ndim != 4 or not torch.isfinite(views).all():
        raise ValueError(f"proxy views: expected finite (B, 1 | 3, H, W), got shape {tuple(views.shape)}")
    gray = views.detach().float().mean(dim=1).cpu().numpy()  # (B, H, W)
    blurred = gaussian_filter(gray, sigma=(0.0, GEOMETRY_BLUR_PX, GEOMETRY_BLUR_PX), mode="reflect")
    median = np.median(blurred, axis=(1, 2), keepdims=True)
    spread = 1.4826 * np.median(np.abs(blurred - median), axis=(1, 2), keepdims=True)
    bound = GEOMETRY_THRESHOLD * np.maximum(spread, _MIN_SPREAD)
    masks = np.full_like(blurred, 0.5)
    masks[blurred > median + bound] = 1.0
    masks[blurred < median - bound] = 0.0
    return torch.from_numpy(masks[:, None].astype(np.float32)).to(views.device)


def proxy_form(pose_projection: torch.nn.Module) -> str:
    """What a (possibly DDP-wrapped) proxy model reads of its proxy: one of :data:`PROXY_FORMS`."""
    config = getattr(pose_projection, "module", pose_projection).config
    return getattr(config, "proxy_form", "render")


def proxy_condition_views(views: torch.Tensor, form: str) -> torch.Tensor:
    """Proxy views as a model of ``form`` encodes them: the render itself, or :func:`proxy_geometry`.

    Raises:
        ValueError: If ``form`` is not one of :data:`PROXY_FORMS`.
    """
    if form not in PROXY_FORMS:
        raise ValueError(f"`proxy_form` must be one of {PROXY_FORMS}, got {form!r}")
    return views if form == "render" else proxy_geometry(views)


def use_proxy_geometry(pose_projection: torch.nn.Module) -> None:
    """Make a proxy model read its proxies as geometry (:func:`proxy_geometry`) from now on; its weights
    are kept, so a fine-tune adapts them.

    Raises:
        ValueError: If the model does not take a proxy.
    """
    if not takes_proxy(pose_projection):
        raise ValueError("proxy_geometry: only a spatial_pose='proxy' model reads a proxy")
    pose_projection.register_to_config(proxy_form="geometry")


def check_turn_inputs(latents: torch.Tensor, pose: torch.Tensor, rotation_sign: int) -> None:
    """Refuse latents and poses a turn by ``rotation_sign * d_az`` cannot take.

    Raises:
        ValueError: If ``latents`` is not ``(B, C, h, w)``, ``pose`` not ``(B, 1, 4)`` or ``rotation_sign``
            not +-1.
    """
    if rotation_sign not in (-1, 1):
        raise ValueError(f"`rotation_sign` must be +1 or -1, got {rotation_sign!r}")
    if latents.ndim != 4 or pose.shape != (latents.shape[0], 1, POSE_DIM):
        raise ValueError(
            f"`latents` must be (B, C, h, w) and `pose` (B, 1, {POSE_DIM}), got {tuple(latents.shape)} and "
            f"{tuple(pose.shape)}"
        )


def rotate_condition_latents(latents: torch.Tensor, pose: torch.Tensor, rotation_sign: int) -> torch.Tensor:
    """The input latent turned about the chip centre by ``rotation_sign * d_az`` (bilinear, reflected border).

    A vehicle turned in azimuth turns its footprint by the same angle in the image plane, while shadow and
    layover stay tied to the range direction: the turned latent shows where the body lies, the UNet
    corrects the rest. Output ``(x, y)`` (normalised, x right, y down) samples the input at
    ``(cos a x - sin a y, sin a x + cos a y)``. Zeros turn to zeros, so the guidance null stays null.

    Shape:
        latents ``(B, C, h, w)``, pose ``(B, 1, 4)`` -> ``(B, C, h, w)``.

    Raises:
        ValueError: If the shapes do not match or ``rotation_sign`` is not +-1.
    """
    check_turn_inputs(latents, pose, rotation_sign)
    sin = rotation_sign * pose[:, 0, 1].to(device=latents.device, dtype=torch.float32)
    cos = pose[:, 0, 2].to(device=latents.device, dtype=torch.float32)
    zero = torch.zeros_like(sin)
    rows = [torch.stack([cos, -sin, zero], -1), torch.stack([sin, cos, zero], -1)]
    matrix = torch.stack(rows, 1)  # (B, 2, 3)
    grid = F.affine_grid(matrix, list(latents.shape), align_corners=False)
    turned = F.grid_sample(latents.float(), grid, padding_mode="reflection", align_corners=False)
    return turned.to(latents.dtype)


def unet_condition_latents(
    condition_latents: torch.Tensor,
    pose: torch.Tensor,
    pose_projection: torch.nn.Module,
    proxy_latents: torch.Tensor | None = None,
) -> torch.Tensor:
    """What the UNet concatenates to the noisy latent, by the pose projection's ``spatial_pose``.

    Args:
        condition_latents: The (possibly dropped, i.e. zeroed) unscaled input latents.
        proxy_latents: ``"proxy"`` only: :func:`proxy_pair_latents`; never dropped for guidance.

    Raises:
        ValueError: If ``proxy_latents`` is missing for a proxy model, given to another, or misshaped.

    Shape:
        ``(B, C, h, w)``, ``(B, 1, 4)``, ``(B, 2C, h, w)`` -> ``(B, C | 2C | 4C, h, w)``.
    """
    config = getattr(pose_projection, "module", pose_projection).config
    mode = getattr(config, "spatial_pose", None)
    if (mode == "proxy") != (proxy_latents is not None):
        raise ValueError(
            "proxy_latents: a UNet with spatial_pose='proxy' takes the proxy pair's latents, any other none "
            f"(this one: spatial_pose={mode!r}, proxy_latents "
            f"{'given' if proxy_latents is not None else 'missing'})"
        )
    if mode is None:
        return condition_latents
    turned = rotate_condition_latents(condition_latents, pose, config.rotation_sign)
    if mode == "rotated_input":
        return torch.cat([condition_latents, turned], dim=1)
    expected = (condition_latents.shape[0], 2 * condition_latents.shape[1], *condition_latents.shape[2:])
    if tuple(proxy_latents.shape) != expected:
        raise ValueError(f"proxy_latents: expected shape {expected}, got {tuple(proxy_latents.shape)}")
    return torch.cat([condition_latents, turned, proxy_latents.to(condition_latents.dtype)], dim=1)


def proxy_pair_latents(
    vae: torch.nn.Module, at_input: torch.Tensor, at_target: torch.Tensor, form: str = "render"
) -> torch.Tensor:
    """The unscaled VAE posterior modes of the proxy at the input's and at the requested pose, stacked,
    each view in the model's ``form`` (:func:`proxy_condition_views`).

    Shape:
        ``(B, 1 | 3, H, W)`` twice -> ``(B, 2C, h, w)``.
    """
    return torch.cat(
        [encode_condition_latents(vae, proxy_condition_views(view, form)) for view in (at_input, at_target)],
        dim=1,
    )


def widen_for_proxy(unet: torch.nn.Module, pose_projection: torch.nn.Module) -> None:
    """Turn a ``"rotated_input"`` model into a ``"proxy"`` one in place, computing exactly what it did (the
    first convolution's new ``2 * latent_channels`` inputs start at zero).

    Raises:
        ValueError: If the model is not a ``"rotated_input"`` one.
    """
    config = pose_projection.config
    if getattr(config, "spatial_pose", None) != "rotated_input":
        raise ValueError(
            "spatial_pose: a proxy model widens a 'rotated_input' one (e.g. sar-zero123/sim-prior-rotated), "
            f"got spatial_pose={getattr(config, 'spatial_pose', None)!r}"
        )
    old = unet.conv_in
    latent_channels = unet.config.out_channels
    extra = 2 * latent_channels
    new = torch.nn.Conv2d(
        old.in_channels + extra, old.out_channels, old.kernel_size, old.stride, old.padding,
        dtype=old.weight.dtype, device=old.weight.device,
    )  # fmt: skip
    with torch.no_grad():
        new.weight.zero_()
        new.weight[:, : old.in_channels] = old.weight
        new.bias.copy_(old.bias)
    unet.conv_in = new
    unet.register_to_config(in_channels=old.in_channels + extra)
    pose_projection.register_to_config(spatial_pose="proxy")
