"""Reference attention: the input view's own features reachable from every place of the generated view."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from sar_zero123.data import load_index
from sar_zero123.data.corpus_proxies import (
    ORACLE_INDEX,
    corpus_proxies_have_oracle,
    load_corpus_proxies,
    write_corpus_proxies,
)
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import PoseProjection
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.reference_attention import (
    attending_to_reference,
    enable_reference_attention,
    reference_features,
    reference_layers,
    reference_weights,
    uses_reference,
)
from sar_zero123.model.spatial_pose import widen_for_proxy
from sar_zero123.sim.corpus import corpus_vehicle_seed, write_prior_corpus
from sar_zero123.sim.procedural import make_procedural_target
from sar_zero123.sim.proxy import ProxyBank
from sar_zero123.training.losses import LossSettings
from sar_zero123.training.step import chosen_proxy_latents, compute_losses

KWARGS = {"num_inference_steps": 3, "guidance_scale": 3.0, "output_type": "np"}


def _open_gates(pipe: SARZero123Pipeline, value: float = 0.7) -> None:
    with torch.no_grad():
        pipe.pose_projection.reference_gates.fill_(value)


def _unet_inputs(pipe: SARZero123Pipeline, batch: int = 2, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    unet = pipe.unet
    x = torch.randn(batch, unet.config.in_channels, 8, 8, generator=generator)
    tokens = torch.randn(batch, 1, unet.config.cross_attention_dim, generator=generator)
    return x, torch.tensor([10, 700][:batch]), tokens


def test_a_model_given_reference_attention_computes_what_it_did_until_trained() -> None:
    pipe = build_sar_zero123("tiny", seed=0)
    image = torch.rand(2, 1, pipe.default_image_size, pipe.default_image_size,
                       generator=torch.Generator().manual_seed(3))  # fmt: skip
    before = pipe(image, [40.0, -120.0], generator=torch.Generator().manual_seed(0), **KWARGS).images
    enable_reference_attention(pipe.unet, pipe.pose_projection)
    layers = reference_layers(pipe.unet)
    assert uses_reference(pipe.pose_projection)
    assert pipe.pose_projection.config.reference_layers == len(layers)
    assert pipe.pose_projection.reference_gates.shape == (len(layers),) and len(layers) >= 2
    after = pipe(image, [40.0, -120.0], generator=torch.Generator().manual_seed(0), **KWARGS).images
    np.testing.assert_array_equal(after, before)  # every gate zero: the same bytes
    _open_gates(pipe)
    opened = pipe(image, [40.0, -120.0], generator=torch.Generator().manual_seed(0), **KWARGS).images
    assert np.abs(opened - before).max() > 1e-3  # the reference reaches the output once a gate opens
    with pytest.raises(ValueError, match="already has reference attention"):
        enable_reference_attention(pipe.unet, pipe.pose_projection)


def test_each_self_attention_adds_its_gated_attention_to_the_reference() -> None:
    """The processor against a direct computation of ``tanh(g) * W_o softmax(Q K_ref^T / sqrt(d)) V_ref``."""
    pipe = build_sar_zero123("tiny", seed=0)
    enable_reference_attention(pipe.unet, pipe.pose_projection)
    _open_gates(pipe, 0.4)
    x, t, tokens = _unet_inputs(pipe)
    features = reference_features(pipe.unet, x.flip(0), timestep=t, encoder_hidden_states=tokens)
    layer = reference_layers(pipe.unet)[0]
    seen = {}
    def record(module, args, kwargs, output):
        seen["input"], seen["output"] = args[0] if args else kwargs["hidden_states"], output

    handle = layer.register_forward_hook(record, with_kwargs=True)
    rows = torch.tensor([1, 0])
    keep = torch.tensor([True, False])
    weights = reference_weights(pipe.pose_projection, keep)
    with torch.no_grad(), attending_to_reference(pipe.unet, features, rows, weights):
        pipe.unet(x, t, encoder_hidden_states=tokens)
    handle.remove()
    hidden, reference = seen["input"], features[0][rows]
    heads, width = layer.heads, hidden.shape[-1]
    with torch.no_grad():
        q, k, v = (f(h).double() for f, h in ((layer.to_q, hidden), (layer.to_k, reference),
                                             (layer.to_v, reference)))  # fmt: skip
        k_own, v_own = layer.to_k(hidden).double(), layer.to_v(hidden).double()
    out_weight = layer.to_out[0].weight.detach().double()
    expected = torch.zeros(2, hidden.shape[1], width, dtype=torch.float64)
    own = torch.zeros_like(expected)
    dim = q.shape[-1] // heads
    for n in range(2):
        for head in range(heads):
            cols = slice(head * dim, (head + 1) * dim)
            scale = 1.0 / math.sqrt(dim)
            mixed = torch.softmax(q[n, :, cols] @ k[n, :, cols].T * scale, -1) @ v[n, :, cols]
            expected[n] += mixed @ out_weight[:, cols].T
            mine = torch.softmax(q[n, :, cols] @ k_own[n, :, cols].T * scale, -1) @ v_own[n, :, cols]
            own[n] += mine @ out_weight[:, cols].T
    own = own + layer.to_out[0].bias.detach().double()
    gate = math.tanh(0.4)
    torch.testing.assert_close(seen["output"][0].double(), own[0] + gate * expected[0], rtol=0, atol=1e-5)
    # the row not kept: its own attention alone
    torch.testing.assert_close(seen["output"][1].double(), own[1], rtol=0, atol=1e-5)


def test_the_null_branch_runs_without_the_reference() -> None:
    pipe = build_sar_zero123("tiny", seed=0)
    enable_reference_attention(pipe.unet, pipe.pose_projection)
    _open_gates(pipe)
    x, t, tokens = _unet_inputs(pipe)
    with torch.no_grad():
        plain = pipe.unet(x, t, encoder_hidden_states=tokens).sample
        features = reference_features(pipe.unet, x, timestep=t, encoder_hidden_states=tokens)
        weights = reference_weights(pipe.pose_projection, torch.tensor([False, True]))
        with attending_to_reference(pipe.unet, features, torch.tensor([0, 1]), weights):
            mixed = pipe.unet(x, t, encoder_hidden_states=tokens).sample
        after = pipe.unet(x, t, encoder_hidden_states=tokens).sample
    torch.testing.assert_close(mixed[0], plain[0], rtol=0, atol=0)
    assert float((mixed[1] - plain[1]).abs().max()) > 1e-4
    torch.testing.assert_close(after, plain, rtol=0, atol=0)  # outside the block the UNet is itself again
    with pytest.raises(ValueError, match="layers' features"):
        with attending_to_reference(pipe.unet, features[:1], torch.tensor([0, 1]), weights):
            pass


def test_a_reference_pipeline_saves_and_loads_its_gates(tmp_path: Path) -> None:
    pipe = build_sar_zero123("tiny", seed=0)
    enable_reference_attention(pipe.unet, pipe.pose_projection)
    _open_gates(pipe, 0.3)
    image = torch.rand(1, 1, pipe.default_image_size, pipe.default_image_size)
    views = pipe(image, 90.0, generator=torch.Generator().manual_seed(0), **KWARGS).images
    pipe.save_pretrained(tmp_path / "pipe")
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "pipe")
    assert uses_reference(loaded.pose_projection)
    gates = loaded.pose_projection.reference_gates.detach()
    torch.testing.assert_close(gates, torch.full((len(reference_layers(loaded.unet)),), 0.3))
    again = loaded(image, 90.0, generator=torch.Generator().manual_seed(0), **KWARGS).images
    np.testing.assert_allclose(again, views, rtol=0, atol=1e-6)
    wrong = PoseProjection(**{**dict(pipe.pose_projection.config), "reference_layers": 1})
    with pytest.raises(ValueError, match="reference_layers=1 gates, but the UNet has"):
        SARZero123Pipeline(**{**pipe.components, "pose_projection": wrong})
    with pytest.raises(ValueError, match="reference_layers"):
        PoseProjection(reference_layers=-1)


def test_a_training_step_trains_the_gates_and_drops_the_reference_with_the_latent() -> None:
    pipe = build_sar_zero123("tiny", seed=0)
    enable_reference_attention(pipe.unet, pipe.pose_projection)
    size = pipe.default_image_size
    generator = torch.Generator().manual_seed(0)
    batch = {"input": torch.rand(3, 1, size, size, generator=generator),
             "target": torch.rand(3, 1, size, size, generator=generator),
             "d_az_deg": torch.tensor([30.0, 90.0, -150.0]), "d_el_deg": torch.zeros(3)}  # fmt: skip
    from sar_zero123.training.step import ImageEmbedder

    losses = compute_losses(
        batch, unet=pipe.unet, pose_projection=pipe.pose_projection, vae=pipe.vae,
        image_encoder=ImageEmbedder(pipe.image_encoder), encoder=None, noise_scheduler=pipe.scheduler,
        generator=torch.Generator().manual_seed(0), apply_dropout=False,
    )  # fmt: skip
    losses.loss.mean().backward()
    grad = pipe.pose_projection.reference_gates.grad
    assert grad is not None and grad.shape == (len(reference_layers(pipe.unet)),)
    assert float(grad.abs().min()) > 0
    pipe.pose_projection.reference_gates.grad = None
    only_latent_dropped = LossSettings(
        pfm_weight=0.0, drop_image_prob=0.0, drop_both_prob=0.0, drop_latent_prob=1.0
    )
    dropped = compute_losses(
        batch, unet=pipe.unet, pose_projection=pipe.pose_projection, vae=pipe.vae,
        image_encoder=ImageEmbedder(pipe.image_encoder), encoder=None, noise_scheduler=pipe.scheduler,
        generator=torch.Generator().manual_seed(0), loss_settings=only_latent_dropped,
    )  # fmt: skip
    dropped.loss.mean().backward()  # every condition latent dropped: no row sees the reference
    assert float(pipe.pose_projection.reference_gates.grad.abs().max()) == 0.0


def test_oracle_proxies_are_the_vehicle_itself_as_the_bank_renders(tmp_path: Path) -> None:
    corpus = tmp_path / "corpus"
    write_prior_corpus(corpus, num_vehicles=3, views_per_vehicle=2, num_validation_vehicles=1, size=24,
                       progress=False)  # fmt: skip
    bank = {"num_vehicles": 3, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0}
    write_corpus_proxies(corpus, tmp_path / "proxies", **bank, candidates=2, oracle=True, progress=False)
    assert corpus_proxies_have_oracle(corpus, tmp_path / "proxies") and not corpus_proxies_have_oracle(corpus)
    records = load_index(corpus)
    chips = load_corpus_proxies(corpus, [r.path for r in records], tmp_path / "proxies")
    assert chips.shape == (6, 3, 24, 24)
    renderer = ProxyBank(**bank)
    for n, record in enumerate(records):
        vehicle = make_procedural_target(corpus_vehicle_seed(record.serial))
        expected = renderer.render_target(vehicle, record.azimuth_deg, record.depression_deg, 24)
        np.testing.assert_allclose(chips[n, 2].numpy(), expected, rtol=0, atol=1e-3)
    from safetensors.torch import load_file

    assert (load_file(tmp_path / "proxies" / "proxies.safetensors")["bank_index"][:, 2] == ORACLE_INDEX).all()
    assert corpus_vehicle_seed("proc00042") == 42
    with pytest.raises(ValueError, match="procNNNNN"):
        corpus_vehicle_seed("T72_132")


def test_a_training_step_gives_the_oracle_at_its_rate_and_the_draws_are_unchanged_without_it() -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    widen_for_proxy(pipe.unet, pipe.pose_projection)
    values = torch.arange(3.0)[None, :, None, None, None]
    batch = {"proxy_latents": values.expand(2000, 3, 8, 2, 2)}  # candidates: best 0, runner-up 1, oracle 2
    chosen = chosen_proxy_latents(batch, pipe.pose_projection, 0.25, torch.Generator().manual_seed(0), 0.5)
    picks = chosen[:, 0, 0, 0]
    shares = [float((picks == k).float().mean()) for k in range(3)]
    for share, expected in zip(shares, (0.25, 0.25, 0.5), strict=True):
        assert abs(share - expected) < 0.045  # binomial(2000, p): 4.6 standard deviations at most
    plain = chosen_proxy_latents(batch, pipe.pose_projection, 0.25, torch.Generator().manual_seed(0))
    old_rule = torch.Generator().manual_seed(0)
    u = torch.rand(2000, generator=old_rule)
    pick = torch.randint(1, 3, (2000,), generator=old_rule)
    expected = torch.where(u < 0.25, pick, torch.zeros_like(pick)).float()
    torch.testing.assert_close(plain[:, 0, 0, 0], expected)  # oracle_prob 0: the draws as before
