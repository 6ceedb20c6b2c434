"""Simulator proxies of a prior corpus's vehicles: what a proxy-conditioned UNet trains with.

A ``spatial_pose="proxy"`` UNet sees, beside the input chip, a simulator vehicle fitted to it rendered at
the input's and the requested pose. Each corpus vehicle gets its proxies as the pipeline would fit them:
the bank (whose seeds are never a corpus's) is fitted to the vehicle's first view, the ``candidates``
best bank vehicles are kept (runners-up: a proxy is never exact) and rendered at every chip's pose.

``proxies.safetensors`` holds ``chips`` ``(N, K, S, S)``, float16 peak-normalised magnitudes, and
``bank_index`` ``(N, K)``; ``proxies.json``, written last and atomically, records the bank, the candidates
and every chip's path in index order. A killed run leaves no partial file.
"""

from __future__ import annotations

import functools
import json
import os
import tempfile
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.data.datasets import load_chip
from sar_zero123.data.images import load_magnitude
from sar_zero123.data.index import load_index
from sar_zero123.domain import naming_write_errors, to_decibels
from sar_zero123.sim.corpus import corpus_vehicle_seed
from sar_zero123.sim.procedural import make_procedural_target
from sar_zero123.sim.proxy import PROXY_FIRST_SEED, ProxyBank

__all__ = [
    "ORACLE_INDEX",
    "PROXIES_FILE",
    "PROXIES_RECORD",
    "corpus_proxies_have_oracle",
    "load_corpus_proxies",
    "write_corpus_proxies",
]

#: The proxies' tensors, beside the corpus's ``index.csv``.
PROXIES_FILE = "proxies.safetensors"
#: Their record (bank, candidates, the chips in index order), written last.
PROXIES_RECORD = "proxies.json"
#: The bank index of the oracle candidate, the vehicle itself (write_corpus_proxies(oracle=True)).
ORACLE_INDEX = -1
_MAX_CANDIDATES = 8


@functools.lru_cache(maxsize=1)
def _bank(*bank_args: Any) -> ProxyBank:
    """The process's bank (its vehicles are built once, then reused for every corpus vehicle)."""
    return ProxyBank(*bank_args)


def _one_thread_each() -> None:
    """One BLAS/FFT thread per process (N processes on N cores, not N x N threads)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _vehicle_proxies(args: tuple) -> tuple[np.ndarray, np.ndarray]:
    """One vehicle's proxies ``(chips (V, K, S, S) float16, bank indices (K,))``: the bank fitted to its first
    chip, the ``K`` best rendered at every chip's pose."""
    bank_args, candidates, fit_chip, poses, oracle_seed = args
    bank = _bank(*bank_args)
    azimuth, depression = poses[0]
    scores = bank.scores(to_decibels(fit_chip.astype(np.float64)), azimuth, depression)
    best = np.argsort(-scores, kind="stable")[:candidates]
    size = fit_chip.shape[-1]
    renders = [[bank.render(int(k), az, el, size) for k in best] for az, el in poses]
    if oracle_seed is not None:  # the vehicle itself, rendered as the bank renders: a perfect proxy
        vehicle = make_procedural_target(oracle_seed)
        for row, (az, el) in zip(renders, poses, strict=True):
            row.append(bank.render_target(vehicle, az, el, size))
        best = np.append(best, ORACLE_INDEX)
    return np.stack([np.stack(row) for row in renders]).astype(np.float16), best.astype(np.int32)


