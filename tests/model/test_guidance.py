"""The guidance branches: which run, how they are stacked for one UNet call, and their guided mix."""

from __future__ import annotations

import torch

from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import embed_pose
from sar_zero123.model.guidance import (
    Branch,
    BranchEncoder,
    GuidedCondition,
    contrast_branches,
    guided_condition,
)


def _condition(guidance_scale: float, contrast_scales: list[float]) -> GuidedCondition:
    latents = torch.zeros(2, 4, 1, 1)
    request = Branch(torch.zeros(2, 1, 8), torch.zeros(2, 1, 4), None)
    return GuidedCondition(
        torch.zeros(1), None, torch.zeros(1), latents, request, guidance_scale, contrast_scales
    )


def test_the_guided_mix_is_the_closed_form_of_every_branch() -> None:
    generator = torch.Generator().manual_seed(0)
    null, request, heading, depression = torch.randn(4, 2, 4, 3, 3, generator=generator, dtype=torch.float64)
    condition = _condition(3.0, [1.5, 0.5])
    assert condition.branches == 4 and condition.do_classifier_free_guidance
    mixed = condition.guide(torch.cat([null, request, heading, depression]))
    expected = null + 3.0 * (request - null) + 1.5 * (request - heading) + 0.5 * (request - depression)
    torch.testing.assert_close(mixed, expected, rtol=0, atol=1e-12)
    # guidance 1: no null branch; the request and one contrast
    unguided = _condition(1.0, [2.0])
    assert unguided.branches == 2 and not unguided.do_classifier_free_guidance
    torch.testing.assert_close(
        unguided.guide(torch.cat([request, heading])), request + 2.0 * (request - heading)
    )
    assert torch.equal(_condition(0.5, []).guide(request), request)


def test_a_contrast_runs_where_its_weight_is_positive_and_its_pose_differs_from_the_request() -> None:
    pose = embed_pose([30.0, 120.0], [4.0, 0.0])
    kinds = [kind for kind, _, _ in contrast_branches(pose, 1.0, 2.0)]
    assert kinds == ["heading", "depression"]
    heading, depression = contrast_branches(pose, 1.0, 2.0)
    torch.testing.assert_close(heading[2], embed_pose([210.0, 300.0], [4.0, 0.0]), rtol=0, atol=1e-6)
    assert torch.equal(depression[2], embed_pose([30.0, 120.0], [0.0, 0.0])) and depression[1] == 2.0
    assert [kind for kind, _, _ in contrast_branches(pose, 0.0, 2.0)] == ["depression"]
    flat = embed_pose([30.0, 120.0], [0.0, 0.0])  # every d_el 0: the depression contrast is the request
    assert [kind for kind, _, _ in contrast_branches(flat, 1.0, 2.0)] == ["heading"]


def test_the_branches_are_stacked_null_request_contrasts() -> None:
    pipe = build_sar_zero123("tiny", seed=0)
    generator = torch.Generator().manual_seed(1)
    embeds = torch.randn(2, 1, pipe.image_encoder.config.projection_dim, generator=generator)  # (B, 1, E)
    encoder = BranchEncoder(pipe.pose_projection, pipe.unet, embeds, None, 3, torch.float32)
    pose = embed_pose([30.0, -60.0], [5.0, 5.0])
    latents = torch.randn(6, 4, 16, 16, generator=generator)
    contrasts = contrast_branches(pose, 1.0, 1.0)
    condition = guided_condition(encoder, pose, contrasts, latents, 2.0, None, 0.18)
    assert condition.branches == 4 and condition.contrast_scales == [1.0, 1.0]
    tokens = condition.tokens.reshape(4, 6, 1, -1)  # (branches, samples, 1, D)
    assert torch.equal(tokens[0], torch.zeros_like(tokens[0]))  # the null's token
    request = pipe.pose_projection(embeds, pose).repeat_interleave(3, dim=0)
    torch.testing.assert_close(tokens[1], request, rtol=0, atol=0)
    heading = pipe.pose_projection(embeds, contrasts[0][2]).repeat_interleave(3, dim=0)
    torch.testing.assert_close(tokens[2], heading, rtol=0, atol=0)
    stacked = condition.unet_condition.reshape(4, 6, 4, 16, 16)
    assert torch.equal(stacked[0], torch.zeros_like(latents))  # the null's condition latent
    assert all(torch.equal(stacked[k], latents) for k in (1, 2, 3))
    assert condition.class_labels is None and torch.equal(condition.input_latents, latents)
