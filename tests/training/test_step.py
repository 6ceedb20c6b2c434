"""Tests of sar_zero123.training.step and training.latent_cache: cached encodings, the step, buckets."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from diffusers import DDPMScheduler
from torch.utils.data import DataLoader, default_collate

from sar_zero123.data import ChipRecord, ViewPairDataset
from sar_zero123.training.latent_cache import (
    CachedViewPairs,
    ChipLatentCache,
    collate_pairs,
    load_chip_images,
)
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import (
    ImageEmbedder,
    compute_losses,
    conditioning_sensitivity,
    min_snr_weights,
    timestep_bucket_losses,
)
from tests.dummies import dummy_images, get_dummy_components


@pytest.fixture(scope="module")
def components():
    return get_dummy_components()


def step_losses(batch, components, seed: int = 3, loss_settings: LossSettings | None = None, **kwargs):
    return compute_losses(
        batch,
        unet=components["unet"],
        pose_projection=components["pose_projection"],
        vae=components["vae"],
        image_encoder=ImageEmbedder(components["image_encoder"]),
        encoder=None,
        noise_scheduler=DDPMScheduler.from_config(components["scheduler"].config),
        generator=torch.Generator().manual_seed(seed),
        loss_settings=loss_settings,
        **kwargs,
    )


def test_cached_encodings_give_the_losses_of_encoding_every_step(components) -> None:
    images = dummy_images(4, seed=5)
    cache = ChipLatentCache.encode(images, components["vae"], components["image_encoder"], batch_size=3)
    assert cache.latent_mean.shape == (4, 4, 16, 16) and cache.image_embeds.shape == (4, 1, 16)
    batch = {
        "input": images[:2],
        "target": images[2:],
        "d_az_deg": torch.tensor([30.0, -150.0]),
        "d_el_deg": torch.tensor([0.0, 2.0]),
    }
    cached = {
        **batch,
        "input_latent_mean": cache.latent_mean[:2],
        "target_latent_mean": cache.latent_mean[2:],
        "target_latent_logvar": cache.latent_logvar[2:],
        "input_image_embeds": cache.image_embeds[:2],
    }
    with torch.no_grad():
        reference, fast = step_losses(batch, components), step_losses(cached, components)
    torch.testing.assert_close(fast.loss, reference.loss, rtol=1e-5, atol=1e-6)
    assert torch.equal(fast.timesteps, reference.timesteps)


def test_a_step_without_loss_settings_is_plain_zero123(components) -> None:
    batch = {"input": dummy_images(2, seed=1), "target": dummy_images(2, seed=2),
             "d_az_deg": torch.tensor([30.0, -90.0]), "d_el_deg": torch.zeros(2)}  # fmt: skip
    with torch.no_grad():
        default = step_losses(batch, components)
        plain = step_losses(batch, components, loss_settings=LossSettings(pfm_weight=0.0))
    assert torch.equal(default.loss, plain.loss) and torch.equal(default.pfm, torch.zeros(2))


def test_cached_view_pairs_serve_the_wrapped_pairs(tmp_path) -> None:
    rng = np.random.default_rng(0)
    records = []
    for k, azimuth in enumerate((10.0, 100.0, 190.0)):
        path = tmp_path / f"chip{k}.npy"
        np.save(path, rng.random((16, 16), dtype=np.float32))
        records.append(ChipRecord(str(path), "A", "s1", 17.0, azimuth))
    pairs = ViewPairDataset(records, size=16, seed=1)
    images = load_chip_images(pairs)
    cache = ChipLatentCache(
        images=images,
        latent_mean=torch.arange(3.0).view(3, 1, 1, 1).expand(3, 4, 2, 2),
        latent_logvar=torch.zeros(3, 4, 2, 2),
        image_embeds=None,
        scaling_factor=1.0,
    )
    cached = CachedViewPairs(pairs, cache)
    for index in range(len(pairs)):
        plain, fast = pairs[index], cached[index]
        assert torch.equal(fast["input"], plain["input"]) and torch.equal(fast["target"], plain["target"])
        assert fast["d_az_deg"] == pytest.approx(plain["d_az_deg"]) and fast["label"] == plain["label"]
        source, target = pairs.pairs[index]
        assert fast["input_latent_mean"][0, 0, 0] == source and fast["target_latent_mean"][0, 0, 0] == target
    cached.set_epoch(4)
    assert pairs.epoch == 4
    with pytest.raises(ValueError, match="cache holds 2 chips"):
        CachedViewPairs(pairs, ChipLatentCache(images[:2], images[:2], images[:2], None, 1.0))


def test_cached_view_pairs_fetch_a_batch_as_default_collate_stacks_its_items(tmp_path) -> None:
    rng = np.random.default_rng(2)
    records = []
    for k in range(12):  # two objects at two depressions, azimuths across the wrap
        path = tmp_path / f"chip{k}.npy"
        np.save(path, rng.random((16, 16), dtype=np.float32))
        obj, depression, azimuth = k % 2, (15.0, 17.0)[(k // 2) % 2], (355.0, 5.0, 180.0)[k // 4]
        records.append(ChipRecord(str(path), "AB"[obj], f"s{obj}", depression, azimuth))
    pairs = ViewPairDataset(records, size=16, seed=3, same_depression=False, pairs_per_chip=3)
    images = load_chip_images(pairs)
    embeds = torch.randn(12, 1, 8)
    cache = ChipLatentCache(images, torch.randn(12, 4, 2, 2), torch.randn(12, 4, 2, 2), embeds, 1.0)
    cached = CachedViewPairs(pairs, cache)
    indices = [5, 0, 17, 3, 3, 30]
    batch, reference = cached.__getitems__(indices), default_collate([cached[i] for i in indices])
    assert sorted(batch) == sorted(reference)
    for key, value in reference.items():
        assert batch[key].dtype == value.dtype and torch.equal(batch[key], value), key
    assert sorted(set(batch["d_az_deg"].abs().tolist())) == [10.0, 175.0]  # 355 -> 5 deg wraps to +-10
    assert collate_pairs(batch) is batch  # a stacked batch passes through
    loaded = next(iter(DataLoader(cached, batch_size=6, shuffle=False, collate_fn=collate_pairs)))
    for key, value in default_collate([cached[i] for i in range(6)]).items():
        assert torch.equal(loaded[key], value), key


def test_chip_latent_cache_rejects_bad_images(components) -> None:
    with pytest.raises(ValueError, match="non-empty"):
        ChipLatentCache.encode(torch.zeros(0, 1, 32, 32), components["vae"])
    with pytest.raises(ValueError, match="non-finite"):
        ChipLatentCache.encode(torch.full((1, 1, 32, 32), float("nan")), components["vae"])


def test_conditioning_sensitivity_is_zero_for_a_model_that_ignores_its_conditioning(components) -> None:
    batch = {
        "input": dummy_images(3, seed=1),
        "target": dummy_images(3, seed=2),
        "d_az_deg": torch.tensor([30.0, 90.0, -60.0]),
        "d_el_deg": torch.zeros(3),
    }
    kwargs = dict(
        pose_projection=components["pose_projection"],
        vae=components["vae"],
        image_encoder=ImageEmbedder(components["image_encoder"]),
        noise_scheduler=DDPMScheduler.from_config(components["scheduler"].config),
    )
    unet = components["unet"]

    class Blind(torch.nn.Module):  # the noisy latent only: condition latent and tokens zeroed
        config = unet.config

        def forward(self, sample, t, encoder_hidden_states, class_labels=None):
            sample = torch.cat([sample[:, :4], torch.zeros_like(sample[:, 4:])], dim=1)
            return unet(sample, t, encoder_hidden_states=torch.zeros_like(encoder_hidden_states))

    blind = conditioning_sensitivity(batch, unet=Blind(), **kwargs)
    assert set(blind) == {f"{kind}_t{t}" for kind in ("pose", "input") for t in (100, 500, 900)}
    assert all(value == 0.0 for value in blind.values())
    seeing = conditioning_sensitivity(batch, unet=unet, **kwargs)
    assert all(value > 1e-4 for key, value in seeing.items() if key.startswith("input"))
    with pytest.raises(ValueError, match="at least 2 pairs"):
        conditioning_sensitivity({k: v[:1] for k, v in batch.items()}, unet=unet, **kwargs)


def test_timestep_bucket_losses_are_bucket_means() -> None:
    losses = torch.tensor([1.0, 3.0, 5.0, 7.0, 9.0])
    timesteps = torch.tensor([0, 249, 250, 999, 600])
    assert timestep_bucket_losses(losses, timesteps, 1000) == {
        "t000-249": 2.0,
        "t250-499": 5.0,
        "t500-749": 9.0,
        "t750-999": 7.0,
    }
    assert timestep_bucket_losses(losses[:1], timesteps[:1], 1000) == {"t000-249": 1.0}


@pytest.mark.parametrize("pose_in_time_embedding", [False, True])
def test_pose_in_time_embedding_is_the_only_pose_path_when_the_token_ignores_the_pose(
    pose_in_time_embedding, tmp_path
) -> None:
    from sar_zero123.model.build import build_sar_zero123
    from sar_zero123.model.pipeline import SARZero123Pipeline

    pipe = build_sar_zero123("tiny", pose_in_time_embedding=pose_in_time_embedding)
    with torch.no_grad():  # zero-1-to-3's initial projection: the token does not see the pose yet
        assert pipe.pose_projection.projection.weight[:, -4:].abs().sum() == 0
        for parameter in pipe.unet.class_embedding.parameters() if pose_in_time_embedding else ():
            parameter.normal_(0.0, 1.0)
    pipe.save_pretrained(tmp_path / "pipe")
    pipe = SARZero123Pipeline.from_pretrained(tmp_path / "pipe")
    pipe.set_progress_bar_config(disable=True)
    views = [
        pipe(
            dummy_images(1, seed=3),
            d_az=d_az,
            d_el=0.0,
            num_inference_steps=2,
            generator=torch.Generator().manual_seed(0),
            output_type="pt",
        ).images
        for d_az in (0.0, 90.0)
    ]
    difference = (views[0] - views[1]).abs().max().item()
    assert (pipe.unet.config.class_embed_type == "projection") == pose_in_time_embedding
    assert difference > 1e-4 if pose_in_time_embedding else difference == 0.0


def test_min_snr_weights_closed_form() -> None:
    from sar_zero123.training.step import min_snr_weights

    scheduler = DDPMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear", beta_start=0.00085,
                              beta_end=0.012)  # fmt: skip
    timesteps = torch.tensor([0, 100, 500, 999])
    abar = scheduler.alphas_cumprod[timesteps].double()
    snr = abar / (1 - abar)
    expected = torch.clamp(snr, max=5.0) / snr
    weights = min_snr_weights(scheduler, timesteps, 5.0).double()
    torch.testing.assert_close(weights, expected, rtol=1e-5, atol=0)
    assert min_snr_weights(scheduler, timesteps, 5.0)[-1] == pytest.approx(1.0)  # high noise: SNR < gamma
    v_scheduler = DDPMScheduler.from_config(scheduler.config, prediction_type="v_prediction")
    v_weights = min_snr_weights(v_scheduler, timesteps, 5.0).double()
    torch.testing.assert_close(v_weights, torch.clamp(snr, max=5.0) / (snr + 1), rtol=1e-5, atol=0)
    with pytest.raises(ValueError, match="snr_gamma must be > 0"):
        min_snr_weights(scheduler, timesteps, 0.0)


def test_min_snr_weighting_scales_l_simple_and_keeps_every_draw(components) -> None:
    images = dummy_images(4, seed=5)
    batch = {
        "input": images[:2],
        "target": images[2:],
        "d_az_deg": torch.tensor([30.0, -150.0]),
        "d_el_deg": torch.tensor([0.0, 2.0]),
    }
    with torch.no_grad():
        plain = step_losses(batch, components)
        weighted = step_losses(batch, components, loss_settings=LossSettings(pfm_weight=0.0, snr_gamma=0.5))
    assert torch.equal(weighted.timesteps, plain.timesteps)  # the same draws: only the weighting differs
    scheduler = DDPMScheduler.from_config(components["scheduler"].config)
    weights = min_snr_weights(scheduler, plain.timesteps, 0.5)
    assert (weights < 1).any()  # gamma below SNR at some sampled t: the weighting changes the loss
    torch.testing.assert_close(weighted.denoising, plain.denoising * weights)
    torch.testing.assert_close(weighted.loss, weighted.denoising)  # lambda = 0: Eq. (21) is L_simple


def test_chosen_timesteps_replace_the_draw_and_leave_the_other_draws_alone(components) -> None:
    images = dummy_images(4, seed=5)
    batch = {"input": images[:2], "target": images[2:], "d_az_deg": torch.tensor([30.0, -150.0]),
             "d_el_deg": torch.tensor([0.0, 2.0])}  # fmt: skip
    with torch.no_grad():
        drawn = step_losses(batch, components)
        same = step_losses(batch, components, timesteps=drawn.timesteps.clone())
        other = step_losses(batch, components, timesteps=torch.tensor([5, 900]))
    torch.testing.assert_close(same.loss, drawn.loss, rtol=0, atol=0)  # same noise, dropout and timesteps
    assert other.timesteps.tolist() == [5, 900] and not torch.equal(other.loss, drawn.loss)
    for bad in (torch.tensor([5.0, 900.0]), torch.tensor([5, 6, 7])):
        with pytest.raises(ValueError, match="timesteps: expected \\(2,\\) integers"):
            step_losses(batch, components, timesteps=bad)
