"""Tests of sar_zero123.training.losses: Eq. (19)-(21), numerical safety and the batch-fraction option."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F
from diffusers import AutoencoderKL, DDPMScheduler
from torch import nn

from sar_zero123.training.losses import (
    DEFAULT_PFM_MIN_SNR,
    MIN_ALPHA_CUMPROD,
    LossSettings,
    append_dims,
    denoising_loss,
    denoising_target,
    estimate_x0,
    pfm_timestep_mask,
    signal_to_noise_ratio,
    total_loss,
)
from sar_zero123.training.pfm import (
    PFM_PROJECTION_FILE,
    ProjectedFeatureEncoder,
    load_pfm_encoder,
    pfm_loss,
    project_encoder_features,
    random_feature_projection,
)

SCHEDULES = {
    "scaled_linear": dict(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012),
    "linear": dict(beta_schedule="linear"),
    "squaredcos_cap_v2": dict(beta_schedule="squaredcos_cap_v2"),
    "zero_snr": dict(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012,
                     rescale_betas_zero_snr=True),
}
HARD_TIMESTEPS = torch.tensor([0, 1, 500, 999])


class TinyEncoder(nn.Module):
    """Stand-in for SAREncoder: (B, 1, S, S) -> (B, 8) pooled features, ``config.image_size``."""

    feature_dim = 8

    def __init__(self, image_size: int = 16) -> None:
        super().__init__()
        self.config = SimpleNamespace(image_size=image_size)
        self.conv = nn.Conv2d(1, 8, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.silu(self.conv(x)).mean(dim=(2, 3))


def frozen(module: nn.Module) -> nn.Module:
    return module.eval().requires_grad_(False)


@pytest.fixture(scope="module")
def vae() -> AutoencoderKL:
    torch.manual_seed(0)
    model = AutoencoderKL(in_channels=1, out_channels=1, down_block_types=("DownEncoderBlock2D",) * 2,
                          up_block_types=("UpDecoderBlock2D",) * 2, block_out_channels=(8, 8),
                          latent_channels=4, norm_num_groups=4, sample_size=16)
    return frozen(model)


@pytest.fixture(scope="module")
def encoder() -> TinyEncoder:
    torch.manual_seed(1)
    return frozen(TinyEncoder(16))


def scheduler_for(name: str, prediction_type: str = "epsilon") -> DDPMScheduler:
    return DDPMScheduler(num_train_timesteps=1000, prediction_type=prediction_type, **SCHEDULES[name])


def test_append_dims_shape_and_error() -> None:
    assert append_dims(torch.ones(3), 4).shape == (3, 1, 1, 1)
    with pytest.raises(ValueError, match="target_ndim"):
        append_dims(torch.ones(3, 2), 1)


def test_estimate_x0_epsilon_matches_eq19_by_hand() -> None:
    scheduler = scheduler_for("scaled_linear")
    abar = scheduler.alphas_cumprod[500].item()  # 0.27633...
    x_t = torch.full((1, 1, 1, 1), 0.7)
    eps = torch.full((1, 1, 1, 1), -0.3)
    expected = 0.7 / math.sqrt(abar) - math.sqrt(1 / abar - 1) * -0.3
    out = estimate_x0(x_t, eps, torch.tensor([500]), scheduler)
    assert out.item() == pytest.approx(expected, rel=1e-6)
    assert expected == pytest.approx(1.8171, abs=1e-3)


@pytest.mark.parametrize("schedule", list(SCHEDULES))
@pytest.mark.parametrize("prediction_type", ["epsilon", "v_prediction", "sample"])
def test_estimate_x0_inverts_add_noise(schedule: str, prediction_type: str) -> None:
    scheduler = scheduler_for(schedule, prediction_type)
    generator = torch.Generator().manual_seed(0)
    x0 = torch.randn(4, 4, 2, 2, generator=generator)
    noise = torch.randn(4, 4, 2, 2, generator=generator)
    timesteps = torch.tensor([0, 1, 500, 900])  # SNR > 1e-3 everywhere: exact inversion
    x_t = scheduler.add_noise(x0, noise, timesteps)
    target = denoising_target(x0, noise, timesteps, scheduler)
    torch.testing.assert_close(estimate_x0(x_t, target, timesteps, scheduler), x0, atol=2e-4, rtol=1e-4)


def test_estimate_x0_v_prediction_exact_at_zero_terminal_snr() -> None:
    scheduler = scheduler_for("zero_snr", "v_prediction")
    x0, noise = torch.randn(1, 4, 2, 2), torch.randn(1, 4, 2, 2)
    t = torch.tensor([999])
    x_t = scheduler.add_noise(x0, noise, t)
    v = scheduler.get_velocity(x0, noise, t)
    torch.testing.assert_close(estimate_x0(x_t, v, t, scheduler), x0, atol=1e-5, rtol=1e-5)


def test_estimate_x0_epsilon_floor_at_zero_terminal_snr() -> None:
    scheduler = scheduler_for("zero_snr")
    assert scheduler.alphas_cumprod[999].item() == 0.0
    out = estimate_x0(torch.ones(1, 1, 1, 1), torch.zeros(1, 1, 1, 1), torch.tensor([999]), scheduler)
    assert out.item() == pytest.approx(1 / math.sqrt(MIN_ALPHA_CUMPROD)) == pytest.approx(4096.0)


def test_estimate_x0_rejects_bad_input() -> None:
    scheduler = scheduler_for("linear")
    x = torch.zeros(2, 4, 2, 2)
    with pytest.raises(ValueError, match="timesteps must lie"):
        estimate_x0(x, x, torch.tensor([0, 1000]), scheduler)
    with pytest.raises(ValueError, match="integer"):
        estimate_x0(x, x, torch.tensor([0.0, 1.0]), scheduler)
    with pytest.raises(ValueError, match="differ"):
        estimate_x0(x, x[:1], torch.tensor([0, 1]), scheduler)
    scheduler.register_to_config(prediction_type="flow")
    with pytest.raises(ValueError, match="prediction_type"):
        estimate_x0(x, x, torch.tensor([0, 1]), scheduler)


def test_denoising_loss_per_sample() -> None:
    output = torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    target = torch.tensor([[0.0, 0.0], [3.0, 1.0]])
    torch.testing.assert_close(denoising_loss(output, target), torch.tensor([2.5, 5.0]))
    with pytest.raises(ValueError, match="differ"):
        denoising_loss(output, target[:1])


def test_default_threshold_keeps_the_paper_schedule_and_caps_the_others() -> None:
    every_t = torch.arange(1000)
    kept = {name: int(pfm_timestep_mask(every_t, scheduler_for(name)).sum()) for name in SCHEDULES}
    assert kept == {"scaled_linear": 1000, "linear": 738, "squaredcos_cap_v2": 959, "zero_snr": 888}
    for name in SCHEDULES:
        snr = signal_to_noise_ratio(scheduler_for(name), every_t)
        assert (1 / snr[snr >= DEFAULT_PFM_MIN_SNR].sqrt()).max() <= 1 / math.sqrt(DEFAULT_PFM_MIN_SNR)


def test_snr_and_mask() -> None:
    scheduler = scheduler_for("scaled_linear")
    snr = signal_to_noise_ratio(scheduler, HARD_TIMESTEPS)
    assert snr[-1].item() == pytest.approx(0.00466 / (1 - 0.00466), rel=1e-2)
    assert pfm_timestep_mask(HARD_TIMESTEPS, scheduler, 0.05).tolist() == [True, True, True, False]
    assert pfm_timestep_mask(HARD_TIMESTEPS, scheduler, 0.0).all()
    with pytest.raises(ValueError, match="min_snr"):
        pfm_timestep_mask(HARD_TIMESTEPS, scheduler, -1.0)


def reference_pfm(x0_hat, target_images, vae, encoder) -> torch.Tensor:
    """Naive Eq. (20): decode, to [0, 1], resize, encode, squared L2 (one sample at a time)."""
    values = []
    for i in range(x0_hat.shape[0]):
        decoded = vae.decode(x0_hat[i:i + 1] / vae.config.scaling_factor).sample
        size = encoder.config.image_size
        a = F.interpolate((decoded + 1) / 2, size=(size, size), mode="bilinear", antialias=True)
        b = F.interpolate(target_images[i:i + 1], size=(size, size), mode="bilinear", antialias=True)
        values.append(((encoder(a) - encoder(b)) ** 2).sum())
    return torch.stack(values)


def test_pfm_loss_matches_reference_and_grads_reach_only_latents(vae, encoder) -> None:
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(3, 1, 32, 32, generator=generator)
    x0_hat = torch.randn(3, 4, 16, 16, generator=generator, requires_grad=True)
    # 32 px chips, encoder trained at 16 px: resized
    loss = pfm_loss(x0_hat, target, vae, encoder)
    assert loss.shape == (3,)
    torch.testing.assert_close(loss, reference_pfm(x0_hat, target, vae, encoder), atol=1e-6, rtol=1e-5)
    loss.sum().backward()
    assert x0_hat.grad is not None and x0_hat.grad.abs().sum() > 0
    assert all(p.grad is None for p in list(vae.parameters()) + list(encoder.parameters()))


def test_pfm_loss_zero_for_identical_images(vae, encoder) -> None:
    latents = torch.randn(2, 4, 16, 16)
    with torch.no_grad():
        decoded = vae.decode(latents / vae.config.scaling_factor).sample
    target = (decoded + 1) / 2
    torch.testing.assert_close(pfm_loss(latents, target, vae, encoder), torch.zeros(2), atol=1e-10, rtol=0)


def test_pfm_loss_rejects_trainable_modules_and_bad_shapes(vae, encoder) -> None:
    latents, target = torch.randn(1, 4, 16, 16), torch.rand(1, 1, 32, 32)
    trainable = TinyEncoder(16).eval()
    with pytest.raises(ValueError, match="encoder must be frozen"):
        pfm_loss(latents, target, vae, trainable)
    with pytest.raises(ValueError, match="eval mode"):
        pfm_loss(latents, target, vae, frozen(TinyEncoder(16)).train())
    with pytest.raises(ValueError, match="batch sizes"):
        pfm_loss(latents, target.repeat(2, 1, 1, 1), vae, encoder)
    with pytest.raises(ValueError, match="VAE factor"):
        pfm_loss(latents, torch.rand(1, 1, 16, 16), vae, encoder)


def test_total_loss_lambda_zero_skips_pfm_and_rejects_negative() -> None:
    scheduler = scheduler_for("scaled_linear")
    output, target = torch.ones(2, 4, 2, 2), torch.zeros(2, 4, 2, 2)
    out = total_loss(output, target, output, torch.tensor([3, 4]), scheduler, pfm_weight=0.0)
    torch.testing.assert_close(out.loss, torch.ones(2))
    assert out.pfm.tolist() == [0.0, 0.0] and not out.pfm_mask.any()
    with pytest.raises(ValueError, match="pfm_weight"):
        total_loss(output, target, output, torch.tensor([3, 4]), scheduler, pfm_weight=-1.0)
    with pytest.raises(ValueError, match="needs target_images"):
        total_loss(output, target, output, torch.tensor([3, 4]), scheduler, pfm_weight=1.0)
    with pytest.raises(ValueError, match="pfm_fraction"):
        total_loss(output, target, output, torch.tensor([3, 4]), scheduler, pfm_weight=0.0, pfm_fraction=0)


def test_total_loss_fraction_and_mask(vae, encoder) -> None:
    scheduler = scheduler_for("scaled_linear")
    generator = torch.Generator().manual_seed(2)
    x_t = torch.randn(4, 4, 16, 16, generator=generator)
    output = torch.randn(4, 4, 16, 16, generator=generator)
    images = torch.rand(4, 1, 32, 32, generator=generator)
    timesteps = torch.tensor([10, 200, 400, 999])  # the last is below SNR 0.05
    kwargs = dict(pfm_weight=4.0, target_images=images, vae=vae, encoder=encoder, pfm_min_snr=0.05)
    full = total_loss(output, output, x_t, timesteps, scheduler, **kwargs)
    assert full.pfm_mask.tolist() == [True, True, True, False]
    x0 = estimate_x0(x_t[:3], output[:3], timesteps[:3], scheduler)
    torch.testing.assert_close(full.pfm[:3], pfm_loss(x0, images[:3], vae, encoder))
    torch.testing.assert_close(full.loss, 4.0 * full.pfm)
    half = total_loss(output, output, x_t, timesteps, scheduler, pfm_fraction=0.5,
                      generator=torch.Generator().manual_seed(0), **kwargs)
    assert int(half.pfm_mask.sum()) == 2  # ceil(0.5 * 3 eligible)
    picked = half.pfm_mask.nonzero().flatten()
    torch.testing.assert_close(half.pfm[picked], full.pfm[picked] * 1.5)  # unbiased: 3 eligible / 2 kept


def test_total_loss_weights_l_simple_before_adding_lambda_pfm(vae, encoder) -> None:
    scheduler = scheduler_for("scaled_linear")
    generator = torch.Generator().manual_seed(4)
    x_t = torch.randn(3, 4, 16, 16, generator=generator)
    output = torch.randn(3, 4, 16, 16, generator=generator)
    target, images = torch.zeros(3, 4, 16, 16), torch.rand(3, 1, 32, 32, generator=generator)
    timesteps, weights = torch.tensor([10, 300, 900]), torch.tensor([0.5, 1.0, 2.0])
    kwargs = dict(pfm_weight=3.0, target_images=images, vae=vae, encoder=encoder, pfm_min_snr=0.0)
    plain = total_loss(output, target, x_t, timesteps, scheduler, **kwargs)
    weighted = total_loss(output, target, x_t, timesteps, scheduler, denoising_weights=weights, **kwargs)
    mse = output.pow(2).flatten(1).mean(1)  # L_simple against a zero target, by hand
    torch.testing.assert_close(weighted.denoising, mse * weights)
    torch.testing.assert_close(weighted.pfm, plain.pfm)
    torch.testing.assert_close(weighted.loss, mse * weights + 3.0 * plain.pfm)  # Eq. (21)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"pfm_weight": -1.0}, r"pfm_weight must be >= 0, got -1.0"),
        ({"pfm_weight": float("nan")}, r"pfm_weight must be >= 0, got nan"),
        ({"pfm_fraction": 0.0}, r"pfm_fraction must be in \(0, 1\], got 0.0"),
        ({"drop_image_prob": 0.6, "drop_both_prob": 0.6}, r"drop_image_prob, .* got \(0.6, 0.6, 0.05\)"),
        ({"snr_gamma": 0.0}, r"snr_gamma must be > 0 or None, got 0.0"),
        ({"azimuth_loss_weight": -0.5}, r"azimuth_loss_weight must be >= 0, got -0.5"),
    ],
)
def test_loss_settings_refuse_each_bad_value_by_its_field_name(values, message) -> None:
    with pytest.raises(ValueError, match=message):
        LossSettings(**values)


def test_loss_settings_default_to_the_papers_loss() -> None:
    settings = LossSettings()
    assert settings.pfm_weight == 4.0 and settings.snr_gamma is None  # Eq. 21 with the paper's lambda
    assert settings.pfm_min_snr == DEFAULT_PFM_MIN_SNR


class TinyDenoiser(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(4, 4, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


FP16_ON_GPU = pytest.param(
    torch.float16, marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="fp16 is checked on a GPU")
)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, FP16_ON_GPU])
@pytest.mark.parametrize("prediction_type", ["epsilon", "v_prediction"])
@pytest.mark.parametrize("schedule", list(SCHEDULES))
@pytest.mark.parametrize("min_snr", [0.0, 0.05])
def test_loss_and_grads_finite_at_hard_timesteps(
    vae, encoder, schedule, prediction_type, dtype, min_snr
) -> None:
    torch.manual_seed(0)
    device = "cuda" if dtype == torch.float16 else "cpu"
    scheduler = scheduler_for(schedule, prediction_type)
    model = TinyDenoiser().to(device, dtype)
    vae_d, encoder_d = vae.to(device, dtype), encoder.to(device, dtype)
    timesteps = HARD_TIMESTEPS.to(device)
    try:
        images = torch.rand(4, 1, 32, 32, device=device)
        latents = torch.randn(4, 4, 16, 16, device=device)
        noise = torch.randn(4, 4, 16, 16, device=device)
        x_t = scheduler.add_noise(latents, noise, timesteps).to(dtype)
        output = model(x_t)
        target = denoising_target(latents, noise, timesteps, scheduler).to(dtype)
        out = total_loss(
            output,
            target,
            x_t,
            timesteps,
            scheduler,
            pfm_weight=4.0,
            target_images=images.to(dtype),
            vae=vae_d,
            encoder=encoder_d,
            pfm_min_snr=min_snr,
        )
        out.loss.mean().backward()
    finally:
        vae.to("cpu", torch.float32), encoder.to("cpu", torch.float32)
    assert torch.isfinite(out.loss).all()
    assert out.pfm_mask[:3].all()
    assert out.pfm_mask[3].item() == (min_snr == 0.0)
    grads = torch.cat([p.grad.float().flatten() for p in model.parameters()])
    assert torch.isfinite(grads).all() and grads.abs().sum() > 0


def test_pfm_loss_with_sar_encoder(vae) -> None:
    from sar_zero123.encoder import SAREncoder, SAREncoderConfig

    torch.manual_seed(0)
    sar_encoder = frozen(SAREncoder(SAREncoderConfig(image_size=16, depths=(1,), hidden_sizes=(8,),
                                                     embedding_size=8)))
    x0_hat = torch.randn(2, 4, 16, 16, requires_grad=True)
    target = torch.rand(2, 1, 32, 32)
    loss = pfm_loss(x0_hat, target, vae, sar_encoder)
    assert loss.shape == (2,) and (loss > 0).all()
    loss.sum().backward()
    assert torch.isfinite(x0_hat.grad).all()


# ------------------------------------------------------------------- paper-comparable PFM projection
def test_random_feature_projection_is_seeded_default_linear_init() -> None:
    weight = random_feature_projection(512, 10, seed=3)
    assert weight.shape == (10, 512) and weight.dtype == torch.float32
    assert torch.equal(weight, random_feature_projection(512, 10, seed=3))
    assert not torch.equal(weight, random_feature_projection(512, 10, seed=4))
    # nn.Linear's default init: U(-1/sqrt(in), 1/sqrt(in)), variance 1 / (3 in).
    bound = 1 / math.sqrt(512)
    assert weight.abs().max().item() <= bound
    assert weight.var().item() == pytest.approx(1 / (3 * 512), rel=0.05)
    with pytest.raises(ValueError, match="positive"):
        random_feature_projection(0, 10)


def test_projected_pfm_equals_authors_mse_of_fc_outputs(vae, encoder, tmp_path) -> None:
    projected = project_encoder_features(encoder, 10, seed=0)
    assert isinstance(projected, ProjectedFeatureEncoder) and projected.config is encoder.config
    assert project_encoder_features(encoder, None) is encoder
    generator = torch.Generator().manual_seed(2)
    target = torch.rand(3, 1, 32, 32, generator=generator)
    x0_hat = torch.randn(3, 4, 16, 16, generator=generator, requires_grad=True)
    loss = pfm_loss(x0_hat, target, vae, projected)
    # Reference: the authors' fc layer (weight W, any bias) then mse_loss over the 10 outputs, per sample.
    fc = nn.Linear(8, 10)
    with torch.no_grad():
        fc.weight.copy_(random_feature_projection(8, 10, seed=0))
    size = encoder.config.image_size
    reference = []
    for i in range(3):
        with torch.no_grad():
            decoded = vae.decode(x0_hat[i:i + 1] / vae.config.scaling_factor).sample
        a = F.interpolate((decoded + 1) / 2, size=(size, size), mode="bilinear", antialias=True)
        b = F.interpolate(target[i:i + 1], size=(size, size), mode="bilinear", antialias=True)
        reference.append(F.mse_loss(fc(encoder(a)), fc(encoder(b))))
    torch.testing.assert_close(loss, torch.stack(reference).detach(), atol=1e-7, rtol=1e-5)
    loss.sum().backward()
    assert x0_hat.grad.abs().sum() > 0 and all(p.grad is None for p in encoder.parameters())
    projected.save_projection(tmp_path)
    from safetensors.torch import load_file

    torch.testing.assert_close(load_file(tmp_path / PFM_PROJECTION_FILE)["weight"], projected.weight)


def test_projection_shrinks_pfm_by_three_times_feature_dim_on_average() -> None:
    # E_W[mean_k ((W d)_k)^2] = ||d||^2 / (3 D) for any difference d: check over 400 seeded draws.
    difference = torch.randn(1, 64, generator=torch.Generator().manual_seed(0))
    ratios = []
    for seed in range(400):
        weight = random_feature_projection(64, 10, seed=seed)
        ratios.append((F.linear(difference, weight) ** 2).mean() / (difference**2).sum())
    assert torch.stack(ratios).mean().item() == pytest.approx(1 / (3 * 64), rel=0.05)


@pytest.mark.parametrize("prediction_type", ["epsilon", "v_prediction"])
def test_pfm_of_a_perfect_prediction_is_the_vae_round_trip_distance(vae, encoder, prediction_type) -> None:
    """Eq. (19)-(20): predicting the true noise (or v) gives x0_hat = x0, so PFM is exactly the feature
    distance between the decoded target latent and the target view (0 for a lossless VAE), at any t."""
    scheduler = scheduler_for("scaled_linear", prediction_type)
    generator = torch.Generator().manual_seed(6)
    latents = torch.randn(3, 4, 16, 16, generator=generator)
    noise = torch.randn(3, 4, 16, 16, generator=generator)
    target_images = torch.rand(3, 1, 32, 32, generator=generator)
    timesteps = torch.tensor([1, 500, 999])
    x_t = scheduler.add_noise(latents, noise, timesteps)
    perfect = denoising_target(latents, noise, timesteps, scheduler)
    out = total_loss(perfect, perfect, x_t, timesteps, scheduler, pfm_weight=1.0, target_images=target_images,
                     vae=vae, encoder=encoder, pfm_min_snr=0.0)
    with torch.no_grad():
        decoded = (vae.decode(latents / vae.config.scaling_factor).sample + 1) / 2
        expected = (encoder(F.interpolate(decoded, size=16, mode="bilinear", antialias=True))
                    - encoder(F.interpolate(target_images, size=16, mode="bilinear", antialias=True)))
    assert out.denoising.abs().max() == 0
    torch.testing.assert_close(out.pfm, expected.pow(2).sum(1), atol=2e-5, rtol=2e-3)
    # and the target of PFM is the target view: matching the decoded latent itself gives zero
    matched = total_loss(perfect, perfect, x_t, timesteps, scheduler, pfm_weight=1.0, target_images=decoded,
                         vae=vae, encoder=encoder, pfm_min_snr=0.0)
    torch.testing.assert_close(matched.pfm, torch.zeros(3), atol=2e-5, rtol=0)


def test_the_finetune_config_inherits_every_loss_setting_once_and_passes_each_through() -> None:
    """One declaration per setting: FinetuneConfig is a LossSettings (its loss fields, defaults, help and
    validation are LossSettings'), declares none of them again, and loss_settings() copies each by name."""
    import dataclasses

    from sar_zero123.config import parse_config
    from sar_zero123.stages.finetune import FinetuneConfig

    names = [item.name for item in dataclasses.fields(LossSettings)]
    assert issubclass(FinetuneConfig, LossSettings)
    assert not set(names) & set(FinetuneConfig.__dict__["__annotations__"])  # not declared a second time
    assert {name: getattr(FinetuneConfig(encoder="e"), name) for name in names} == dataclasses.asdict(
        LossSettings()
    )
    changed = {"pfm_weight": 0.5, "pfm_min_snr": 0.2, "pfm_fraction": 0.5, "drop_image_prob": 0.1,
               "drop_both_prob": 0.1, "drop_latent_prob": 0.1, "snr_gamma": 2.0, "azimuth_loss_weight": 0.5,
               "proxy_runner_up_prob": 0.5, "proxy_oracle_prob": 0.25}  # fmt: skip
    assert set(changed) == set(names)
    config = FinetuneConfig(encoder="enc", **changed)
    settings = config.loss_settings()
    assert type(settings) is LossSettings and dataclasses.asdict(settings) == changed
    settings.pfm_weight = 9.0  # a copy: the step's settings never write back into the run's config
    assert config.pfm_weight == 0.5
    with pytest.raises(ValueError, match="pfm_fraction must be in"):  # validated where declared
        FinetuneConfig(encoder="enc", pfm_fraction=0.0)
    parsed = parse_config(FinetuneConfig, ["--encoder", "e", "--pfm_fraction", "0.5", "--snr_gamma", "5"])
    assert parsed.pfm_fraction == 0.5 and parsed.snr_gamma == 5.0


def test_finetune_config_refuses_the_removed_pfm_variants_by_name() -> None:
    """``pfm_features`` and ``pfm_snr_gamma`` were removed: a record holding their defaults still reads, any
    other value is refused naming the field and why it went."""
    from sar_zero123.config import drop_removed_fields
    from sar_zero123.stages.finetune import FinetuneConfig

    old_record = {"pfm_features": "pooled", "pfm_snr_gamma": None, "seed": 1}
    assert drop_removed_fields(FinetuneConfig, old_record, "run") == {"seed": 1}
    with pytest.raises(ValueError, match=r"^run: pfm_features='stages', but pfm_features was removed: "):
        drop_removed_fields(FinetuneConfig, {"pfm_features": "stages"}, "run")
    with pytest.raises(ValueError, match=r"^run: pfm_snr_gamma=5.0, but pfm_snr_gamma was removed: "):
        drop_removed_fields(FinetuneConfig, {"pfm_snr_gamma": 5.0}, "run")


def test_load_pfm_encoder_reads_a_frozen_encoder_at_its_size_and_adds_the_seeded_projection(tmp_path) -> None:
    from sar_zero123.encoder import SAREncoder, SAREncoderConfig

    torch.manual_seed(3)
    config = SAREncoderConfig(image_size=16, depths=(1, 1), hidden_sizes=(4, 8), embedding_size=4)
    SAREncoder(config).save_pretrained(tmp_path / "encoder")
    plain = load_pfm_encoder(tmp_path / "encoder", image_size=16)
    assert isinstance(plain, SAREncoder) and not plain.training
    assert not any(p.requires_grad for p in plain.parameters())
    projected = load_pfm_encoder(tmp_path / "encoder", image_size=16, projection_dim=10, seed=2)
    assert isinstance(projected, ProjectedFeatureEncoder) and projected.weight.shape == (10, 8)
    torch.testing.assert_close(projected.weight, random_feature_projection(8, 10, seed=2))
    with pytest.raises(ValueError, match=r"was trained on 16 px chips but training runs at image_size=32"):
        load_pfm_encoder(tmp_path / "encoder", image_size=32)
