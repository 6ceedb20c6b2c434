"""The learned shortlist of the proxy fit: inputs, saving, and a bank fitted through it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from sar_zero123.domain import to_decibels
from sar_zero123.model.proxy import DEFAULT_PROXY, check_proxy_settings, proxy_bank
from sar_zero123.model.retrieval import (
    RETRIEVAL_TOP,
    ProxyRetrievalNet,
    _bucket_chips,
    load_retrieval,
    retrieval_inputs,
    save_retrieval,
)
from sar_zero123.pretrained import resolve_retrieval
from sar_zero123.sim.proxy import ProxyBank

BANK = {"num_vehicles": 6, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0}


def tiny_net(seed: int = 0) -> ProxyRetrievalNet:
    torch.manual_seed(seed)
    return ProxyRetrievalNet(BANK, channels=(8, 8, 8, 8), embed_dim=16, harmonics=2)


def test_inputs_are_pooled_standardised_and_affine_invariant():
    chips = torch.randn(3, 64, 64) * 5 - 20
    x = retrieval_inputs(chips, 1.5)
    assert x.shape == (3, 32, 32)
    torch.testing.assert_close(x.mean(dim=(1, 2)), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(x.std(dim=(1, 2)), torch.ones(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(retrieval_inputs(chips * 0.25 + 7.0, 1.5), x, atol=1e-4, rtol=0)
    # no blur: the 2 x 2 mean of a chip whose pixels equal their block's index
    blocks = torch.arange(4.0).view(1, 2, 2).repeat_interleave(2, 1).repeat_interleave(2, 2)
    pooled = retrieval_inputs(blocks, 0.0)[0]
    expected = (torch.arange(4.0).view(2, 2) - 1.5) / torch.arange(4.0).std()
    torch.testing.assert_close(pooled, expected)
    assert torch.equal(retrieval_inputs(torch.full((1, 8, 8), 3.0), 0.0), torch.zeros(1, 4, 4))


def test_forward_shapes_and_a_full_turn_is_no_turn():
    net = tiny_net()
    x = retrieval_inputs(torch.randn(2, 64, 64), 1.5)
    logits = net(x, torch.tensor([10.0, 200.0]), torch.tensor([15.0, 30.0]))
    assert logits.shape == (2, BANK["num_vehicles"])
    torch.testing.assert_close(net(x, torch.tensor([370.0, -160.0]), torch.tensor([15.0, 30.0])), logits,
                               atol=1e-4, rtol=0)  # fmt: skip
    ranked = net.rank(np.random.default_rng(0).normal(size=(64, 64)), 10.0, 15.0)
    assert sorted(ranked.tolist()) == list(range(BANK["num_vehicles"]))


def test_save_and_load_round_trip_and_refuse_another_bank(tmp_path):
    net = tiny_net()
    save_retrieval(net, tmp_path / "r", {"training": {"steps": 1}})
    loaded = load_retrieval(tmp_path / "r", BANK)
    x = retrieval_inputs(torch.randn(2, 64, 64), 1.5)
    pose = (torch.tensor([10.0, 20.0]), torch.tensor([17.0, 17.0]))
    torch.testing.assert_close(loaded(x, *pose), net.half().float()(x, *pose), atol=1e-3, rtol=1e-3)
    with pytest.raises(ValueError, match=r"retrieval: .* ranks the bank .*'num_vehicles': 6.*not"):
        load_retrieval(tmp_path / "r", {**BANK, "num_vehicles": 7})
    config = tmp_path / "r" / "config.json"
    config.write_text(config.read_text().replace('"embed_dim": 16', '"embed_dim": 17'))
    with pytest.raises(ValueError, match=r"retrieval: .*config.json' does not match its SHA-256"):
        load_retrieval(tmp_path / "r")
    with pytest.raises(FileNotFoundError, match=r"retrieval: .*model.safetensors not found"):
        (tmp_path / "r" / "model.safetensors").unlink()
        load_retrieval(tmp_path / "r")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "config.json").write_text(json.dumps({"bank": {}}))
    (tmp_path / "bad" / "model.safetensors").write_bytes(b"")
    with pytest.raises(ValueError, match=r"is not a ProxyRetrievalNet config"):
        load_retrieval(tmp_path / "bad")


def test_a_bank_with_a_learned_shortlist_renders_only_the_ranked_vehicles():
    net = tiny_net()
    chip = to_decibels(ProxyBank(**BANK).render(4, 30.0, 17.0, 64))
    exhaustive = ProxyBank(**BANK).scores(chip, 30.0, 17.0)
    bank = ProxyBank(**BANK, shortlist=2, retrieval=net)
    scores = bank.scores(chip, 30.0, 17.0)
    chosen = np.sort(net.rank(chip, 30.0, 17.0)[:2])
    assert np.flatnonzero(np.isfinite(scores)).tolist() == chosen.tolist()
    np.testing.assert_allclose(scores[chosen], exhaustive[chosen])
    excluded = bank.scores(chip, 30.0, 17.0, exclude=[int(chosen[0])])
    assert np.isfinite(excluded).sum() == 2 and not np.isfinite(excluded[chosen[0]])
    with pytest.raises(ValueError, match=r"retrieval: ranks the bank"):
        ProxyBank(**{**BANK, "num_vehicles": 5}, shortlist=2, retrieval=net)


def test_recorded_retrieval_is_checked_and_loaded(tmp_path):
    assert check_proxy_settings(DEFAULT_PROXY)["retrieval"] is None
    old = {k: v for k, v in DEFAULT_PROXY.items() if k not in ("retrieval", "shortlist", "max_shift_px")}
    assert check_proxy_settings(old)["retrieval"] is None  # a record written before the field existed
    with pytest.raises(ValueError, match=r"proxy.retrieval: a learned shortlist needs shortlist > 0"):
        check_proxy_settings({**DEFAULT_PROXY, "retrieval": "x"})
    with pytest.raises(ValueError, match=r"proxy.retrieval: expected null or the name or folder"):
        check_proxy_settings({**DEFAULT_PROXY, "retrieval": 3, "shortlist": 2})
    with pytest.raises(FileNotFoundError, match=r"no bundled retrieval of that name"):
        resolve_retrieval("sar-zero123/nothing")
    with pytest.raises(FileNotFoundError, match=r"no config.json in"):
        resolve_retrieval(tmp_path)
    save_retrieval(tiny_net(), tmp_path / "r")
    bank = proxy_bank(*BANK.values(), 0, 2, str(tmp_path / "r"))
    assert bank.shortlist == 2 and bank.retrieval.bank == BANK


def test_training_chips_carry_the_banks_pooled_correlations_as_targets():
    bank_args = tuple(BANK.values())
    out = _bucket_chips((bank_args, 90.0, 15.0, 4, (0, 1), 64, 0))
    assert out["inputs"].shape == (4, 32, 32) and out["inputs"].dtype == np.float16
    assert out["top_index"].shape == (4, min(RETRIEVAL_TOP, BANK["num_vehicles"]))
    assert np.all(np.abs(out["azimuth"] - 90.0) <= 2.5) and np.all(np.abs(out["depression"] - 15.0) <= 2.5)
    assert np.all(np.diff(out["top_score"], axis=1) <= 0)  # best first
    again = _bucket_chips((bank_args, 90.0, 15.0, 4, (0, 1), 64, 0))
    np.testing.assert_array_equal(out["top_index"], again["top_index"])  # seeded


def test_a_retrieval_folder_without_manifest_warns_and_a_relative_one_is_read_in_the_pipeline(
    tmp_path, caplog, monkeypatch
):
    from sar_zero123.model.pipeline_loading import anchored_proxy
    from sar_zero123.model.retrieval import load_retrieval

    save_retrieval(tiny_net(), tmp_path / "pipe" / "retrieval")
    (tmp_path / "pipe" / "retrieval" / "manifest.json").unlink()
    with caplog.at_level("WARNING"):
        load_retrieval(tmp_path / "pipe" / "retrieval", BANK)
    assert "has no manifest.json: its weights are loaded unchecked" in caplog.text
    proxy = {**DEFAULT_PROXY, "shortlist": 2, "retrieval": "retrieval"}
    monkeypatch.chdir(tmp_path)  # the working directory never anchors a pipeline's own relative path
    anchored = anchored_proxy(proxy, str(tmp_path / "pipe"))
    assert anchored["retrieval"] == str(tmp_path / "pipe" / "retrieval")
    assert {k: v for k, v in anchored.items() if k != "retrieval"} == {
        k: v for k, v in proxy.items() if k != "retrieval"
    }
    for kept in ("sar-zero123/proxy-retrieval", str(tmp_path / "abs"), None):
        assert anchored_proxy({**proxy, "retrieval": kept}, str(tmp_path / "pipe"))["retrieval"] == kept
    assert anchored_proxy(proxy, None) is proxy  # built in code: as given
    assert anchored_proxy(None, str(tmp_path)) is None


def test_fit_settings_are_bounded_before_any_render():
    from sar_zero123.sim.proxy import MAX_BLUR_SIGMA_PX, MAX_RENDERED_BANK

    with pytest.raises(ValueError, match=r"proxy.num_vehicles: a bank without a learned shortlist"):
        check_proxy_settings({**DEFAULT_PROXY, "num_vehicles": MAX_RENDERED_BANK + 1, "retrieval": None})
    big = {
        **DEFAULT_PROXY,
        "num_vehicles": 100_000,
        "shortlist": 64,
        "retrieval": "sar-zero123/proxy-retrieval",
    }
    assert check_proxy_settings(big)["num_vehicles"] == 100_000  # a learned shortlist renders 64 of them
    for blur in (1e6, MAX_BLUR_SIGMA_PX + 0.5, float("inf"), -1.0):
        with pytest.raises(ValueError, match=r"proxy.blur_sigma_px: expected a value in \[0, 16\] pixels"):
            check_proxy_settings({**DEFAULT_PROXY, "blur_sigma_px": blur})
    assert (
        check_proxy_settings({**DEFAULT_PROXY, "blur_sigma_px": MAX_BLUR_SIGMA_PX})["blur_sigma_px"] == 16.0
    )
