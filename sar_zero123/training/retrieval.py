"""Training of the proxy fit's learned shortlist (:class:`~sar_zero123.model.retrieval.ProxyRetrievalNet`):
its loss, its held-out recall and the loop."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from sar_zero123.model.retrieval import ProxyRetrievalNet

logger = logging.getLogger(__name__)

__all__ = ["HELD_OUT_SHARE", "retrieval_loss", "shortlist_recall", "training_chips", "train_retrieval"]

#: The share of the chips :func:`train_retrieval` keeps out of training to measure its recall on.
HELD_OUT_SHARE = 0.05


def training_chips(chips: int, held_out_share: float = HELD_OUT_SHARE) -> int:
    """How many of ``chips`` :func:`train_retrieval` trains on (at least one is held out)."""
    return chips - max(1, int(chips * held_out_share))



def retrieval_loss(
    logits: torch.Tensor, top_index: torch.Tensor, top_score: torch.Tensor, temperature: float
) -> torch.Tensor:
    """Cross-entropy of the logits against each chip's soft target: the softmax over ``temperature`` of its
    :data:`~sar_zero123.model.retrieval.RETRIEVAL_TOP` best bank correlations (the others weigh nothing).
    """
    target = torch.softmax(top_score.float() / temperature, dim=1)
    log_p = torch.log_softmax(logits.float(), dim=1).gather(1, top_index.long())
    return -(target * log_p).sum(dim=1).mean()


def shortlist_recall(ranked: np.ndarray, best: np.ndarray, ks: Sequence[int]) -> dict[int, float]:
    """Share of chips whose exhaustive best (``best`` ``(N,)``) is among the first ``k`` of ``ranked``
    ``(N, V)``, for each ``k``."""
    position = np.argmax(ranked == best[:, None], axis=1)
    return {int(k): float(np.mean(position < k)) for k in ks}


def train_retrieval(
    data: dict[str, np.ndarray],
    bank: dict[str, Any],
    steps: int,
    batch_size: int = 256,
    learning_rate: float = 2e-3,
    temperature: float = 0.01,
    seed: int = 0,
    held_out_share: float = HELD_OUT_SHARE,
    log_every: int = 250,
    init: ProxyRetrievalNet | None = None,
) -> tuple[ProxyRetrievalNet, dict[int, float]]:
    """Train a ProxyRetrievalNet on :func:`make_retrieval_data`'s chips (AdamW, warm-up, cosine decay),
    a seeded ``held_out_share`` kept out, from ``init``'s weights where given.

    Returns:
        ``(net, recall)``: the network in eval mode, and the held-out :func:`shortlist_recall` at 1, 8, 32, 64
        and 128.

    Raises:
        ValueError: For fewer chips than a batch, or a non-positive step count, batch or temperature.
        FloatingPointError: Naming ``learning_rate``, at the first step whose loss is not finite.
    """
    n = len(data["azimuth"])
    if not (steps >= 1 and batch_size >= 1 and temperature > 0 and 0 < held_out_share < 1):
        raise ValueError(
            f"steps, batch_size, temperature, held_out_share: expected >= 1, >= 1, > 0 and in (0, 1), got "
            f"{steps}, {batch_size}, {temperature}, {held_out_share}"
        )
    held_count = n - training_chips(n, held_out_share)
    if n - held_count < batch_size:
        raise ValueError(
            f"batch_size: expected at most the {n - held_count} training chips, got {batch_size}"
        )
    torch.manual_seed(seed)
    order = np.random.default_rng(seed).permutation(n)
    held, train = order[:held_count], order[held_count:]
    tensors = {k: torch.from_numpy(np.asarray(v)) for k, v in data.items()}
    net = ProxyRetrievalNet(bank)
    if init is not None:  # continue from a trained network of the same bank and sizes
        if init.config() != net.config():
            raise ValueError(f"init: expected a network of {net.config()}, got {init.config()}")
        net.load_state_dict(init.state_dict())
    net.train()
    optimizer = torch.optim.AdamW(net.parameters(), lr=learning_rate, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: min(1.0, (s + 1) / 200) * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps))
    )
    rng = np.random.default_rng(seed + 1)
    for step in range(steps):
        batch = torch.from_numpy(rng.choice(train, batch_size, replace=False))
        logits = net(
            tensors["inputs"][batch].float(), tensors["azimuth"][batch], tensors["depression"][batch]
        )
        loss = retrieval_loss(logits, tensors["top_index"][batch], tensors["top_score"][batch], temperature)
        if not torch.isfinite(loss):  # diverged: stop at once, naming the setting that moves it
            raise FloatingPointError(
                f"learning_rate: the shortlist's loss is {loss.item()} at step {step} (learning_rate "
                f"{learning_rate:g}); lower it"
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        if log_every and (step % log_every == 0 or step == steps - 1):
            logger.info("step %d: loss %.3f", step, loss.item())
    net.eval()
    with torch.no_grad():
        rows = torch.from_numpy(held)
        logits = net(tensors["inputs"][rows].float(), tensors["azimuth"][rows], tensors["depression"][rows])
        ranked = torch.argsort(logits, dim=1, descending=True, stable=True).numpy()
    best = np.asarray(data["top_index"])[held, 0].astype(np.int64)
    return net, shortlist_recall(ranked, best, (1, 8, 32, 64, 128))
