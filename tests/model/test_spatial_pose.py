"""The spatial pose path: the input latent turned by the requested azimuth change (issue 35)."""

from __future__ import annotations

import json

import pytest
import torch
from dummies import read_the_pose

from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import PoseProjection, embed_pose
from sar_zero123.model.guidance import flipped_heading_pose, same_depression_pose
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import check_sampler_start
from sar_zero123.model.spatial_pose import (
    condition_channels,
    rotate_condition_latents,
    unet_condition_latents,
)


def latents(batch: int = 2, channels: int = 4, side: int = 8) -> torch.Tensor:
    return torch.randn(batch, channels, side, side, generator=torch.Generator().manual_seed(0))


def test_a_turn_of_zero_is_the_identity_and_a_full_turn_is_too() -> None:
    x = latents()
    for d_az in (0.0, 360.0, -720.0):
        turned = rotate_condition_latents(x, embed_pose([d_az] * 2, 0.0), rotation_sign=-1)
        torch.testing.assert_close(turned, x, atol=1e-5, rtol=0)


@pytest.mark.parametrize(("sign", "quarter_turns"), [(1, 1), (-1, -1)])
def test_a_quarter_turn_is_rot90_in_the_documented_direction(sign: int, quarter_turns: int) -> None:
    # output (x, y) reads the input at (cos a x - sin a y, sin a x + cos a y): a = 90 deg reads (-y, x)
    x = latents()
    turned = rotate_condition_latents(x, embed_pose([90.0, 90.0], 0.0), rotation_sign=sign)
    torch.testing.assert_close(turned, torch.rot90(x, quarter_turns, dims=(2, 3)), atol=1e-5, rtol=0)
    half = rotate_condition_latents(x, embed_pose([180.0, -180.0], 0.0), rotation_sign=sign)
    torch.testing.assert_close(half, torch.rot90(x, 2, dims=(2, 3)), atol=1e-5, rtol=0)


def test_each_sample_turns_by_its_own_angle_and_zeros_stay_zero() -> None:
    x = latents()
    turned = rotate_condition_latents(x, embed_pose([0.0, 90.0], 0.0), rotation_sign=1)
    torch.testing.assert_close(turned[0], x[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(turned[1], torch.rot90(x[1], 1, dims=(1, 2)), atol=1e-5, rtol=0)
    null = rotate_condition_latents(torch.zeros_like(x), embed_pose([37.0, 211.0], 0.0), rotation_sign=-1)
    assert torch.equal(null, torch.zeros_like(x))  # the guidance null stays null
    # only sin and cos of d_az enter: 370 and 10 give the same bytes
    a = rotate_condition_latents(x[:1].repeat(2, 1, 1, 1), embed_pose([370.0, 10.0], 0.0), rotation_sign=-1)
    assert torch.equal(a[0], a[1])


def test_bad_arguments_are_refused_with_their_names() -> None:
    with pytest.raises(ValueError, match="rotation_sign"):
        rotate_condition_latents(latents(), embed_pose([0.0, 0.0], 0.0), rotation_sign=2)
    with pytest.raises(ValueError, match=r"`pose` \(B, 1, 4\)"):
        rotate_condition_latents(latents(), embed_pose([0.0], 0.0), rotation_sign=1)
    with pytest.raises(ValueError, match="spatial_pose"):
        PoseProjection(8, 4, spatial_pose="rays")
    with pytest.raises(ValueError, match="rotation_sign"):
        PoseProjection(8, 4, rotation_sign=0)
    with pytest.raises(ValueError, match="spatial_pose"):
        condition_channels("rays", 4)


def test_condition_input_is_the_latent_alone_or_the_latent_and_its_turn() -> None:
    x, pose = latents(), embed_pose([30.0, -60.0], 0.0)
    assert unet_condition_latents(x, pose, PoseProjection(8, 4)) is x  # zero-1-to-3, untouched
    projection = PoseProjection(8, 4, spatial_pose="rotated_input", rotation_sign=-1)
    both = unet_condition_latents(x, pose, projection)
    assert both.shape == (2, 8, 8, 8) and torch.equal(both[:, :4], x)
    assert torch.equal(both[:, 4:], rotate_condition_latents(x, pose, -1))
    assert condition_channels(None, 4) == 4 and condition_channels("rotated_input", 4) == 8


def test_a_spatial_pipeline_feeds_the_turned_latent_and_round_trips(tmp_path) -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    assert pipe.unet.config.in_channels == 12 and pipe.pose_projection.config.spatial_pose == "rotated_input"
    seen = []
    pipe.unet.register_forward_pre_hook(lambda module, args: seen.append(args[0].clone()))
    image = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(1))
    out = pipe(image, d_az=90.0, num_inference_steps=2, output_type="pt",
               generator=torch.Generator().manual_seed(0)).images  # fmt: skip
    assert out.shape == (1, 1, 32, 32) and torch.isfinite(out).all()
    first = seen[0]  # (2, 12, 16, 16): [null; conditional] x [x_t, latent, turned latent]
    assert first.shape == (2, 12, 16, 16) and torch.equal(first[0, 4:], torch.zeros_like(first[0, 4:]))
    torch.testing.assert_close(first[1, 8:], torch.rot90(first[1, 4:8], -1, dims=(1, 2)), atol=1e-5, rtol=0)
    pipe.save_pretrained(tmp_path / "pipe")
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "pipe")
    assert loaded.pose_projection.config.spatial_pose == "rotated_input"
    assert loaded.pose_projection.config.rotation_sign == -1


