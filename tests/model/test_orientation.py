"""Tests of sar_zero123.model.orientation: the input azimuth, estimated and turned by the pose."""

from __future__ import annotations

import math

import pytest
import torch
from diffusers import DDPMScheduler

from sar_zero123 import SARZero123Pipeline, build_sar_zero123, embed_pose
from sar_zero123.model.conditioning import pose_class_labels
from sar_zero123.model.orientation import (
    AzimuthEstimator,
    azimuth_deg,
    azimuth_estimation_loss,
    azimuth_vector,
    target_view_features,
    turn_azimuth,
)
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import ImageEmbedder, compute_losses, conditioning_sensitivity
from tests.dummies import dummy_images


@pytest.fixture(scope="module")
def pipe() -> SARZero123Pipeline:
    return build_sar_zero123("tiny", estimate_input_azimuth=True, input_code_dim=3)


def test_turn_azimuth_adds_the_pose_angle() -> None:
    generator = torch.Generator().manual_seed(0)
    azimuth = torch.rand(64, generator=generator, dtype=torch.float64) * 720 - 360
    d_az = torch.rand(64, generator=generator, dtype=torch.float64) * 720 - 360
    turned = turn_azimuth(azimuth_vector(azimuth), embed_pose(d_az, torch.zeros(64)))
    torch.testing.assert_close(turned, azimuth_vector(azimuth + d_az), atol=1e-6, rtol=0)


def test_azimuth_vector_is_sine_then_cosine() -> None:
    torch.testing.assert_close(
        azimuth_vector([0.0, 90.0, 180.0, -90.0]),
        torch.tensor([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]]),
        atol=1e-7,
        rtol=0,
    )


def test_azimuth_deg_inverts_azimuth_vector_and_ignores_the_code() -> None:
    azimuth = torch.tensor([0.0, 45.0, 179.5, 180.0, 270.0, 359.9], dtype=torch.float64)
    vector = torch.cat([azimuth_vector(azimuth), torch.randn(6, 3)], dim=-1)  # a code after the azimuth
    torch.testing.assert_close(azimuth_deg(vector), azimuth, atol=1e-4, rtol=0)
    longer = 2.5 * azimuth_vector([-90.0])  # an unnormalised vector; negative angles map into [0, 360)
    torch.testing.assert_close(azimuth_deg(longer), torch.tensor([270.0], dtype=torch.float64))


def test_target_view_features_turn_the_azimuth_and_keep_the_code() -> None:
    estimate = torch.cat([azimuth_vector([40.0, 300.0]), torch.tensor([[1.0, -2.0], [0.5, 3.0]])], dim=-1)
    features = target_view_features(estimate, embed_pose([50.0, 90.0], [0.0, 0.0]))
    torch.testing.assert_close(features[:, :2], azimuth_vector([90.0, 30.0]), atol=1e-6, rtol=0)
    assert torch.equal(features[:, 2:], estimate[:, 2:])


def test_azimuth_estimation_loss_is_one_minus_cosine() -> None:
    estimate = torch.cat([azimuth_vector([30.0, 30.0, 30.0, 30.0]), torch.randn(4, 5)], dim=-1)
    loss = azimuth_estimation_loss(estimate, torch.tensor([30.0, 120.0, 210.0, 90.0]))
    torch.testing.assert_close(
        loss, torch.tensor([0.0, 1.0, 2.0, 1 - math.cos(math.radians(60))]), atol=1e-6, rtol=0
    )


