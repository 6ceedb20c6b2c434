"""A learned shortlist for the proxy fit: a small network that ranks a bank's vehicles for a chip at its pose.

An exhaustive fit renders every bank vehicle at the chip's pose, most of a proxy view's cost.
:class:`ProxyRetrievalNet` reads the chip (blurred, 2 x 2 pooled, standardised, and a copy turned to the
vehicle's frame) and its pose and gives one logit per bank vehicle, trained toward the softmax of each
vehicle's correlation with the chip (:func:`~sar_zero123.training.retrieval.train_retrieval`). A fit then
renders and scores only its ``shortlist`` best.

Training chips (:func:`make_retrieval_data`) are procedural vehicles in no prior corpus and no test set
(half the bank's, half from :data:`RETRIEVAL_FIRST_SEED`), at random poses with clutter and speckle, half
remapped by :func:`~sar_zero123.augment.codomain.random_monotonic` so the intensity mapping does not
decide; targets are computed before the remap. The config records the bank; :func:`load_retrieval` refuses
another.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sar_zero123.domain import to_decibels
from sar_zero123.sim.procedural import make_procedural_target
from sar_zero123.sim.proxy import POSE_BUCKET_DEG, ProxyBank
from sar_zero123.sim.render import render_chip

logger = logging.getLogger(__name__)

__all__ = [
    "RETRIEVAL_FIRST_SEED", "RETRIEVAL_TOP", "ProxyRetrievalNet", "load_retrieval", "make_retrieval_data",
    "retrieval_inputs", "save_retrieval",
]  # fmt: skip

#: First seed of the training vehicles beyond the bank: above the default bank's and every prior corpus's.
RETRIEVAL_FIRST_SEED = 2_000_000
#: Bank vehicles kept per training chip as its soft target (the rest weigh nothing at the temperature used).
RETRIEVAL_TOP = 64
#: The simulator chips' rotation convention: a vehicle turned by ``a`` turns its footprint by ``-a``.
_ROTATION_SIGN = -1
_CONFIG = "config.json"
_WEIGHTS = "model.safetensors"


def _pose_features(azimuth_deg: torch.Tensor, depression_deg: torch.Tensor, harmonics: int) -> torch.Tensor:
    """``[cos k a, sin k a (k = 1..harmonics), e, e^2]``, ``e = (depression - 30) / 15``: ``(B, 2H + 2)``."""
    a = torch.deg2rad(azimuth_deg.float())[:, None] * torch.arange(1, harmonics + 1, dtype=torch.float32)
    e = ((depression_deg.float() - 30.0) / 15.0)[:, None]
    return torch.cat([torch.cos(a), torch.sin(a), e, e * e], dim=1)


def retrieval_inputs(chips: torch.Tensor, blur_sigma_px: float) -> torch.Tensor:
    """Chips ``(B, S, S)`` (``S`` even; any affine map of decibels) as the network reads them: blurred by
    the bank's ``blur_sigma_px``, 2 x 2 average-pooled, standardised per chip (0 for a constant chip).

    Returns:
        ``(B, S / 2, S / 2)`` float32.
    """
    x = chips.float()[:, None]
    if blur_sigma_px > 0:
        radius = max(1, int(math.ceil(4 * blur_sigma_px)))
        t = torch.arange(-radius, radius + 1, dtype=torch.float32)
        kernel = torch.exp(-0.5 * (t / blur_sigma_px) ** 2)
        kernel = kernel / kernel.sum()
        x = F.pad(x, (radius, radius, radius, radius), mode="reflect")
        x = F.conv2d(F.conv2d(x, kernel.view(1, 1, 1, -1)), kernel.view(1, 1, -1, 1))
    x = F.avg_pool2d(x, 2)[:, 0]
    mean = x.mean(dim=(1, 2), keepdim=True)
    std = x.std(dim=(1, 2), keepdim=True)
    return torch.where(std > 0, (x - mean) / std.clamp_min(1e-6), torch.zeros_like(x))


class ProxyRetrievalNet(nn.Module):
    """Logits over a bank's vehicles for chips at their poses.

    Args:
        bank: The bank it ranks: ``num_vehicles``, ``first_seed``, ``blur_sigma_px``, ``render_seed``.
        channels: Widths of the four convolution stages (the last three halve the 32 px input).
        embed_dim: Width of the chip's embedding and of each vehicle's code.
        harmonics: Azimuth harmonics of the pose features.
    """

    def __init__(
        self, bank: dict[str, Any], channels: Sequence[int] = (32, 64, 128, 128), embed_dim: int = 256,
        harmonics: int = 3,
    ) -> None:  # fmt: skip
        super().__init__()
        if len(channels) != 4 or not all(isinstance(c, int) and c >= 1 for c in channels):
            raise ValueError(f"channels: expected four positive integers, got {channels!r}")
        self.bank = {key: bank[key] for key in ("num_vehicles", "first_seed", "blur_sigma_px", "render_seed")}
        self.channels, self.embed_dim, self.harmonics = (
            tuple(int(c) for c in channels),
            int(embed_dim),
            int(harmonics),
        )
        layers: list[nn.Module] = []
        width = 2
        for k, c in enumerate(self.channels):
            layers += [
                nn.Conv2d(width, c, 3, stride=1 if k == 0 else 2, padding=1),
                nn.GroupNorm(8, c),
                nn.SiLU(),
            ]
            width = c
        self.trunk = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(4), nn.Flatten())
        pose_dim = 2 * self.harmonics + 2
        self.head = nn.Sequential(
            nn.Linear(width * 16 + pose_dim, 512), nn.SiLU(), nn.Linear(512 + pose_dim, self.embed_dim)
        )
        self.codes = nn.Parameter(
            torch.randn(int(self.bank["num_vehicles"]), self.embed_dim) / self.embed_dim**0.5
        )
        self.bias = nn.Parameter(torch.zeros(int(self.bank["num_vehicles"])))

    def config(self) -> dict[str, Any]:
        """What :func:`load_retrieval` rebuilds it from."""
        return {"bank": self.bank, "channels": list(self.channels), "embed_dim": self.embed_dim,
                "harmonics": self.harmonics}  # fmt: skip

    def forward(
        self, inputs: torch.Tensor, azimuth_deg: torch.Tensor, depression_deg: torch.Tensor
    ) -> torch.Tensor:
        """Logits ``(B, num_vehicles)`` for :func:`retrieval_inputs` ``(B, s, s)`` at their poses ``(B,)``."""
        x = inputs[:, None]
        # the chip turned to the vehicle's frame (its hull along one axis whatever its azimuth)
        angle = torch.deg2rad(-azimuth_deg.float() * _ROTATION_SIGN)
        cos, sin = torch.cos(angle), torch.sin(angle)
        theta = torch.stack([torch.stack([cos, -sin, torch.zeros_like(cos)], 1),
                             torch.stack([sin, cos, torch.zeros_like(cos)], 1)], 1)  # fmt: skip
        grid = F.affine_grid(theta, list(x.shape), align_corners=False)
        turned = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        pose = _pose_features(azimuth_deg, depression_deg, self.harmonics)
        h = self.head[1](self.head[0](torch.cat([self.trunk(torch.cat([x, turned], 1)), pose], 1)))
        z = self.head[2](torch.cat([h, pose], 1))
        return z @ self.codes.t() + self.bias

    @torch.no_grad()
    def rank(self, chip: np.ndarray, azimuth_deg: float, depression_deg: float) -> np.ndarray:
        """Bank indices, best first, for one chip ``(S, S)`` (any affine map of decibels) at its pose."""
        inputs = retrieval_inputs(torch.from_numpy(np.asarray(chip, dtype=np.float32))[None],
                                  float(self.bank["blur_sigma_px"]))  # fmt: skip
        logits = self(inputs, torch.tensor([float(azimuth_deg)]), torch.tensor([float(depression_deg)]))[0]
        return torch.argsort(logits, descending=True, stable=True).numpy()


def _bucket_chips(args: tuple) -> dict[str, np.ndarray]:
    """One pose bucket's training chips and targets (a worker process)."""
    from threadpoolctl import threadpool_limits

    from sar_zero123.augment.codomain import random_monotonic

    bank_args, azimuth, depression, count, seed, size, pool = args
    threadpool_limits(limits=1)
    bank = _bank(*bank_args)  # built once per worker process
    rng = np.random.default_rng(seed)
    # pose targets: the bank's pooled correlations at the bucket's centre; turntable targets (pool > 0)
    # the caller looks up from each chip's vehicle
    features = None if pool else bank.bucket_features(azimuth, depression, size)
    chips, azimuths, depressions, top_index, top_score, vehicles = [], [], [], [], [], []
    generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
    for k in range(count):
        if pool:
            vehicle = int(rng.integers(bank.num_vehicles + pool))
            target = _pool_target(bank, vehicle)
        elif k % 2 == 0:
            vehicle = int(rng.integers(bank.num_vehicles))
            target = bank.target(vehicle)
        else:
            vehicle = -1
            target = make_procedural_target(RETRIEVAL_FIRST_SEED + int(rng.integers(1_000_000)))
        a = float(azimuth + rng.uniform(-POSE_BUCKET_DEG / 2, POSE_BUCKET_DEG / 2)) % 360.0
        e = float(np.clip(depression + rng.uniform(-POSE_BUCKET_DEG / 2, POSE_BUCKET_DEG / 2), 1.0, 89.0))
        magnitude = render_chip(target, a, e, size, rng)
        vehicles.append(vehicle)
        if features is None:
            best, scores = np.zeros(0, dtype=np.int64), np.zeros(0)
        else:
            scores = features @ bank.coarse_features(to_decibels(magnitude)[None])[0]
            best = np.argsort(-scores, kind="stable")[:RETRIEVAL_TOP]
        if rng.uniform() < 0.5:  # the co-domain's random monotonic map: the target stays the chip's own
            magnitude = random_monotonic(torch.from_numpy(magnitude)[None, None].clamp(0, 1), gamma=0.5,
                                         generator=generator)[0, 0].numpy()  # fmt: skip
        chips.append(to_decibels(np.maximum(magnitude, 1e-6)).astype(np.float32))
        azimuths.append(a), depressions.append(e), top_index.append(best), top_score.append(scores[best])
    inputs = retrieval_inputs(torch.from_numpy(np.stack(chips)), bank.blur_sigma_px).numpy()
    return {"inputs": inputs.astype(np.float16), "azimuth": np.array(azimuths, dtype=np.float32),
            "vehicle": np.array(vehicles, dtype=np.int32),
            "depression": np.array(depressions, dtype=np.float32),
            "top_index": np.stack(top_index).astype(np.int16),
            "top_score": np.stack(top_score).astype(np.float32)}  # fmt: skip


