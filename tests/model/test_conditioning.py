"""Tests for the zero-1-to-3 conditioning: pose vector, PoseProjection, image embeddings and latents."""

from __future__ import annotations

import math

import pytest
import torch
from diffusers import AutoencoderKL
from dummies import dummy_images, get_dummy_components

from sar_zero123.model.conditioning import (
    CLIP_IMAGE_MEAN,
    CLIP_IMAGE_STD,
    PoseProjection,
    embed_pose,
    encode_condition_latents,
    encode_image_embeddings,
    encode_target_latents,
    match_channels,
)


@pytest.fixture(scope="module")
def components():
    return get_dummy_components()


# ------------------------------------------------------------------------------------ embed_pose
def test_embed_pose_hand_computed_values():
    pose = embed_pose([90.0, 180.0, -30.0], [10.0, 0.0, -5.0])
    expected = torch.tensor(
        [
            [math.radians(10.0), 1.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, 0.0],
            [math.radians(-5.0), -0.5, math.sqrt(3.0) / 2.0, 0.0],
        ]
    )
    assert pose.shape == (3, 1, 4)
    assert pose.dtype == torch.float32
    torch.testing.assert_close(pose[:, 0], expected, atol=1e-7, rtol=0)


def _zero123_relative_pose(elevation_cond_deg, azimuth_cond_deg, elevation_target_deg, azimuth_target_deg):
    """zero-1-to-3's get_T for two cameras on a sphere: polar angle from +Z, azimuth atan2(y, x)."""

    def spherical(elevation_deg, azimuth_deg):
        e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
        x, y, z = 1.5 * math.cos(e) * math.cos(a), 1.5 * math.cos(e) * math.sin(a), 1.5 * math.sin(e)
        return math.atan2(math.hypot(x, y), z), math.atan2(y, x)

    theta_c, az_c = spherical(elevation_cond_deg, azimuth_cond_deg)
    theta_t, az_t = spherical(elevation_target_deg, azimuth_target_deg)
    d_az = (az_t - az_c) % (2 * math.pi)
    return [theta_t - theta_c, math.sin(d_az), math.cos(d_az), 0.0]


def test_embed_pose_sign_convention_against_zero123_and_authors():
    # Input chip at depression 15, azimuth 40; target at depression 17, azimuth 100.
    pose = embed_pose(100.0 - 40.0, 17.0 - 15.0)[0, 0].double()
    # The authors' get_T: d_theta = target depression - input depression (radians), sin/cos of d_az.
    d_az = math.radians(60.0)
    authors = torch.tensor([math.radians(2.0), math.sin(d_az), math.cos(d_az), 0.0], dtype=torch.float64)
    torch.testing.assert_close(pose, authors, atol=1e-7, rtol=0)
    # zero-1-to-3 with cameras at elevation = depression: the polar slot has the opposite sign.
    zero123 = torch.tensor(_zero123_relative_pose(15.0, 40.0, 17.0, 100.0), dtype=torch.float64)
    torch.testing.assert_close(pose[0], -zero123[0], atol=1e-7, rtol=0)
    torch.testing.assert_close(pose[1:], zero123[1:], atol=1e-7, rtol=0)


def test_embed_pose_is_periodic_in_azimuth():
    pose = embed_pose([10.0, 370.0, -350.0, 730.0], 3.0)
    for row in range(1, 4):
        assert torch.equal(pose[row], pose[0])


def test_embed_pose_broadcasts_scalars():
    assert embed_pose(45.0, [0.0, 1.0]).shape == (2, 1, 4)
    assert embed_pose(torch.tensor([0.0, 1.0, 2.0]), 0.0).shape == (3, 1, 4)
    assert embed_pose(45.0, 0.0).shape == (1, 1, 4)


