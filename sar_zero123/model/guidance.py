"""The guidance branches of a sampling call, stacked into one batched UNet call per step, and their mix.

Up to four branches per output sample: zero-1-to-3's classifier-free null (zero token and condition
latent; the pose is never dropped), the request, and one contrast branch per contrast weight (the heading
flipped, :func:`flipped_heading_pose`, or the input's own depression, :func:`same_depression_pose`):

    eps = eps_null + w * (eps_request - eps_null) + sum_k s_k * (eps_request - eps_contrast_k)

(the null term only where ``w > 1``). A contrast equal to the request adds exactly 0 and is not run.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import torch

from sar_zero123.model.conditioning import pose_class_labels
from sar_zero123.model.input_tokens import input_token_context
from sar_zero123.model.orientation import target_view_features
from sar_zero123.model.reference_attention import (
    attending_to_reference,
    input_reference,
    own_pose,
    reference_weights,
    uses_reference,
)
from sar_zero123.model.spatial_pose import unet_condition_latents

__all__ = [
    "Branch", "BranchEncoder", "GuidedCondition", "contrast_branches", "flipped_heading_pose",
    "guided_condition", "reference_context", "same_depression_pose",
]  # fmt: skip


def flipped_heading_pose(pose: torch.Tensor) -> torch.Tensor:
    """The pose with the azimuth change turned by 180 deg (``sin``, ``cos`` negated). ``(B, 1, 4)``."""
    flipped = pose.clone()
    flipped[..., 1:3] = -flipped[..., 1:3]
    return flipped


def same_depression_pose(pose: torch.Tensor) -> torch.Tensor:
    """The pose at the input's own depression (``d_el`` set to 0). ``(B, 1, 4)``."""
    same = pose.clone()
    same[..., 0] = 0.0
    return same


def contrast_branches(
    pose: torch.Tensor, heading_scale: float, depression_scale: float
) -> list[tuple[str, float, torch.Tensor]]:
    """The contrast branches a call runs, ``(kind, scale, pose)``: ``"heading"`` then ``"depression"``,
    each where its weight is positive and its pose differs from the request's.
    """
    candidates = (
        ("heading", heading_scale, flipped_heading_pose(pose)),
        ("depression", depression_scale, same_depression_pose(pose)),
    )
    return [c for c in candidates if c[1] > 0.0 and not torch.equal(c[2], pose)]


@dataclass
class Branch:
    """One branch's inputs per output sample: token ``(N, 1, D)``, pose ``(N, 1, 4)``, class labels or
    ``None``.
    """

    tokens: torch.Tensor
    pose: torch.Tensor
    class_labels: torch.Tensor | None


@dataclass
class BranchEncoder:
    """The pose-dependent part of the condition, for any pose of the call's inputs.

    Args:
        image_embeds: The inputs' CLIP embeddings, once per input ``(B, 1, E)``.
        estimate: The azimuth estimator's reading of each input, where the UNet takes it, else ``None``.
        num_images_per_prompt: Output samples per input; each branch gets one row per sample.
        dtype: The UNet's dtype.
    """

    pose_projection: torch.nn.Module
    unet: torch.nn.Module
    image_embeds: torch.Tensor
    estimate: torch.Tensor | None
    num_images_per_prompt: int
    dtype: torch.dtype

    def branch(self, pose: torch.Tensor) -> Branch:
        """The branch of ``pose`` ``(B, 1, 4)``: its token, per-sample pose and class labels."""
        repeats = self.num_images_per_prompt
        tokens = self.pose_projection(self.image_embeds, pose.to(self.image_embeds.device))
        tokens = tokens.repeat_interleave(repeats, dim=0).to(self.dtype)
        features = None if self.estimate is None else target_view_features(self.estimate, pose)
        if features is not None:
            features = features.repeat_interleave(repeats, dim=0)
        per_sample = pose.repeat_interleave(repeats, dim=0)
        labels = pose_class_labels(self.unet, per_sample, features)
        return Branch(tokens, per_sample, None if labels is None else labels.to(self.dtype))


@dataclass
class GuidedCondition:
    """Everything the denoising loop hands the UNet at each step, every branch stacked
    ``([null;] request; contrasts...)``.

    Args:
        tokens: Cross-attention tokens ``(branches * N, 1, D)``.
        class_labels: The UNet's class labels, or ``None``.
        unet_condition: What the UNet concatenates to the noisy latent.
        input_latents: Each output sample's unscaled input latent ``(N, C, h, w)`` (an image-to-image start).
        request: The request's branch (its pose turns a ``"turned_input"`` start).
        guidance_scale: Classifier-free guidance weight; the null runs where it is above 1.
        contrast_scales: Each contrast branch's weight, in order.
        reference: The reference-attention context, or a null context.
        input_tokens: The input-token context (none for the null), or a null context.
    """

    tokens: torch.Tensor
    class_labels: torch.Tensor | None
    unet_condition: torch.Tensor
    input_latents: torch.Tensor
    request: Branch
    guidance_scale: float
    contrast_scales: list[float]
    reference: contextlib.AbstractContextManager = field(default_factory=contextlib.nullcontext)
    input_tokens: contextlib.AbstractContextManager = field(default_factory=contextlib.nullcontext)

    @property
    def dtype(self) -> torch.dtype:
        """The UNet's dtype, which every branch input and the latents take."""
        return self.input_latents.dtype

    @property
    def do_classifier_free_guidance(self) -> bool:
        """Whether the null branch runs (``guidance_scale > 1``)."""
        return self.guidance_scale > 1.0

    @property
    def branches(self) -> int:
        """How many branches each output sample runs per step."""
        return 1 + int(self.do_classifier_free_guidance) + len(self.contrast_scales)

    def guide(self, noise_pred: torch.Tensor) -> torch.Tensor:
        """The guided noise estimate (module docstring) from the stacked prediction.
        ``(branches * N, C, h, w) -> (N, C, h, w)``.
        """
        parts = list(noise_pred.chunk(self.branches))
        noise_contrasts = parts[len(parts) - len(self.contrast_scales) :]
        parts = parts[: len(parts) - len(self.contrast_scales)]
        if self.do_classifier_free_guidance:
            noise_uncond, noise_cond = parts
            noise_pred = noise_uncond + self.guidance_scale * (noise_cond - noise_uncond)
        else:
            noise_cond = noise_pred = parts[0]
        for scale, noise_contrast in zip(self.contrast_scales, noise_contrasts, strict=True):
            noise_pred = noise_pred + scale * (noise_cond - noise_contrast)
        return noise_pred