def write_corpus_proxies(
    corpus_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str] | None = None,
    *,
    num_vehicles: int = 250,
    first_seed: int = PROXY_FIRST_SEED,
    blur_sigma_px: float = 1.5,
    render_seed: int = 0,
    candidates: int = 2,
    size: int | None = None,
    num_workers: int = 1,
    progress: bool = True,
    oracle: bool = False,
) -> Path:
    """Fit and render every corpus vehicle's proxies (see the module docstring); returns the record's path.

    Args:
        corpus_dir: A prior corpus or any image folder whose ``index.csv`` gives azimuths and depressions.
        out_dir: Where :data:`PROXIES_FILE` and :data:`PROXIES_RECORD` go; ``None``: ``corpus_dir``.
        num_vehicles, first_seed, blur_sigma_px, render_seed: The :class:`ProxyBank`.
        candidates: Best-scoring bank vehicles kept per corpus vehicle (1-8).
        size: Chip side, each chip read as a fine-tune reads it (a centre crop keeping the pixel spacing);
            ``None``: the chips as they are, which must be square and of one size.
        oracle: Also keep as the last candidate (:data:`ORACLE_INDEX`) the vehicle itself, rendered as the
            bank renders (a simulated corpus only), so that the UNet learns when to trust a proxy.

    Raises:
        FileNotFoundError: If ``corpus_dir`` has no ``index.csv``.
        ValueError: For an invalid bank or ``candidates``, or chips that are not square and one size.
    """
    corpus = Path(corpus_dir)
    if not (corpus / "index.csv").is_file():
        raise FileNotFoundError(f"corpus_dir: expected a folder with index.csv, got {corpus}")
    if (
        isinstance(candidates, bool)
        or int(candidates) != candidates
        or not 1 <= candidates <= _MAX_CANDIDATES
    ):
        raise ValueError(f"candidates: expected an integer in [1, {_MAX_CANDIDATES}], got {candidates!r}")
    bank_args = (num_vehicles, first_seed, blur_sigma_px, render_seed, 0)
    ProxyBank(*bank_args)  # refuses an invalid bank here, not in a worker
    if candidates > num_vehicles:
        raise ValueError(f"candidates: at most the bank's {num_vehicles} vehicles, got {candidates}")
    records = load_index(corpus)
    paths = [Path(r.path).resolve().relative_to(corpus.resolve()).as_posix() for r in records]
    vehicles: dict[tuple[str, str], list[int]] = {}
    for n, record in enumerate(records):
        vehicles.setdefault((record.target_class, record.serial), []).append(n)
    if size is not None and (isinstance(size, bool) or int(size) != size or size < 1):
        raise ValueError(f"size: expected an integer >= 1 or None, got {size!r}")
    jobs, read_size = [], size
    for members in vehicles.values():
        path = records[members[0]].path
        if read_size is None:  # the chips as stored: one square size
            chip = np.asarray(load_magnitude(path), dtype=np.float32)
        else:
            chip = load_chip(path, int(read_size))
        size = chip.shape[-1] if size is None else int(size)
        if chip.shape != (size, size):
            raise ValueError(
                f"{paths[members[0]]}: expected a square chip of the index's first size {size}, got "
                f"{chip.shape}"
            )
        poses = [(records[n].azimuth_deg, records[n].depression_deg) for n in members]
        seed = corpus_vehicle_seed(records[members[0]].serial) if oracle else None
        jobs.append((bank_args, int(candidates), chip, poses, seed))
    kept_candidates = candidates + int(oracle)
    chips = np.zeros((len(records), kept_candidates, size, size), dtype=np.float16)
    bank_index = np.zeros((len(records), kept_candidates), dtype=np.int32)
    with ProcessPoolExecutor(max_workers=num_workers, initializer=_one_thread_each) as pool:
        for done, (members, (vehicle_chips, best)) in enumerate(
            zip(vehicles.values(), pool.map(_vehicle_proxies, jobs, chunksize=4), strict=True), 1
        ):
            chips[members] = vehicle_chips
            bank_index[members] = best
            if progress and done % 200 == 0:
                print(f"proxies: {done}/{len(vehicles)} vehicles", flush=True)
    record = {
        "bank": dict(zip(("num_vehicles", "first_seed", "blur_sigma_px", "render_seed"), bank_args)),
        "candidates": int(candidates),
        "oracle": bool(oracle),
        "fit": "each vehicle's first chip in the index, at its azimuth and depression",
        "size": size,
        "paths": paths,
    }
    kept = "no proxies file is kept from a failed write; a re-run starts over"
    out = corpus if out_dir is None else Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with naming_write_errors(out / PROXIES_FILE, kept):
        fd, tmp = tempfile.mkstemp(prefix=".proxies-", suffix=".safetensors", dir=out)
        os.close(fd)
        try:
            save_file(
                {"chips": torch.from_numpy(chips), "bank_index": torch.from_numpy(bank_index)},
                tmp,
                metadata={"format": "pt"},
            )
            os.replace(tmp, out / PROXIES_FILE)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return write_json_atomic(record, out / PROXIES_RECORD)  # last: the proxies are complete


def corpus_proxies_have_oracle(
    corpus_dir: str | os.PathLike[str], proxies_dir: str | os.PathLike[str] | None = None
) -> bool:
    """Whether a corpus's proxies keep the oracle as their last candidate (``oracle=True`` above)."""
    folder = Path(corpus_dir) if proxies_dir is None else Path(proxies_dir)
    record = folder / PROXIES_RECORD
    return record.is_file() and json.loads(record.read_text()).get("oracle") is True


def load_corpus_proxies(
    corpus_dir: str | os.PathLike[str],
    chip_paths: Sequence[str | os.PathLike],
    proxies_dir: str | os.PathLike[str] | None = None,
) -> torch.Tensor:
    """The proxies of the given chips of a corpus, in their order: ``(N, K, S, S)`` float32 magnitudes.

    ``chip_paths`` are absolute or relative to the corpus; ``proxies_dir`` defaults to the corpus folder.

    Raises:
        FileNotFoundError: If the corpus has no proxies (naming the command that writes them).
        ValueError: If the record and the tensors disagree, or a chip has no proxy.
    """
    corpus = Path(corpus_dir)
    folder = corpus if proxies_dir is None else Path(proxies_dir)
    record_path, tensor_path = folder / PROXIES_RECORD, folder / PROXIES_FILE
    if not record_path.is_file() or not tensor_path.is_file():
        raise FileNotFoundError(
            f"{folder}: no {PROXIES_RECORD} / {PROXIES_FILE}; write them with "
            "sar_zero123.sim.corpus_proxies.write_corpus_proxies (train/pretrain_prior.py does)"
        )
    record: dict[str, Any] = json.loads(record_path.read_text())
    tensors = load_file(tensor_path)
    chips = tensors.get("chips")
    paths = record.get("paths")
    if chips is None or not isinstance(paths, list) or chips.ndim != 4 or chips.shape[0] != len(paths):
        raise ValueError(
            f"{tensor_path}: expected `chips` (N, K, S, S) with one row per path of {record_path}, got "
            f"{None if chips is None else tuple(chips.shape)} and "
            f"{len(paths) if isinstance(paths, list) else paths} paths"
        )
    row = {path: n for n, path in enumerate(paths)}
    root = corpus.resolve()
    rows = []
    for chip_path in chip_paths:
        path = Path(chip_path)
        if path.is_absolute():
            resolved = path.resolve()
            path = resolved.relative_to(root) if resolved.is_relative_to(root) else resolved
        relative = path.as_posix()
        if relative not in row:
            raise ValueError(f"{chip_path}: no proxy in {record_path} (written for another corpus?)")
        rows.append(row[relative])
    return chips[torch.as_tensor(rows, dtype=torch.long)].float()