@pytest.mark.parametrize(
    ("d_az", "d_el", "match"),
    [
        (float("nan"), 0.0, "d_az_deg"),
        (0.0, float("inf"), "d_el_deg"),
        ([1.0, 2.0], [1.0, 2.0, 3.0], "same length"),
        ([], 0.0, "d_az_deg"),
        ([[1.0, 2.0]], 0.0, "1-D"),
    ],
)
def test_embed_pose_rejects_bad_angles(d_az, d_el, match):
    with pytest.raises(ValueError, match=match):
        embed_pose(d_az, d_el)


# -------------------------------------------------------------------------------- PoseProjection
def test_pose_projection_starts_as_identity_on_the_image_embedding():
    projection = PoseProjection(in_features=12, out_features=8)
    embeds = torch.randn(3, 1, 8, generator=torch.Generator().manual_seed(0))
    pose = embed_pose([10.0, 100.0, 250.0], [0.0, 5.0, -5.0])
    torch.testing.assert_close(projection(embeds, pose), embeds, atol=0, rtol=0)
    assert torch.count_nonzero(projection.projection.weight[:, 8:]) == 0
    assert torch.count_nonzero(projection.projection.bias) == 0


def test_pose_projection_zero123_shape_and_config_round_trip(tmp_path):
    projection = PoseProjection()
    assert tuple(projection.projection.weight.shape) == (768, 772)
    projection.save_pretrained(tmp_path)
    loaded = PoseProjection.from_pretrained(tmp_path)
    assert (loaded.config.in_features, loaded.config.out_features) == (772, 768)
    assert set(loaded.state_dict()) == {"projection.weight", "projection.bias"}


def test_pose_projection_rejects_bad_sizes_and_shapes():
    with pytest.raises(ValueError, match="in_features"):
        PoseProjection(in_features=4, out_features=8)
    projection = PoseProjection(in_features=12, out_features=8)
    with pytest.raises(ValueError, match="image_embeds"):
        projection(torch.zeros(2, 1, 7), torch.zeros(2, 1, 4))
    with pytest.raises(ValueError, match="pose"):
        projection(torch.zeros(2, 1, 8), torch.zeros(3, 1, 4))


# ---------------------------------------------------------------------------- image conditioning
def test_match_channels():
    gray = torch.rand(2, 1, 4, 4)
    assert torch.equal(match_channels(gray, 3), gray.expand(-1, 3, -1, -1))
    torch.testing.assert_close(match_channels(gray.expand(-1, 3, -1, -1), 1), gray, atol=1e-7, rtol=0)
    with pytest.raises(ValueError, match="channels"):
        match_channels(torch.rand(2, 2, 4, 4), 3)