#: A bank per settings, built once per process (``model.proxy.proxy_bank`` would import this module back).
_bank = functools.lru_cache(maxsize=4)(ProxyBank)
#: Procedural seed of the turntable pool's first vehicle beyond the bank (:func:`turntable_similarity`).
TURNTABLE_POOL_SEED = RETRIEVAL_FIRST_SEED + 1_500_000


def _pool_target(bank: ProxyBank, vehicle: int):
    """Vehicle ``vehicle`` of the turntable pool: the bank's own first, then procedural seeds from
    :data:`TURNTABLE_POOL_SEED`."""
    if vehicle < bank.num_vehicles:
        return bank.target(vehicle)
    return _pool_vehicle(TURNTABLE_POOL_SEED + vehicle - bank.num_vehicles)


@functools.lru_cache(maxsize=4096)
def _pool_vehicle(seed: int):
    """A pool vehicle beyond the bank, built once per process (its chips and turntable reuse it)."""
    return make_procedural_target(seed)


def _turntable_features(args: tuple) -> np.ndarray:
    """Pooled features ``(len(vehicles), A, size^2 / 4)`` of pool vehicles on an azimuth grid (a worker)."""
    from threadpoolctl import threadpool_limits

    bank_args, vehicles, azimuths, depression, size = args
    threadpool_limits(limits=1)
    bank = _bank(*bank_args)  # built once per worker process
    out = []
    for vehicle in vehicles:
        target = _pool_target(bank, int(vehicle))
        renders = [
            render_chip(target, a, depression, size, np.random.default_rng(bank.render_seed))
            for a in azimuths
        ]
        out.append(bank.coarse_features(to_decibels(np.stack(renders))).astype(np.float16))
    return np.stack(out)