def test_a_pipeline_saved_before_the_field_existed_loads_as_zero123(tmp_path) -> None:
    build_sar_zero123("tiny", seed=0).save_pretrained(tmp_path / "old")
    config_file = tmp_path / "old" / "pose_projection" / "config.json"
    config = json.loads(config_file.read_text())
    config.pop("spatial_pose"), config.pop("rotation_sign")
    config_file.write_text(json.dumps(config))
    (tmp_path / "old" / "manifest.json").unlink()  # folders of that time had none
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "old")
    assert loaded.pose_projection.config.spatial_pose is None and loaded.unet.config.in_channels == 8


def test_a_unet_whose_inputs_do_not_fit_the_mode_is_refused() -> None:
    spatial, plain = build_sar_zero123("tiny", spatial_pose="rotated_input"), build_sar_zero123("tiny")
    with pytest.raises(ValueError, match=r"in_channels` must be 12.*spatial_pose='rotated_input'.*got 8"):
        SARZero123Pipeline(**{**spatial.components, "unet": plain.unet})


def test_heading_guidance_adds_the_pull_away_from_the_flipped_heading(monkeypatch) -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    image = torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(1))
    d_az = [30.0, -100.0]
    calls, steps = [], []

    def record(module, args, kwargs, out):
        calls.append((args, kwargs, out.sample))

    pipe.unet.register_forward_hook(record, with_kwargs=True)
    step = pipe.scheduler.step

    def scheduler_step(noise, *args, **kwargs):
        steps.append(noise)
        return step(noise, *args, **kwargs)

    monkeypatch.setattr(pipe.scheduler, "step", scheduler_step)

    def sample(**options):
        generators = [torch.Generator().manual_seed(k) for k in range(2)]
        return pipe(image, d_az=d_az, num_inference_steps=2, output_type="pt", generator=generators,
                    **options).images  # fmt: skip

    out = sample(guidance_scale=2.5, heading_guidance_scale=4.0)
    assert out.shape == (2, 1, 32, 32) and torch.isfinite(out).all()
    (args, kwargs, noise_pred), noise = calls[0], steps[0]
    assert args[0].shape == (6, 12, 16, 16)  # [null; conditional; flipped] x 2 samples
    uncond, cond, flip = noise_pred.chunk(3)
    torch.testing.assert_close(noise, uncond + 2.5 * (cond - uncond) + 4.0 * (cond - flip))
    # the flipped branch: the same input latent, turned by d_az + 180, and the flipped pose's token
    torch.testing.assert_close(args[0][4:6, 4:8], args[0][2:4, 4:8])
    turned_back = torch.rot90(args[0][2:4, 8:], 2, dims=(2, 3))
    torch.testing.assert_close(args[0][4:6, 8:], turned_back, atol=1e-5, rtol=0)
    pose = embed_pose(d_az, [0.0, 0.0])
    tokens, _ = pipe.encode_conditioning(image, flipped_heading_pose(pose))
    torch.testing.assert_close(kwargs["encoder_hidden_states"][4:6], tokens)
    torch.testing.assert_close(flipped_heading_pose(pose), embed_pose([210.0, 80.0], [0.0, 0.0]))
    # weight 0 is the old sampler exactly; without CFG the flipped branch runs beside the conditional one
    plain = sample(guidance_scale=2.5)
    assert torch.equal(plain, sample(guidance_scale=2.5, heading_guidance_scale=0.0))
    assert not torch.allclose(plain, out)
    calls.clear()
    sample(guidance_scale=1.0, heading_guidance_scale=1.0)
    assert calls[0][0][0].shape == (4, 12, 16, 16)
    with pytest.raises(ValueError, match=r"`heading_guidance_scale` must lie in \[0, 100\], got -1.0"):
        pipe(image, d_az=30.0, heading_guidance_scale=-1.0)
    with pytest.raises(ValueError, match="`heading_guidance_scale` must lie in"):
        pipe(image, d_az=30.0, heading_guidance_scale=float("nan"))


