"""The proxy shortlist's training: its loss and recall, and a loop that learns a separable toy task and stops
at once when it diverges."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sar_zero123.training.retrieval import retrieval_loss, shortlist_recall, train_retrieval

BANK = {"num_vehicles": 3, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0}


def toy_data(n: int = 48, seed: int = 0) -> dict[str, np.ndarray]:
    """Chips whose best vehicle is written in their mean intensity (vehicle k: chips around k)."""
    rng = np.random.default_rng(seed)
    best = rng.integers(0, 3, n)
    inputs = (best[:, None, None] + 0.1 * rng.standard_normal((n, 32, 32))).astype(np.float32)
    top_index = np.stack([best, (best + 1) % 3, (best + 2) % 3], 1)
    top_score = np.tile(np.array([1.0, 0.0, -1.0], np.float32), (n, 1))
    azimuth, depression = rng.uniform(0, 360, n).astype(np.float32), np.full(n, 17.0, np.float32)
    return {"inputs": inputs, "azimuth": azimuth, "depression": depression, "top_index": top_index,
            "top_score": top_score}  # fmt: skip


def test_a_diverging_shortlist_stops_at_once_naming_the_learning_rate() -> None:
    torch.set_num_threads(1)
    with pytest.raises(FloatingPointError, match=r"^learning_rate: the shortlist's loss is nan at step \d+"):
        train_retrieval(toy_data(), BANK, steps=20, batch_size=8, learning_rate=1e30, held_out_share=0.25)


def test_the_loop_returns_an_eval_network_and_its_held_out_recall() -> None:
    torch.set_num_threads(1)
    net, recall = train_retrieval(toy_data(), BANK, steps=3, batch_size=8, held_out_share=0.25)
    assert not net.training and sorted(recall) == [1, 8, 32, 64, 128]
    assert all(0.0 <= value <= 1.0 for value in recall.values()) and recall[8] == 1.0  # 3 vehicles: all in 8


def test_loss_is_the_cross_entropy_against_the_tempered_softmax_of_the_scores():
    logits = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
    index, score = torch.tensor([[3, 1]]), torch.tensor([[0.9, 0.8]])
    target = torch.softmax(torch.tensor([90.0, 80.0]), 0)
    log_p = torch.log_softmax(logits[0], 0)[[3, 1]]
    expected = -(target * log_p).sum()
    torch.testing.assert_close(retrieval_loss(logits, index, score, 0.01), expected)


def test_recall_counts_the_best_within_the_first_k():
    ranked = np.array([[2, 0, 1], [0, 1, 2], [1, 2, 0], [2, 1, 0]])
    assert shortlist_recall(ranked, np.array([2, 1, 0, 0]), (1, 2, 3)) == {1: 0.25, 2: 0.5, 3: 1.0}