def turntable_similarity(
    bank: ProxyBank,
    pool: int,
    step_deg: float = 15.0,
    depression_deg: float = 17.0,
    size: int = 64,
    workers: int = 2,
) -> np.ndarray:
    """How alike each pool vehicle and each bank vehicle image from every side: their renders' pooled
    correlation at the same azimuth (a ``step_deg`` grid at ``depression_deg``), averaged.

    Returns:
        ``(num_vehicles + pool, num_vehicles)`` float32: rows the bank's vehicles then ``pool``
        procedural ones from :data:`TURNTABLE_POOL_SEED`; columns the bank's.
    """
    azimuths = np.arange(0.0, 360.0, step_deg)
    bank_args = (bank.num_vehicles, bank.first_seed, bank.blur_sigma_px, bank.render_seed)
    chunks = np.array_split(np.arange(bank.num_vehicles + pool), max(1, 8 * workers))
    with ProcessPoolExecutor(max_workers=workers) as executor:
        jobs = [(bank_args, c, azimuths, depression_deg, size) for c in chunks if len(c)]
        features = torch.from_numpy(
            np.concatenate(list(executor.map(_turntable_features, jobs))).astype(np.float32)
        )
    return (torch.einsum("upd,vpd->uv", features, features[: bank.num_vehicles]) / len(azimuths)).numpy()


