"""Pipelines bundled inside the package, loadable by name.

Example::

    from sar_zero123 import SIM_PRIOR_ROTATED, SARZero123Pipeline

    pipe = SARZero123Pipeline.from_pretrained(SIM_PRIOR_ROTATED)  # "sar-zero123/sim-prior-rotated"

A registered name resolves to a ``save_pretrained`` folder next to this file, shipped as package data;
``README.md`` here lists them, each with its model card. A retired name (:data:`RETIRED_PIPELINES`) is
refused, naming the bundled pipeline that replaces it.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = [
    "BUNDLED_NAMESPACE",
    "BUNDLED_PIPELINES",
    "PRETRAINED_DIR",
    "RETIRED_PIPELINES",
    "SIM_PRIOR_IDENTITY",
    "SIM_PRIOR_ROTATED",
    "PROXY_RETRIEVAL",
    "is_bundled_name",
    "resolve_pretrained",
    "resolve_retrieval",
]

#: The multi-view SAR prior trained on procedural simulated vehicles only, with the spatial pose input
#: (``spatial_pose="rotated_input"``): turns unseen vehicles' footprints (model card:
#: ``sim_prior_rotated.md``).
SIM_PRIOR_ROTATED = "sar-zero123/sim-prior-rotated"
#: ``sim-prior-rotated`` taught to read a simulator proxy fitted to its input (``spatial_pose="proxy"``), with
#: the input's own latent as cross-attention tokens and pairs whose proxy is the vehicle itself, so that a
#: turned vehicle keeps more of its own identity: needs the input's absolute azimuth (model card:
#: ``sim_prior_identity.md``).
SIM_PRIOR_IDENTITY = "sar-zero123/sim-prior-identity"
#: The learned shortlist of the default proxy bank (:class:`~sar_zero123.model.retrieval.ProxyRetrievalNet`;
#: model card: ``proxy_retrieval.md``): a proxy fit in 64 renders instead of 1,000.
PROXY_RETRIEVAL = "sar-zero123/proxy-retrieval"
#: Registered retrieval name -> folder under :data:`PRETRAINED_DIR`.
BUNDLED_RETRIEVAL: dict[str, str] = {PROXY_RETRIEVAL: "proxy_retrieval"}
#: The prefix of every bundled name: a name under it that is not registered (and no such path exists) is
#: refused with the list of bundled names, rather than looked up on a model hub.
BUNDLED_NAMESPACE = "sar-zero123/"
#: Registered name -> folder under :data:`PRETRAINED_DIR`.
BUNDLED_PIPELINES: dict[str, str] = {
    SIM_PRIOR_ROTATED: "sim_prior_rotated",
    SIM_PRIOR_IDENTITY: "sim_prior_identity",
}
#: A name no longer bundled -> the bundled name that replaces it (its weights remain in the git history).
RETIRED_PIPELINES: dict[str, str] = {
    "sar-zero123/sim-prior": SIM_PRIOR_ROTATED,
    "sar-zero123/sim-prior-proxy": SIM_PRIOR_IDENTITY,
}
#: Where the bundled folders live (this package's own folder).
PRETRAINED_DIR = Path(__file__).resolve().parent


def is_bundled_name(name_or_path: str | os.PathLike) -> bool:
    """Whether ``name_or_path`` is a registered name, which always means the bundled weights (a local folder
    spelled the same loads only as a path, ``./sar-zero123/sim-prior-rotated``)."""
    text = os.fspath(name_or_path)
    return text in BUNDLED_PIPELINES


def resolve_pretrained(name_or_path: str | os.PathLike) -> Path:
    """The bundled folder a registered name stands for; any other argument as a ``Path``, unchanged.

    Raises:
        FileNotFoundError: For a registered name whose folder has no ``model_index.json``, a retired name
            (naming its replacement), or an unregistered name under :data:`BUNDLED_NAMESPACE` (listing the
            bundled names).
    """
    text = os.fspath(name_or_path)
    if text in RETIRED_PIPELINES:
        raise FileNotFoundError(
            f"{text!r}: this bundled pipeline is retired; use {RETIRED_PIPELINES[text]!r} instead (a local "
            f"folder of that name: ./{text})"
        )
    if text.startswith(BUNDLED_NAMESPACE) and text not in BUNDLED_PIPELINES:
        bundled = sorted(BUNDLED_PIPELINES)
        raise FileNotFoundError(
            f"{text!r}: no bundled pipeline of that name; bundled: {bundled} (a local folder: ./{text})"
        )
    if not is_bundled_name(name_or_path):
        return Path(name_or_path)
    name = os.fspath(name_or_path)
    folder = PRETRAINED_DIR / BUNDLED_PIPELINES[name]
    if not (folder / "model_index.json").is_file():
        raise FileNotFoundError(
            f"bundled pipeline {name!r}: its weights are missing from this install (no model_index.json "
            f"in {str(folder)!r}); reinstall sar_zero123 from a release that ships them, or pass the "
            "folder of a saved pipeline instead"
        )
    return folder


def resolve_retrieval(name_or_path: str | os.PathLike) -> Path:
    """The folder of a learned proxy shortlist: a registered name (:data:`PROXY_RETRIEVAL`) or a path.

    Raises:
        FileNotFoundError: For an unregistered name under :data:`BUNDLED_NAMESPACE`, or a folder without the
            network's ``config.json``.
    """
    text = os.fspath(name_or_path)
    if text in BUNDLED_RETRIEVAL:  # always the bundled network (a local folder: ./sar-zero123/...)
        folder = PRETRAINED_DIR / BUNDLED_RETRIEVAL[text]
    elif text.startswith(BUNDLED_NAMESPACE):
        raise FileNotFoundError(
            f"{text!r}: no bundled retrieval of that name; bundled: {sorted(BUNDLED_RETRIEVAL)} (a local "
            f"folder: ./{text})"
        )
    else:
        folder = Path(text)
    if not (folder / "config.json").is_file():
        raise FileNotFoundError(
            f"retrieval {text!r}: no config.json in {str(folder)!r} (a folder written by "
            "train/train_proxy_retrieval.py)"
        )
    return folder