def test_depression_guidance_adds_the_pull_away_from_the_input_depression(monkeypatch) -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input", input_depression=True)
    read_the_pose(pipe.pose_projection)
    image = torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(1))
    d_az, d_el, depression = [30.0, -100.0], [13.0, -7.0], [17.0, 17.0]
    calls, steps = [], []
    pipe.unet.register_forward_hook(lambda m, a, k, out: calls.append((a, k, out.sample)), with_kwargs=True)
    step = pipe.scheduler.step

    def scheduler_step(noise, *args, **kwargs):
        steps.append(noise)
        return step(noise, *args, **kwargs)

    monkeypatch.setattr(pipe.scheduler, "step", scheduler_step)

    def sample(elevation=d_el, **options):
        generators = [torch.Generator().manual_seed(k) for k in range(2)]
        return pipe(image, d_az=d_az, d_el=elevation, input_depression_deg=depression, num_inference_steps=2,
                    output_type="pt", generator=generators, **options).images  # fmt: skip

    out = sample(guidance_scale=2.5, heading_guidance_scale=4.0, depression_guidance_scale=2.0)
    assert out.shape == (2, 1, 32, 32) and torch.isfinite(out).all()
    (args, kwargs, noise_pred), noise = calls[0], steps[0]
    assert args[0].shape == (8, 12, 16, 16)  # [null; conditional; flipped; input depression] x 2 samples
    uncond, cond, flip, same = noise_pred.chunk(4)
    expected = uncond + 2.5 * (cond - uncond) + 4.0 * (cond - flip) + 2.0 * (cond - same)
    torch.testing.assert_close(noise, expected)
    # the contrast branch: the same input latent, turned by the same d_az, with the pose at d_el = 0
    torch.testing.assert_close(args[0][6:8, 4:], args[0][2:4, 4:])
    pose = embed_pose(d_az, d_el, depression)
    assert torch.equal(same_depression_pose(pose), embed_pose(d_az, [0.0, 0.0], depression))
    tokens, _ = pipe.encode_conditioning(image, same_depression_pose(pose))
    torch.testing.assert_close(kwargs["encoder_hidden_states"][6:8], tokens)
    # weight 0 is the old sampler exactly; a request at the input's depression is unchanged by any weight
    plain = sample(guidance_scale=2.5)
    assert torch.equal(plain, sample(guidance_scale=2.5, depression_guidance_scale=0.0))
    assert not torch.allclose(plain, sample(guidance_scale=2.5, depression_guidance_scale=2.0))
    level = sample([0.0, 0.0], guidance_scale=2.5)
    calls.clear()
    assert torch.equal(sample([0.0, 0.0], guidance_scale=2.5, depression_guidance_scale=5.0), level)
    assert calls[0][0][0].shape == (4, 12, 16, 16)  # no third branch: it would add exactly 0
    mixed = sample([0.0, -7.0], guidance_scale=2.5, depression_guidance_scale=5.0)
    torch.testing.assert_close(mixed[0], level[0], atol=1e-5, rtol=0)  # the d_el = 0 request unchanged
    assert not torch.allclose(mixed[1], level[1])
    with pytest.raises(ValueError, match=r"`depression_guidance_scale` must lie in \[0, 100\], got -1.0"):
        sample(depression_guidance_scale=-1.0)
    with pytest.raises(ValueError, match=r"^depression_guidance_scale must lie in \[0, 100\], got nan"):
        check_sampler_start(1.0, 0.0, {"steps": 20}, depression_guidance_scale=float("nan"))