def make_retrieval_data(
    bank: ProxyBank,
    depressions: Sequence[float],
    chips_per_bucket: int,
    seed: int = 0,
    size: int = 64,
    workers: int = 2,
    target: str = "pose",
    pool: int = 1500,
) -> dict[str, np.ndarray]:
    """Training chips for :class:`ProxyRetrievalNet`: ``chips_per_bucket`` in every azimuth bucket at each
    depression bucket centre, in ``workers`` processes.

    Args:
        target: ``"pose"``: the bank's pooled correlations with the chip at its pose bucket (the exhaustive
            fit's ranking). ``"turntable"``: its vehicle's :func:`turntable_similarity` to each bank vehicle
            (chips of the bank's vehicles and of ``pool`` procedural ones).
        pool: Procedural vehicles beyond the bank that the turntable targets cover.

    Returns:
        ``inputs`` ``(N, S/2, S/2)`` float16, ``azimuth``, ``depression``, ``vehicle`` ``(N,)``,
        ``top_index`` ``(N, RETRIEVAL_TOP)`` int16 and ``top_score``.

    Raises:
        ValueError: For another ``target``, or a bank too large for int16 indices.
    """
    if target not in ("pose", "turntable"):
        raise ValueError(f"target: expected 'pose' or 'turntable', got {target!r}")
    if not bank.num_vehicles <= np.iinfo(np.int16).max:
        raise ValueError(
            f"bank.num_vehicles: expected at most {np.iinfo(np.int16).max}, got {bank.num_vehicles}"
        )
    bank_args = (bank.num_vehicles, bank.first_seed, bank.blur_sigma_px, bank.render_seed)
    pool = int(pool) if target == "turntable" else 0
    similarity = turntable_similarity(bank, pool, size=size, workers=workers) if pool else None
    jobs = [
        (bank_args, float(a), float(e), int(chips_per_bucket), (seed, j), size, pool)
        for j, (a, e) in enumerate(
            (a, e) for e in depressions for a in np.arange(0.0, 360.0, POSE_BUCKET_DEG)
        )
    ]
    with ProcessPoolExecutor(max_workers=workers) as executor:
        parts = list(executor.map(_bucket_chips, jobs))
    data = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    if similarity is not None:
        rows = torch.from_numpy(similarity)[torch.from_numpy(data["vehicle"]).long()]
        top = torch.topk(rows, min(RETRIEVAL_TOP, bank.num_vehicles), dim=1)  # sorted, best first
        data["top_index"] = top.indices.numpy().astype(np.int16)
        data["top_score"] = top.values.numpy().astype(np.float32)
    return data


