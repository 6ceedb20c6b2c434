"""The proxy-retrieval stage: the learned shortlist of a proxy bank, trained on the simulator only.

``sar-zero123-proxy-retrieval`` (``python train/train_proxy_retrieval.py``) parses its flags into
:class:`ProxyRetrievalConfig` and calls :func:`run_proxy_retrieval`: the training chips
(:func:`~sar_zero123.model.retrieval.make_retrieval_data`, cached in ``data.npz``), the network
(:func:`~sar_zero123.training.retrieval.train_retrieval`) written to ``retrieval/`` (sealed), and its held-out
recall in ``metrics.json``. A pipeline uses it through its proxy settings (``"shortlist": 64, "retrieval":
"<output_dir>/retrieval"``); the bundled one is ``sar-zero123/proxy-retrieval``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from sar_zero123.config.json_io import write_json_atomic
from sar_zero123.model.proxy import DEFAULT_PROXY
from sar_zero123.model.retrieval import (
    POSE_BUCKET_DEG,
    ProxyRetrievalNet,
    load_retrieval,
    make_retrieval_data,
    save_retrieval,
)
from sar_zero123.runs.folder import StageTimer, finish_run
from sar_zero123.runs.stage import open_stage_folder
from sar_zero123.sim.proxy import ProxyBank
from sar_zero123.training.retrieval import train_retrieval, training_chips

logger = logging.getLogger(__name__)

__all__ = ["ProxyRetrievalConfig", "run_proxy_retrieval"]


@dataclass
class ProxyRetrievalConfig:
    """Train the learned shortlist of the default proxy bank into ``output_dir/retrieval``."""

    #: Settings without a flag (``--set FIELD=VALUE`` or ``--config``; ``--help`` lists them at its end).
    ADVANCED_FIELDS = ("batch_size", "learning_rate", "temperature", "workers", "pool_vehicles")

    output_dir: str = "runs/proxy_retrieval"  # run folder: data.npz, retrieval/, metrics.json
    target: Literal["pose", "turntable"] = "pose"  # rank as the fit at the chip's pose, or from every side
    init: str | None = None  # a saved network (name or folder) of the same bank to start from
    num_vehicles: int = DEFAULT_PROXY["num_vehicles"]  # vehicles of the bank it ranks (the default bank's)
    depressions_deg: list[float] = field(default_factory=lambda: [15.0, 20.0, 30.0, 45.0])  # bucket centres
    chips_per_bucket: int = 200  # training chips per 5 deg pose bucket
    steps: int = 6000  # optimiser steps
    batch_size: int = 256  # chips per step
    learning_rate: float = 2e-3  # AdamW peak learning rate (cosine decay)
    temperature: float = 0.01  # softmax temperature of the targets (the bank's correlations)
    seed: int = 0  # chips, split and initialisation
    pool_vehicles: int = 1500  # procedural vehicles beyond the bank that turntable targets cover
    workers: int = 2  # processes rendering the training chips
    resume: bool = False  # a finished run with these settings is returned; an unfinished one is redone
    restart: bool = False  # move an existing folder at output_dir aside (never deleted) and train anew

    def __post_init__(self) -> None:
        self.depressions_deg = [float(d) for d in self.depressions_deg]
        if not all(0.0 < d < 90.0 for d in self.depressions_deg) or not self.depressions_deg:
            raise ValueError(f"depressions_deg: expected degrees in (0, 90), got {self.depressions_deg}")
        for name, low in (("num_vehicles", 1), ("chips_per_bucket", 1), ("steps", 1), ("batch_size", 1),
                          ("workers", 1), ("pool_vehicles", 0)):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
        if self.num_vehicles > np.iinfo(np.int16).max:
            raise ValueError(
                f"num_vehicles: expected at most {np.iinfo(np.int16).max}, got {self.num_vehicles}"
            )
        if self.init is not None:  # refused before any chip is rendered
            from sar_zero123.pretrained import resolve_retrieval

            resolve_retrieval(self.init)
        for name in ("learning_rate", "temperature"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: expected a value > 0, got {getattr(self, name)!r}")
        chips = len(self.depressions_deg) * round(360.0 / POSE_BUCKET_DEG) * self.chips_per_bucket
        if self.batch_size > training_chips(chips):  # known before the chips are rendered
            raise ValueError(
                f"batch_size: expected at most the {training_chips(chips)} training chips of "
                f"{len(self.depressions_deg)} depression(s) x {self.chips_per_bucket} chips per bucket, got "
                f"{self.batch_size}"
            )

    def bank(self) -> dict[str, Any]:
        """The settings of the proxy bank the network ranks: the default bank's, ``num_vehicles`` vehicles."""
        bank = {**DEFAULT_PROXY, "num_vehicles": self.num_vehicles}
        return {key: bank[key] for key in ("num_vehicles", "first_seed", "blur_sigma_px", "render_seed")}


