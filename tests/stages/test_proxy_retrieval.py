"""The proxy-retrieval stage: a tiny run end to end, its folder, its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sar_zero123.model.retrieval import load_retrieval
from sar_zero123.sim.proxy import ProxyBank
from sar_zero123.stages.proxy_retrieval import ProxyRetrievalConfig, run_proxy_retrieval

TINY = {"num_vehicles": 4, "depressions_deg": [17.0], "chips_per_bucket": 2, "steps": 3, "batch_size": 8,
        "workers": 1}  # fmt: skip


def test_a_tiny_run_writes_a_sealed_network_for_its_bank_and_its_recall(tmp_path):
    out = run_proxy_retrieval(ProxyRetrievalConfig(output_dir=str(tmp_path / "run"), **TINY))
    assert out == tmp_path / "run" / "retrieval"
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "manifest.json", "model.safetensors"]
    net = load_retrieval(
        out, {"num_vehicles": 4, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0}
    )
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["chips"] == 72 * 2 and set(metrics["held_out_recall"]) == {"1", "8", "32", "64", "128"}
    assert metrics["held_out_recall"]["8"] == 1.0  # 4 vehicles: every one within the first 8
    with np.load(tmp_path / "run" / "data.npz") as data:
        assert data["inputs"].shape == (144, 32, 32) and data["top_index"].shape == (144, 4)
    chip = ProxyBank(4).render(2, 40.0, 17.0, 64)
    bank = ProxyBank(4, shortlist=2, retrieval=net)
    assert np.isfinite(bank.scores(np.log10(chip + 1e-3), 40.0, 17.0)).sum() == 2
    # the same settings again: the finished run is returned as it is
    again = run_proxy_retrieval(ProxyRetrievalConfig(output_dir=str(tmp_path / "run"), resume=True, **TINY))
    assert again == out
    with pytest.raises(ValueError, match=r"steps"):
        run_proxy_retrieval(ProxyRetrievalConfig(output_dir=str(tmp_path / "run"), **{**TINY, "steps": 4}))


@pytest.mark.parametrize(
    ("changes", "match"),
    [({"depressions_deg": [95.0]}, r"depressions_deg: expected degrees in \(0, 90\), got \[95.0\]"),
     ({"steps": 0}, r"steps: expected an integer >= 1, got 0"),
     ({"num_vehicles": 40000}, r"num_vehicles: expected at most 32767, got 40000"),
     ({"temperature": 0.0}, r"temperature: expected a value > 0, got 0.0"),
     # 1 depression x 72 buckets x 2 chips = 144, 7 held out: known before any chip is rendered
     ({"batch_size": 138}, r"batch_size: expected at most the 137 training chips of 1 depression\(s\) x 2 ")],
)  # fmt: skip
def test_bad_settings_are_refused_by_name(changes, match):
    with pytest.raises(ValueError, match=match):
        ProxyRetrievalConfig(**{**TINY, **changes})


def test_a_missing_start_network_is_refused_before_any_work(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"retrieval '.*nothing': no config.json in"):
        ProxyRetrievalConfig(output_dir=str(tmp_path / "run"), init=str(tmp_path / "nothing"), **TINY)
    assert not (tmp_path / "run").exists()


def _saved_network(folder, num_vehicles=4, seal=True, **sizes):
    from sar_zero123.model.retrieval import ProxyRetrievalNet, save_retrieval

    bank = {"num_vehicles": num_vehicles, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0}
    save_retrieval(ProxyRetrievalNet(bank, **sizes), folder)
    if not seal:
        (folder / "manifest.json").unlink()
    return folder


def _truncate(folder):
    weights = folder / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])
    return folder


@pytest.mark.parametrize(
    ("make", "error", "match"),
    [(lambda f: _saved_network(f, num_vehicles=5), ValueError,
      r"^init: retrieval: .* ranks the bank \{'num_vehicles': 5, .*\}, not \{'num_vehicles': 4, "),
     (lambda f: _truncate(_saved_network(f)), ValueError,
      r"^init: retrieval: '.*model.safetensors' has 1000 bytes, manifest.json records \d+ \(truncated\?\)"),
     (lambda f: _truncate(_saved_network(f, seal=False)), ValueError,
      r"^init: the weights in '.*start' cannot be read \(Error while deserializing header"),
     (lambda f: _saved_network(f, embed_dim=64), ValueError,
      r"^init: '.*' is a network of \{.*'embed_dim': 64.*\}; this stage trains \{.*'embed_dim': 256"),
     (lambda f: (_saved_network(f) / "model.safetensors").unlink() or f, FileNotFoundError,
      r"^init: retrieval: .*model.safetensors not found")],
    ids=["another bank", "truncated", "truncated, no manifest", "other sizes", "no weights"],
)  # fmt: skip
def test_a_start_network_that_cannot_start_this_run_is_refused_before_any_chip_is_rendered(
    tmp_path, monkeypatch, make, error, match
):
    """Read and checked whole before the folder opens: no run.json or data.npz blocks the corrected run."""
    import sar_zero123.stages.proxy_retrieval as stage

    start = make(tmp_path / "start")
    monkeypatch.setattr(stage, "make_retrieval_data", lambda *a, **k: pytest.fail("chips were rendered"))
    config = ProxyRetrievalConfig(output_dir=str(tmp_path / "run"), init=str(start), **TINY)
    with pytest.raises(error, match=match):
        run_proxy_retrieval(config)
    assert not (tmp_path / "run").exists()
    with pytest.raises(FileNotFoundError, match=r"no config.json in '.*empty'"):  # an empty folder
        (tmp_path / "empty").mkdir()
        ProxyRetrievalConfig(output_dir=str(tmp_path / "run"), init=str(tmp_path / "empty"), **TINY)


def test_turntable_targets_rank_the_bank_by_likeness_from_every_side(tmp_path):
    """A bank vehicle is most like itself from every side (similarity 1 with itself, its renders being the
    same bytes); a run with turntable targets starts from a saved network and records both."""
    from sar_zero123.model.retrieval import make_retrieval_data, turntable_similarity

    bank = ProxyBank(3)
    similarity = turntable_similarity(bank, pool=2, step_deg=90.0, workers=1)
    assert similarity.shape == (5, 3) and np.all(similarity <= 1.0 + 1e-3)
    np.testing.assert_allclose(np.diag(similarity[:3]), 1.0, atol=1e-3)
    assert np.all(np.argmax(similarity[:3], axis=1) == np.arange(3))
    data = make_retrieval_data(bank, [17.0], 1, workers=1, target="turntable", pool=2)
    assert data["top_index"].shape == (72, 3) and np.all(data["vehicle"] < 5)
    own = data["vehicle"] < 3  # the bank's own vehicles: themselves first
    assert np.array_equal(data["top_index"][own, 0], data["vehicle"][own])
    first = run_proxy_retrieval(ProxyRetrievalConfig(output_dir=str(tmp_path / "a"), **TINY))
    out = run_proxy_retrieval(ProxyRetrievalConfig(output_dir=str(tmp_path / "b"), target="turntable",
                                                   init=str(first), pool_vehicles=2, **TINY))  # fmt: skip
    assert json.loads((out / "config.json").read_text())["training"]["target"] == "turntable"
    with pytest.raises(ValueError, match=r"target: expected 'pose' or 'turntable', got 'x'"):
        make_retrieval_data(bank, [17.0], 1, workers=1, target="x")
