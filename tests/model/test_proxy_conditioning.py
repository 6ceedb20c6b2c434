"""The proxy-conditioned UNet (spatial_pose="proxy"): the corpus's proxies, the widened warm start, the
training step's proxy choice, and the pipeline that fits and renders the proxy itself (issue 61)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from dummies import proxy_pipeline

from sar_zero123.data import load_index
from sar_zero123.data.corpus_proxies import (
    PROXIES_FILE,
    PROXIES_RECORD,
    load_corpus_proxies,
    write_corpus_proxies,
)
from sar_zero123.domain import to_decibels
from sar_zero123.model import proxy as proxy_module
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import embed_pose
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.spatial_pose import (
    condition_channels,
    takes_proxy,
    unet_condition_latents,
    widen_for_proxy,
)
from sar_zero123.sim.corpus import write_prior_corpus
from sar_zero123.sim.proxy import ProxyBank
from sar_zero123.training.step import chosen_proxy_latents

BANK = {"num_vehicles": 3, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0}
PROXY = {**BANK, "max_shift_px": 0, "min_db": -60.0, "max_db": 0.0, "min_fit_score": -1.0}  # noise chips


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("proxy") / "corpus"
    write_prior_corpus(out, num_vehicles=4, views_per_vehicle=3, num_validation_vehicles=1, size=32,
                       progress=False)  # fmt: skip
    write_corpus_proxies(out, **BANK, candidates=2, progress=False)
    return out


def test_corpus_proxies_are_the_best_bank_fits_rendered_at_every_chip_pose(corpus: Path) -> None:
    records = load_index(corpus)
    record = json.loads((corpus / PROXIES_RECORD).read_text())
    assert record["candidates"] == 2 and record["bank"] == BANK and len(record["paths"]) == len(records) == 12
    chips = load_corpus_proxies(corpus, [r.path for r in records])
    assert chips.shape == (12, 2, 32, 32) and chips.dtype == torch.float32
    bank = ProxyBank(**BANK)
    for first in (0, 3):  # each vehicle's fit is made on its first chip, at its pose
        fit = records[first]
        scores = bank.scores(to_decibels(np.load(fit.path).astype(np.float64)), fit.azimuth_deg,
                             fit.depression_deg)  # fmt: skip
        best = np.argsort(-scores, kind="stable")[:2]
        for n in range(first, first + 3):  # the same two bank vehicles at each of the vehicle's poses
            for k in range(2):
                expected = bank.render(int(best[k]), records[n].azimuth_deg, records[n].depression_deg, 32)
                # stored as float16 (one unit in the last place <= 5e-4 on [0, 1]); a render's BLAS threads
                # may move its last float32 bits, hence a rounding either side
                np.testing.assert_allclose(chips[n, k].numpy(), expected, rtol=0, atol=1e-3)
    # any subset, in the order asked, and relative paths too
    subset = load_corpus_proxies(corpus, [records[5].path, "chips/proc00000/proc00000_001.npy"])
    torch.testing.assert_close(subset, chips[[5, 1]])
    with pytest.raises(ValueError, match="no proxy"):
        load_corpus_proxies(corpus, ["chips/elsewhere.npy"])
    with pytest.raises(FileNotFoundError, match="write_corpus_proxies"):
        load_corpus_proxies(corpus / "chips", [])
    with pytest.raises(ValueError, match="candidates"):
        write_corpus_proxies(corpus, **BANK, candidates=4)
    assert not list(corpus.glob(".*"))  # no temporary file left behind
    assert (corpus / PROXIES_FILE).is_file()


def test_corpus_proxies_of_chips_of_several_sizes_fit_the_crop_a_fine_tune_reads(tmp_path: Path) -> None:
    """Real folders mix chip sizes (MSTAR: 128 to 193 px): with ``size`` each vehicle is fitted to the
    centre crop a fine-tune reads (``load_chip``) and its proxies rendered at that size; without it they
    are refused."""
    import dataclasses

    from chip_folders import write_chip_folder

    from sar_zero123.data.datasets import load_chip
    from sar_zero123.data.index import write_index

    root = write_chip_folder(tmp_path / "mixed", classes=("A",), azimuths_deg=(0, 90), size=24)
    other = write_chip_folder(tmp_path / "other", classes=("B",), azimuths_deg=(0, 90), size=30)
    records = list(load_index(root))
    for record in load_index(other):
        path = root / Path(record.path).name
        path.write_bytes(Path(record.path).read_bytes())
        records.append(dataclasses.replace(record, path=path))
    write_index(records, root)
    refused = r"expected a square chip of the index's first size 24, got \(30, 30\)"
    with pytest.raises(ValueError, match=refused):
        write_corpus_proxies(root, tmp_path / "refused", **BANK, candidates=1, progress=False)
    with pytest.raises(ValueError, match="size: expected an integer >= 1 or None, got 0"):
        write_corpus_proxies(root, tmp_path / "refused", **BANK, size=0, progress=False)
    write_corpus_proxies(root, tmp_path / "proxies", **BANK, candidates=1, size=20, progress=False)
    chips = load_corpus_proxies(root, [r.path for r in records], tmp_path / "proxies")
    assert chips.shape == (8, 1, 20, 20)
    bank = ProxyBank(**BANK)
    for first in (0, 4):  # each vehicle (4 chips) fitted to its first chip's 20 px centre crop
        fit = records[first]
        crop = load_chip(fit.path, 20)
        scores = bank.scores(to_decibels(crop.astype(np.float64)), fit.azimuth_deg, fit.depression_deg)
        best = int(np.argmax(scores))
        for n in range(first, first + 4):
            expected = bank.render(best, records[n].azimuth_deg, records[n].depression_deg, 20)
            np.testing.assert_allclose(chips[n, 0].numpy(), expected, rtol=0, atol=1e-3)


def test_a_widened_model_computes_what_it_did_until_trained() -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    unet, projection = pipe.unet, pipe.pose_projection
    x = torch.randn(2, 12, 8, 8)  # tiny latents: 4 channels each for noisy, input, turned
    t = torch.tensor([10, 500])
    tokens = torch.randn(2, 1, unet.config.cross_attention_dim)
    before = unet(x, t, encoder_hidden_states=tokens).sample
    widen_for_proxy(unet, projection)
    assert takes_proxy(projection) and unet.config.in_channels == 4 + condition_channels("proxy", 4) == 20
    proxies = torch.randn(2, 8, 8, 8)
    after = unet(torch.cat([x, proxies], 1), t, encoder_hidden_states=tokens).sample
    torch.testing.assert_close(after, before, rtol=0, atol=0)
    with pytest.raises(ValueError, match="rotated_input"):
        widen_for_proxy(unet, projection)  # only a rotated_input model widens


def test_the_condition_input_stacks_the_proxy_pair_after_the_input_and_its_turn() -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    widen_for_proxy(pipe.unet, pipe.pose_projection)
    latents, proxies = torch.randn(2, 4, 8, 8), torch.randn(2, 8, 8, 8)
    pose = embed_pose([0.0, 90.0], [0.0, 0.0])
    stacked = unet_condition_latents(latents, pose, pipe.pose_projection, proxies)
    assert stacked.shape == (2, 16, 8, 8)
    torch.testing.assert_close(stacked[:, :4], latents)
    torch.testing.assert_close(stacked[0, 4:8], latents[0])  # a turn of 0 is the identity
    torch.testing.assert_close(stacked[:, 8:], proxies)
    with pytest.raises(ValueError, match="proxy_latents: a UNet with spatial_pose='proxy'.*missing"):
        unet_condition_latents(latents, pose, pipe.pose_projection)
    with pytest.raises(ValueError, match=r"proxy_latents: expected shape \(2, 8, 8, 8\)"):
        unet_condition_latents(latents, pose, pipe.pose_projection, proxies[:, :4])
    plain = build_sar_zero123("tiny", seed=0)
    with pytest.raises(ValueError, match="spatial_pose=None, proxy_latents given"):
        unet_condition_latents(latents, pose, plain.pose_projection, proxies)


def test_a_training_step_takes_the_best_proxy_or_a_runner_up_at_its_rate() -> None:
    pipe = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    widen_for_proxy(pipe.unet, pipe.pose_projection)
    proxies = torch.stack([torch.zeros(400, 8, 2, 2), torch.ones(400, 8, 2, 2)], dim=1)  # (B, K=2, 2C, h, w)
    batch = {"proxy_latents": proxies}
    best = chosen_proxy_latents(batch, pipe.pose_projection, 0.0, torch.Generator().manual_seed(0))
    assert best.shape == (400, 8, 2, 2) and float(best.abs().max()) == 0.0
    always = chosen_proxy_latents(batch, pipe.pose_projection, 1.0, torch.Generator().manual_seed(0))
    assert float(always.min()) == 1.0
    some = chosen_proxy_latents(batch, pipe.pose_projection, 0.25, torch.Generator().manual_seed(0))
    share = float(some[:, 0, 0, 0].mean())
    assert 0.19 < share < 0.31  # binomial(400, 0.25): 4.5 standard deviations either side
    with pytest.raises(ValueError, match="no `proxy_latents`"):
        chosen_proxy_latents({}, pipe.pose_projection, 0.25)
    assert chosen_proxy_latents({}, build_sar_zero123("tiny").pose_projection, 0.25) is None


def _proxy_pipeline() -> SARZero123Pipeline:
    return proxy_pipeline(PROXY)


def test_a_proxy_pipeline_fits_its_proxy_and_needs_the_input_pose(tmp_path: Path, monkeypatch) -> None:
    pipe = _proxy_pipeline()
    size = pipe.default_image_size
    image = torch.rand(1, 1, size, size)
    kwargs = {"num_inference_steps": 2, "guidance_scale": 1.0, "output_type": "np"}
    with pytest.raises(ValueError, match="input_azimuth_deg.*spatial_pose='proxy' fits a simulator vehicle"):
        pipe(image, 90.0, 0.0, input_depression_deg=17.0, **kwargs)
    out = pipe(image, 90.0, 0.0, input_depression_deg=17.0, input_azimuth_deg=40.0,
               generator=torch.Generator().manual_seed(0), **kwargs)  # fmt: skip
    fitted = out.images
    # the proxy pipeline is the same as handing it the proxy it fitted
    bank = ProxyBank(**BANK)
    from sar_zero123.data import DecibelScaling

    scaling = DecibelScaling(min_db=-60.0, max_db=0.0)
    chip = image[0, 0].double().numpy()
    index = int(np.argmax(bank.scores(chip, 40.0, 17.0)))
    # and it says how well that vehicle fits: the best bank score for the chip at its pose
    assert out.proxy_fit_scores.shape == (1,)
    np.testing.assert_allclose(out.proxy_fit_scores, [bank.scores(chip, 40.0, 17.0).max()], atol=1e-6)
    views = torch.stack([scaling.normalize(torch.from_numpy(bank.render(index, az, 17.0, size))).float()
                         for az in (40.0, 130.0)])[None]  # fmt: skip
    given = pipe(image, 90.0, 0.0, input_depression_deg=17.0, proxy_views=views,
                 generator=torch.Generator().manual_seed(0), **kwargs).images  # fmt: skip
    np.testing.assert_allclose(fitted, given, atol=1e-5)
    no_fit = pipe(image, 90.0, 0.0, input_depression_deg=17.0, proxy_views=views, **kwargs)
    assert no_fit.proxy_fit_scores is None  # given views: no fit ran
    other = pipe(image, 90.0, 0.0, input_depression_deg=17.0, proxy_views=views.flip(1),
                 generator=torch.Generator().manual_seed(0), **kwargs).images  # fmt: skip
    assert np.abs(other - given).max() > 1e-3  # the proxy pair reaches the output
    for bad, why in ((views[:, :1], "got shape"), (views * 50.0, "outside"), (views - 20.0, "outside"),
                     (views.to(torch.complex64), "complex64"), ("proxy.npy", "got a str")):  # fmt: skip
        with pytest.raises(ValueError, match=rf"proxy_views` must be real normalised dB views.*{why}"):
            pipe(image, 90.0, 0.0, input_depression_deg=17.0, proxy_views=bad, **kwargs)

    # given views are used as they are, the start draft too: no fit runs, the azimuth given or not
    def no_fit(*args, **kwargs):
        raise AssertionError("a fit ran although proxy_views were given")

    with monkeypatch.context() as patched:
        patched.setattr(proxy_module, "draft_target_views", no_fit)
        drafted = pipe(image, 90.0, 0.0, input_depression_deg=17.0, input_azimuth_deg=40.0, proxy_views=views,
                       strength=0.5, start_from="proxy", generator=torch.Generator().manual_seed(0),
                       **kwargs).images  # fmt: skip
    drafted_from_views = pipe(image, 90.0, 0.0, input_depression_deg=17.0, proxy_views=views, strength=0.5,
                              start_image=views[:, 1:2], generator=torch.Generator().manual_seed(0),
                              **kwargs).images  # fmt: skip
    np.testing.assert_array_equal(drafted, drafted_from_views)
    plain = build_sar_zero123("tiny", seed=0)
    with pytest.raises(ValueError, match="takes no proxy"):
        plain(image, 90.0, proxy_views=views, **kwargs)
    # saved and loaded, it stays a proxy pipeline with its bank
    pipe.save_pretrained(tmp_path / "pipe")
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "pipe")
    assert takes_proxy(loaded.pose_projection) and loaded.unet.config.in_channels == 20
    assert loaded.config.proxy == {**PROXY, "shortlist": 0, "retrieval": None}


def test_heading_guidance_contrasts_with_the_proxy_at_the_flipped_heading(monkeypatch) -> None:
    pipe = _proxy_pipeline()
    seen = []
    original = proxy_module.proxy_drafts

    def spy(images, d_az, d_el, *args, **kwargs):
        seen.append([torch.as_tensor(a, dtype=torch.float64).reshape(-1).tolist() for a in (d_az, d_el)])
        return original(images, d_az, d_el, *args, **kwargs)

    monkeypatch.setattr(proxy_module, "proxy_drafts", spy)
    size = pipe.default_image_size
    pipe(torch.rand(2, 1, size, size), [30.0, -90.0], 0.0, input_depression_deg=17.0, input_azimuth_deg=10.0,
         num_inference_steps=1, guidance_scale=2.0, heading_guidance_scale=1.0, output_type="np")  # fmt: skip
    # one call, each chip's renders side by side: its input pose, the request, the flipped heading
    assert seen == [[[0.0, 30.0, 210.0, 0.0, -90.0, 90.0], [0.0] * 6]]


def test_each_chip_is_fitted_once_however_large_the_batch(monkeypatch) -> None:
    pipe = _proxy_pipeline()
    fits = []
    original = ProxyBank.retrieve

    def counting(self, chip, *args, **kwargs):
        fits.append(1)
        return original(self, chip, *args, **kwargs)

    monkeypatch.setattr(ProxyBank, "retrieve", counting)
    size = pipe.default_image_size
    chips = torch.rand(65, 1, size, size, generator=torch.Generator().manual_seed(7))  # > the 64 fits kept
    pipe(chips, 120.0, 0.0, input_depression_deg=17.0, input_azimuth_deg=10.0, num_inference_steps=1,
         guidance_scale=2.0, heading_guidance_scale=1.0, output_type="np")  # fmt: skip
    assert len(fits) == 65  # not once per render (3 x 65)


def test_a_proxy_fine_tune_widens_its_start_and_exports_a_proxy_pipeline(corpus: Path, tmp_path: Path):
    from sar_zero123.stages.finetune import FinetuneConfig, run_finetune

    start = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    start.save_pretrained(tmp_path / "start")
    config = FinetuneConfig(
        output_dir=str(tmp_path / "run"), pretrained=str(tmp_path / "start"), spatial_pose="proxy",
        data=str(corpus), protocol="ood-PROCVAL", pfm_weight=0.0, train_batch_size=2, max_train_steps=2,
        validation_steps=0, checkpointing_steps=2, num_validation_images=2, use_ema=False, report_to="none",
        same_depression=False,
    )  # fmt: skip
    run_finetune(config)
    pipe = SARZero123Pipeline.from_pretrained(tmp_path / "run" / "pipeline")
    assert takes_proxy(pipe.pose_projection) and pipe.unet.config.in_channels == 20
    assert pipe.config.proxy["num_vehicles"] == 1000 and pipe.config.proxy["min_db"] == -60.0
    # the proxy weights were trained from zero; the start's own weights moved too
    weight = pipe.unet.conv_in.weight.detach()
    assert float(weight[:, 12:].abs().max()) > 0.0
    with pytest.raises(ValueError, match="validation_steps: spatial_pose='proxy' needs 0"):
        FinetuneConfig(pretrained=str(tmp_path / "start"), spatial_pose="proxy", data=str(corpus),
                       pfm_weight=0.0)  # fmt: skip
    with pytest.raises(ValueError, match="spatial_pose: only for a model built from scratch"):
        FinetuneConfig(pretrained=str(tmp_path / "start"), spatial_pose="rotated_input", pfm_weight=0.0)


def test_a_chip_no_vehicle_fits_is_refused_below_the_floor() -> None:
    """Clutter alone (here: noise) scores far below a vehicle; under the default floor it is refused by name,
    and a simulated vehicle at its pose passes."""
    from sar_zero123.model.proxy import MIN_FIT_SCORE, draft_target_views, fit_scores

    proxy = {**PROXY, "min_fit_score": MIN_FIT_SCORE}
    size = 32
    noise = torch.rand(1, 1, size, size, generator=torch.Generator().manual_seed(0))
    pose = (torch.tensor([40.0]), torch.tensor([17.0]))
    request = (torch.tensor([90.0]), torch.tensor([0.0]))
    assert fit_scores(noise, *pose, proxy)[0] < MIN_FIT_SCORE
    with pytest.raises(
        ValueError,
        match=rf"image: input 0: no simulator vehicle fits it \(fit score .*below the floor {MIN_FIT_SCORE}",
    ):
        draft_target_views(noise, *pose, *request, proxy)
    bank = ProxyBank(**BANK)
    from sar_zero123.data import DecibelScaling

    vehicle = DecibelScaling(min_db=-60.0, max_db=0.0).normalize(bank.render(1, 40.0, 17.0, size))
    chip = torch.from_numpy(np.asarray(vehicle, dtype=np.float32))[None, None]
    assert fit_scores(chip, *pose, proxy)[0] > 0.9  # a bank vehicle fits itself
    drafts, _ = draft_target_views(chip, *pose, *request, proxy)
    assert drafts.shape == (1, 1, size, size)
    for bad in (1.5, float("nan"), True, "0.3"):
        with pytest.raises(ValueError, match=r"proxy.min_fit_score: expected a correlation in \[-1, 1\]"):
            draft_target_views(chip, *pose, *request, {**proxy, "min_fit_score": bad})


def test_a_geometry_fine_tune_caches_the_proxies_masks_and_exports_its_form(
    corpus: Path, tmp_path: Path, monkeypatch
) -> None:
    from sar_zero123.model.spatial_pose import proxy_form
    from sar_zero123.stages.finetune import FinetuneConfig, run_finetune
    from sar_zero123.training.latent_cache import ChipLatentCache

    seen = []
    original = ChipLatentCache.encode.__func__

    def spy(cls, images, vae, *args, proxy_images=None, **kwargs):
        seen.append(proxy_images)
        return original(cls, images, vae, *args, proxy_images=proxy_images, **kwargs)

    monkeypatch.setattr(ChipLatentCache, "encode", classmethod(spy))
    start = build_sar_zero123("tiny", seed=0, spatial_pose="rotated_input")
    start.save_pretrained(tmp_path / "start")
    config = FinetuneConfig(
        output_dir=str(tmp_path / "run"), pretrained=str(tmp_path / "start"), spatial_pose="proxy",
        proxy_geometry=True, data=str(corpus), protocol="ood-PROCVAL", pfm_weight=0.0, train_batch_size=2,
        max_train_steps=1, validation_steps=0, checkpointing_steps=1, num_validation_images=2, use_ema=False,
        report_to="none", same_depression=False,
    )  # fmt: skip
    run_finetune(config)
    assert set(torch.unique(seen[0]).tolist()) <= {0.0, 0.5, 1.0}  # every candidate as its masks
    pipe = SARZero123Pipeline.from_pretrained(tmp_path / "run" / "pipeline")
    assert proxy_form(pipe.pose_projection) == "geometry"
    with pytest.raises(ValueError, match="proxy_geometry: only a spatial_pose='proxy' model"):
        FinetuneConfig(proxy_geometry=True, pfm_weight=0.0, spatial_pose="rotated_input")
    from sar_zero123.stages.prior import PriorConfig

    with pytest.raises(ValueError, match="proxy_geometry: only a spatial_pose='proxy' prior"):
        PriorConfig(proxy_geometry=True)