def guided_condition(
    encoder: BranchEncoder,
    pose: torch.Tensor,
    contrasts: list[tuple[str, float, torch.Tensor]],
    input_latents: torch.Tensor,
    guidance_scale: float,
    proxy_latents: torch.Tensor | None,
    scaling_factor: float,
) -> GuidedCondition:
    """The branches stacked for one UNet call per step: ``[null;] request; contrasts...``.

    Args:
        pose: The request's pose, once per input ``(B, 1, 4)``.
        contrasts: :func:`contrast_branches`.
        input_latents: Each output sample's input latent ``(N, C, h, w)``, in the UNet's dtype.
        proxy_latents: A ``spatial_pose="proxy"`` UNet's proxy pairs, once per input
            ``(1 + len(contrasts), B, 2C, h, w)``; the null keeps the request's.
        scaling_factor: The VAE's (for the reference pass).

    Returns:
        The condition: the null's condition latent is zeros, the others' the input's, turned by each
        branch's pose where the model takes it spatially.
    """
    request = encoder.branch(pose)
    do_classifier_free_guidance = guidance_scale > 1.0
    branches = [request] + [encoder.branch(contrast_pose) for _, _, contrast_pose in contrasts]
    latents = [input_latents] * len(branches)
    if do_classifier_free_guidance:  # the null: zeros after the projection and for the condition latent
        branches = [Branch(torch.zeros_like(request.tokens), request.pose, request.class_labels)] + branches
        latents = [torch.zeros_like(input_latents)] + latents
    labels = None
    if request.class_labels is not None:
        labels = torch.cat([branch.class_labels for branch in branches])
    if proxy_latents is not None:  # (1 + contrasts, B, 2C, h, w) -> one row per sample and branch
        proxy_latents = proxy_latents.repeat_interleave(encoder.num_images_per_prompt, dim=1).flatten(0, 1)
        if do_classifier_free_guidance:
            proxy_latents = torch.cat([proxy_latents[: input_latents.shape[0]], proxy_latents])
    latents, poses = torch.cat(latents), torch.cat([branch.pose for branch in branches])
    condition = GuidedCondition(
        tokens=torch.cat([branch.tokens for branch in branches]),
        class_labels=labels,
        unet_condition=unet_condition_latents(latents, poses, encoder.pose_projection, proxy_latents),
        input_latents=input_latents,
        request=request,
        guidance_scale=guidance_scale,
        contrast_scales=[scale for _, scale, _ in contrasts],
        input_tokens=input_token_context(encoder.unet, encoder.pose_projection, latents, poses),
    )
    if uses_reference(encoder.pose_projection):  # once per call: the input's own features
        condition.reference = reference_context(
            encoder, pose, input_latents, proxy_latents, condition.branches, do_classifier_free_guidance,
            scaling_factor,
        )  # fmt: skip
    return condition


def reference_context(
    encoder: BranchEncoder,
    pose: torch.Tensor,
    input_latents: torch.Tensor,
    proxy_latents: torch.Tensor | None,
    branches: int,
    do_classifier_free_guidance: bool,
    scaling_factor: float,
) -> contextlib.AbstractContextManager:
    """The reference pass and the context in which every branch but the null attends to its input's
    features.

    Args:
        pose: The request's pose, once per input ``(B, 1, 4)``.
        input_latents: One per output sample (the real inputs', not the null's).
        proxy_latents: The stacked branches' proxy pairs (first half: the proxy at the input's pose).
    """
    own = encoder.branch(own_pose(pose))
    num_samples = input_latents.shape[0]
    proxy_at_input = None
    if proxy_latents is not None:
        proxy_at_input = proxy_latents[-num_samples:, : input_latents.shape[1]]
    features = input_reference(
        encoder.unet, encoder.pose_projection, input_latents, own.pose, own.tokens, own.class_labels,
        scaling_factor, proxy_at_input,
    )  # fmt: skip
    rows = torch.arange(num_samples, device=input_latents.device).repeat(branches)
    keep = torch.ones(branches * num_samples, dtype=torch.bool)
    if do_classifier_free_guidance:  # the null runs without the reference
        keep[:num_samples] = False
    weights = reference_weights(encoder.pose_projection, keep).detach()
    return attending_to_reference(encoder.unet, features, rows, weights)