def test_image_embeddings_follow_clip_normalisation(components):
    encoder = components["image_encoder"]
    images = dummy_images(batch_size=2)  # 32 px = the tiny encoder's image_size: no resize
    mean = torch.tensor(CLIP_IMAGE_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(CLIP_IMAGE_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        expected = encoder(pixel_values=(images.expand(-1, 3, -1, -1) - mean) / std).image_embeds
        embeds = encode_image_embeddings(encoder, images)
        embeds_rgb = encode_image_embeddings(encoder, images.expand(-1, 3, -1, -1))
        embeds_single = encode_image_embeddings(encoder, images[1:])
    assert embeds.shape == (2, 1, encoder.config.projection_dim)
    torch.testing.assert_close(embeds[:, 0], expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(embeds_rgb, embeds, atol=0, rtol=0)
    torch.testing.assert_close(embeds_single, embeds[1:], atol=1e-5, rtol=0)


def _cubic_convolution_resize(image, size, a=-0.75):
    """Separable cubic convolution with align_corners=True and replicated borders (float64 NumPy loops):
    the definition behind kornia's resize(interpolation="bicubic", align_corners=True, antialias=False)."""
    import numpy as np

    def kernel(x):
        x = abs(x)
        if x <= 1:
            return (a + 2) * x**3 - (a + 3) * x**2 + 1
        if x < 2:
            return a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a
        return 0.0

    def along_rows(array):
        n_in = array.shape[0]
        out = np.zeros((size,) + array.shape[1:])
        for j in range(size):
            source = j * (n_in - 1) / (size - 1)
            first = math.floor(source)
            for m in range(first - 1, first + 3):
                out[j] += kernel(source - m) * array[min(max(m, 0), n_in - 1)]
        return out

    return along_rows(along_rows(np.asarray(image, dtype=np.float64)).T).T


@pytest.mark.parametrize("input_size", [20, 64])
def test_image_embeddings_resize_like_zero123(components, input_size):
    encoder = components["image_encoder"]
    size = encoder.config.image_size
    images = torch.rand(1, 1, input_size, input_size, generator=torch.Generator().manual_seed(input_size))
    # zero-1-to-3: resize the [-1, 1] image (cubic convolution, align_corners=True), then (x + 1) / 2.
    resized = (_cubic_convolution_resize((images[0, 0] * 2 - 1).double().numpy(), size) + 1) / 2
    reference = torch.from_numpy(resized).float()[None, None]
    torch.testing.assert_close(
        torch.nn.functional.interpolate(images, size=(size, size), mode="bicubic", align_corners=True),
        reference, atol=1e-5, rtol=0,  # float32 resize against the float64 definition
    )
    mean = torch.tensor(CLIP_IMAGE_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(CLIP_IMAGE_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        expected = encoder(pixel_values=(reference.expand(-1, 3, -1, -1) - mean) / std).image_embeds
        embeds = encode_image_embeddings(encoder, images)
        antialiased = torch.nn.functional.interpolate(
            images, size=(size, size), mode="bicubic", align_corners=False, antialias=True
        )
        other = encoder(pixel_values=(antialiased.expand(-1, 3, -1, -1) - mean) / std).image_embeds
    torch.testing.assert_close(embeds[:, 0], expected, atol=1e-5, rtol=0)
    assert (other - expected).abs().max() > 1e-3  # the former preprocessing is measurably different


def test_image_embeddings_resize_other_sizes(components):
    with torch.no_grad():
        embeds = encode_image_embeddings(components["image_encoder"], torch.rand(1, 1, 64, 64))
    assert embeds.shape == (1, 1, components["image_encoder"].config.projection_dim)
    assert torch.isfinite(embeds).all()


def test_condition_latents_are_the_unscaled_posterior_mode(components):
    vae = components["vae"]
    images = dummy_images(batch_size=2)
    with torch.no_grad():
        expected = vae.encode(images * 2.0 - 1.0).latent_dist.mode()
        latents = encode_condition_latents(vae, images)
    assert latents.shape == (2, 4, 16, 16)
    torch.testing.assert_close(latents, expected, atol=0, rtol=0)


def test_target_latents_are_scaled_posterior_samples(components):
    vae = components["vae"]
    images = dummy_images(batch_size=2)
    with torch.no_grad():
        posterior = vae.encode(images * 2.0 - 1.0).latent_dist
        expected = posterior.sample(generator=torch.Generator().manual_seed(3)) * vae.config.scaling_factor
        latents = encode_target_latents(vae, images, generator=torch.Generator().manual_seed(3))
        again = encode_target_latents(vae, images, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(latents, expected, atol=0, rtol=0)
    assert torch.equal(latents, again)
    assert not torch.equal(latents / vae.config.scaling_factor, posterior.mode())


def test_rgb_vae_gets_replicated_single_channel_input():
    torch.manual_seed(0)
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        block_out_channels=(8, 16),
        layers_per_block=1,
        norm_num_groups=8,
    ).eval()
    images = dummy_images(batch_size=1)
    with torch.no_grad():
        single = encode_condition_latents(vae, images)
        rgb = encode_condition_latents(vae, images.expand(-1, 3, -1, -1))
    torch.testing.assert_close(single, rgb, atol=0, rtol=0)