def run_proxy_retrieval(config: ProxyRetrievalConfig) -> Path:
    """Render the chips (or reuse ``data.npz`` made with the same settings), train, and write the network;
    returns its folder (``output_dir/retrieval``)."""
    timer = StageTimer()
    bank = config.bank()
    init = _start_network(config.init, bank)  # refused before the folder is opened or a chip rendered
    folder = open_stage_folder(
        config.output_dir, "proxy_retrieval", config, data=None, resume=config.resume, restart=config.restart,
        may_differ=("resume", "restart", "workers"), resume_hint="--resume",
    )  # fmt: skip
    out = folder.path / "retrieval"
    if folder.finished:
        logger.info("%s already holds this network", folder.path)
        return out
    settings = {"bank": bank, "depressions_deg": config.depressions_deg, "target": config.target,
                "chips_per_bucket": config.chips_per_bucket, "seed": config.seed,
                "pool_vehicles": config.pool_vehicles if config.target == "turntable" else 0}  # fmt: skip
    key = json.dumps(settings, sort_keys=True)
    data_file = folder.path / "data.npz"
    data = None
    if data_file.is_file():  # the stage's own file, written last and whole; checked against its key
        with np.load(data_file, allow_pickle=False) as stored:
            if str(stored["key"]) == key:
                data = {name: stored[name] for name in stored.files if name != "key"}
    if data is None:
        data = make_retrieval_data(ProxyBank(*bank.values()), config.depressions_deg, config.chips_per_bucket,
                                   config.seed, workers=config.workers, target=config.target,
                                   pool=config.pool_vehicles)  # fmt: skip
        partial = folder.path / "data.partial.npz"
        np.savez(partial, key=np.array(key), **data)
        partial.replace(data_file)
        logger.info("rendered %d training chips in %.0f s", len(data["azimuth"]), timer.seconds)
    net, recall = train_retrieval(data, bank, config.steps, config.batch_size, config.learning_rate,
                                  config.temperature, config.seed, init=init)  # fmt: skip
    save_retrieval(net, out, {"training": {"chips": int(len(data["azimuth"])), "steps": config.steps,
                                           "target": config.target, "init": config.init,
                                           "command": "train/train_proxy_retrieval.py"}})  # fmt: skip
    metrics = {"held_out_recall": {str(k): v for k, v in recall.items()}, "chips": int(len(data["azimuth"])),
               "seconds": timer.seconds}  # fmt: skip
    write_json_atomic(metrics, folder.path / "metrics.json")
    logger.info("held-out recall of the bucket's best vehicle: %s", recall)
    finish_run(folder, ["retrieval", "metrics.json", "data.npz"], seconds=timer.seconds, results=metrics)
    return out


def _start_network(init: str | None, bank: dict[str, Any]) -> ProxyRetrievalNet | None:
    """The saved network ``init`` names (``None``: none), read whole and checked against ``bank`` and the
    network this stage trains (:func:`~sar_zero123.training.retrieval.train_retrieval`'s), so that a
    folder of another bank, other sizes or a truncated file is refused before any work.

    Raises:
        FileNotFoundError: Naming ``init``, for a folder without the network's files.
        ValueError: Naming ``init``, for a file that differs from its manifest or cannot be read, another
            bank, or other sizes.
    """
    if init is None:
        return None
    from safetensors import SafetensorError

    from sar_zero123.pretrained import resolve_retrieval

    with torch.random.fork_rng(devices=[]):  # building the networks leaves the global generator as it was
        folder = resolve_retrieval(init)
        try:
            net = load_retrieval(folder, bank)
        except FileNotFoundError as error:
            raise FileNotFoundError(f"init: {error}") from None
        except ValueError as error:
            raise ValueError(f"init: {' '.join(str(error).split())}") from None
        except SafetensorError as error:  # a truncated or corrupt file in a folder without a manifest
            raise ValueError(f"init: the weights in {str(folder)!r} cannot be read ({error})") from None
        trained = ProxyRetrievalNet(bank).config()
    if net.config() != trained:
        raise ValueError(f"init: {init!r} is a network of {net.config()}; this stage trains {trained}")
    return net