@pytest.mark.parametrize("side", [8, 16, 20])
def test_estimator_returns_a_unit_azimuth_and_a_code_for_any_latent_size(side: int) -> None:
    torch.manual_seed(0)
    estimator = AzimuthEstimator(latent_channels=4, hidden_channels=(8, 16, 16), code_dim=5)
    outputs = estimator(torch.randn(3, 4, side, side))
    assert outputs.shape == (3, 7) and estimator.output_dim == 7
    torch.testing.assert_close(outputs[:, :2].norm(dim=-1), torch.ones(3), atol=1e-6, rtol=0)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"latent_channels": 0}, "latent_channels"),
        ({"hidden_channels": ()}, "hidden_channels"),
        ({"code_dim": -1}, "code_dim"),
    ],
)
def test_estimator_refuses_bad_sizes(kwargs: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        AzimuthEstimator(**kwargs)


def test_pose_class_labels_append_the_target_view_features(pipe: SARZero123Pipeline) -> None:
    pose = embed_pose([30.0, 90.0], [0.0, 2.0])
    features = torch.randn(2, 5)
    labels = pose_class_labels(pipe.unet, pose, features)
    assert labels.shape == (2, 9)
    torch.testing.assert_close(labels[:, :4], pose[:, 0])
    torch.testing.assert_close(labels[:, 4:], features)
    with pytest.raises(ValueError, match="5 target-view features.*got 0"):
        pose_class_labels(pipe.unet, pose)
    with pytest.raises(ValueError, match="got 2 target-view features"):
        pose_class_labels(pipe.unet, pose, features[:, :2])


def test_pose_class_labels_refuse_features_the_unet_does_not_take() -> None:
    plain = build_sar_zero123("tiny", pose_in_time_embedding=True)
    with pytest.raises(ValueError, match="0 target-view features"):
        pose_class_labels(plain.unet, embed_pose([0.0], [0.0]), azimuth_vector([0.0]))
    zero123_layout = build_sar_zero123("tiny")
    with pytest.raises(ValueError, match="does not embed the pose"):
        pose_class_labels(zero123_layout.unet, embed_pose([0.0], [0.0]), azimuth_vector([0.0]))


def test_estimator_is_built_seeded_and_leaves_the_other_components_unchanged() -> None:
    with_estimator = build_sar_zero123("tiny", estimate_input_azimuth=True, seed=3)
    again = build_sar_zero123("tiny", estimate_input_azimuth=True, seed=3)
    plain = build_sar_zero123("tiny", seed=3)
    for a, b in zip(with_estimator.azimuth_estimator.parameters(), again.azimuth_estimator.parameters()):
        assert torch.equal(a, b)
    for a, b in zip(with_estimator.vae.parameters(), plain.vae.parameters()):
        assert torch.equal(a, b)
    assert plain.azimuth_estimator is None
    assert with_estimator.unet.config.class_embed_type == "projection"
    assert with_estimator.unet.config.projection_class_embeddings_input_dim == 4 + 2 + 16


def test_pipeline_needs_the_estimator_exactly_when_the_unet_takes_its_azimuth(
    pipe: SARZero123Pipeline,
) -> None:
    components = dict(pipe.components)
    with pytest.raises(ValueError, match="azimuth_estimator"):
        SARZero123Pipeline(**{**components, "azimuth_estimator": None})
    plain = build_sar_zero123("tiny")
    with pytest.raises(ValueError, match="azimuth_estimator"):
        SARZero123Pipeline(**{**plain.components, "azimuth_estimator": pipe.azimuth_estimator})


def test_pipeline_with_estimator_round_trips_and_turns_with_the_pose(
    pipe: SARZero123Pipeline, tmp_path
) -> None:
    image = dummy_images(1, seed=2)

    def run(p: SARZero123Pipeline, d_az: float) -> torch.Tensor:
        return p(
            image,
            d_az=d_az,
            d_el=0.0,
            num_inference_steps=2,
            guidance_scale=3.0,
            generator=torch.Generator().manual_seed(0),
            output_type="pt",
        ).images

    pipe.set_progress_bar_config(disable=True)
    reference = run(pipe, 30.0)
    pipe.save_pretrained(tmp_path)
    loaded = SARZero123Pipeline.from_pretrained(tmp_path)
    loaded.set_progress_bar_config(disable=True)
    assert isinstance(loaded.azimuth_estimator, AzimuthEstimator)
    # the same weights, to float rounding: a reloaded module may take other CPU kernels (6e-7 on AMD EPYC)
    torch.testing.assert_close(run(loaded, 30.0), reference, rtol=0, atol=1e-5)
    # the turned azimuth reaches the UNet: same seed, other pose, other output
    assert (run(pipe, 210.0) - reference).abs().max() > 1e-3


def _batch() -> dict:
    images = dummy_images(4, seed=5)
    return {
        "input": images[:2],
        "target": images[2:],
        "d_az_deg": torch.tensor([30.0, -150.0]),
        "d_el_deg": torch.tensor([0.0, 2.0]),
        "input_azimuth_deg": torch.tensor([10.0, 250.0]),
    }


def _losses(pipe: SARZero123Pipeline, batch: dict, weight: float):
    return compute_losses(
        batch,
        unet=pipe.unet,
        pose_projection=pipe.pose_projection,
        vae=pipe.vae,
        image_encoder=ImageEmbedder(pipe.image_encoder),
        encoder=None,
        noise_scheduler=DDPMScheduler.from_config(pipe.scheduler.config),
        generator=torch.Generator().manual_seed(3),
        azimuth_estimator=pipe.azimuth_estimator,
        loss_settings=LossSettings(pfm_weight=0.0, azimuth_loss_weight=weight),
    )


def test_training_step_adds_the_weighted_estimator_loss_and_trains_the_estimator(
    pipe: SARZero123Pipeline,
) -> None:
    batch = _batch()
    losses = _losses(pipe, batch, weight=0.5)
    with torch.no_grad():
        condition = pipe.vae.encode(batch["input"] * 2 - 1).latent_dist.mode()
        expected = azimuth_estimation_loss(pipe.azimuth_estimator(condition), batch["input_azimuth_deg"])
    torch.testing.assert_close(losses.azimuth, expected, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(losses.loss, losses.denoising + 0.5 * losses.azimuth)
    pipe.azimuth_estimator.zero_grad()
    losses.loss.mean().backward()
    head = pipe.azimuth_estimator.head.weight.grad
    assert head is not None and head.abs().sum() > 0
    for module in (pipe.unet, pipe.pose_projection, pipe.azimuth_estimator, pipe.vae, pipe.image_encoder):
        module.zero_grad(set_to_none=True)


def test_training_step_needs_the_input_azimuth(pipe: SARZero123Pipeline) -> None:
    batch = _batch()
    del batch["input_azimuth_deg"]
    with pytest.raises(ValueError, match="input_azimuth_deg"):
        _losses(pipe, batch, weight=1.0)


def test_sensitivity_runs_with_the_estimator(pipe: SARZero123Pipeline) -> None:
    result = conditioning_sensitivity(
        _batch(),
        unet=pipe.unet,
        pose_projection=pipe.pose_projection,
        vae=pipe.vae,
        image_encoder=ImageEmbedder(pipe.image_encoder),
        noise_scheduler=DDPMScheduler.from_config(pipe.scheduler.config),
        timesteps=(500,),
        azimuth_estimator=pipe.azimuth_estimator,
    )
    assert set(result) == {"pose_t500", "input_t500"} and result["pose_t500"] > 0


def test_several_images_per_input_get_the_single_image_conditioning(pipe: SARZero123Pipeline) -> None:
    pipe.set_progress_bar_config(disable=True)
    image, kwargs = dummy_images(1, seed=4), {"d_az": 75.0, "d_el": 0.0, "num_inference_steps": 2}

    def run(count: int) -> torch.Tensor:
        generators = [torch.Generator().manual_seed(k) for k in range(count)]
        output = pipe(image, num_images_per_prompt=count, generator=generators, output_type="pt", **kwargs)
        return output.images

    single, double = run(1), run(2)
    torch.testing.assert_close(double[:1], single, atol=1e-5, rtol=0)
    assert not torch.allclose(double[0], double[1])  # other noise, other view


def test_an_estimator_from_another_run_is_refused_and_its_own_loads(tmp_path) -> None:
    from sar_zero123.data import DecibelScaling
    from sar_zero123.model.orientation import estimator_weights_digest
    from sar_zero123.model.pipeline import SARZero123Pipeline
    from sar_zero123.training.finetuning import export_finetuned

    pipe = build_sar_zero123("tiny", estimate_input_azimuth=True, seed=3)
    export_finetuned(tmp_path / "pipeline", pipe, DecibelScaling())
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "pipeline")
    recorded = loaded.pose_projection.config.trained_estimator
    assert recorded == estimator_weights_digest(pipe.azimuth_estimator) == estimator_weights_digest(
        loaded.azimuth_estimator.half()  # a float16 copy (a bundled prior's) is the same estimator
    )
    other = build_sar_zero123("tiny", estimate_input_azimuth=True, seed=4).azimuth_estimator
    with pytest.raises(ValueError, match=r"`azimuth_estimator`: weights SHA-256 .* but the UNet was trained"):
        SARZero123Pipeline(**{**loaded.components, "azimuth_estimator": other})