def save_retrieval(net: ProxyRetrievalNet, folder: str | Path, extra: dict[str, Any] | None = None) -> Path:
    """Write ``config.json`` and ``model.safetensors`` (float16) to ``folder``, sealed last by its
    ``manifest.json`` (:func:`~sar_zero123.runs.manifest.write_manifest`)."""
    from safetensors.torch import save_file

    from sar_zero123.runs.manifest import write_manifest

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to(torch.float16).contiguous() for k, v in net.state_dict().items()}
    save_file(state, str(folder / _WEIGHTS))
    (folder / _CONFIG).write_text(
        json.dumps({**net.config(), **(extra or {})}, indent=2, sort_keys=True) + "\n"
    )
    write_manifest(folder)
    return folder


def load_retrieval(folder: str | Path, bank: dict[str, Any] | None = None) -> ProxyRetrievalNet:
    """A saved :class:`ProxyRetrievalNet` (weights read as safetensors: data, never code).

    Raises:
        FileNotFoundError: If ``folder`` lacks its config or weights.
        ValueError: If a file differs from the folder's ``manifest.json``, its config is malformed, or it
            records another bank than ``bank``.
    """
    from safetensors.torch import load_file

    from sar_zero123.runs.manifest import MANIFEST_FILE, manifest_problem

    folder = Path(folder)
    for name in (_CONFIG, _WEIGHTS):
        if not (folder / name).is_file():
            raise FileNotFoundError(
                f"retrieval: {folder / name} not found (a saved ProxyRetrievalNet folder)"
            )
    if not (folder / MANIFEST_FILE).is_file():
        logger.warning("retrieval %s has no %s: its weights are loaded unchecked", folder, MANIFEST_FILE)
    problem = manifest_problem(folder)
    if problem is not None:
        raise ValueError(f"retrieval: {problem}")
    try:
        config = json.loads((folder / _CONFIG).read_text())
        saved_bank = {
            key: config["bank"][key] for key in ("num_vehicles", "first_seed", "blur_sigma_px", "render_seed")
        }
        net = ProxyRetrievalNet(saved_bank, config["channels"], config["embed_dim"], config["harmonics"])
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(
            f"retrieval: {folder / _CONFIG} is not a ProxyRetrievalNet config ({error})"
        ) from None
    if bank is not None:
        wanted = {key: bank[key] for key in saved_bank}
        if wanted != saved_bank:
            raise ValueError(f"retrieval: {folder} ranks the bank {saved_bank}, not {wanted}")
    state = load_file(str(folder / _WEIGHTS))
    try:
        net.load_state_dict({k: v.float() for k, v in state.items()})
    except RuntimeError as error:
        raise ValueError(f"retrieval: {folder / _WEIGHTS} does not match its config ({error})") from None
    return net.eval()
