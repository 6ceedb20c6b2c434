"""Loading and saving a :class:`~sar_zero123.model.pipeline.SARZero123Pipeline`, and what it records.

:class:`PipelineLoadingMixin` gives the pipeline ``from_pretrained`` (bundled names resolved, a local folder
checked against its ``manifest.json`` and file by file), ``save_pretrained`` (sealed by a manifest) and
``from_zero123``. :func:`check_recorded_settings` checks what ``model_index.json`` records beside the
weights: the measured-best sampler, the proxy settings and the lineage.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import torch

from sar_zero123.model.loading import check_pipeline_folder, find_failing_component
from sar_zero123.model.proxy import check_proxy_settings
from sar_zero123.model.sampler import SAMPLER_DEFAULTS, START_FROM, SamplerSettings, _check_strength
from sar_zero123.model.zero123_checkpoints import load_zero123_components
from sar_zero123.pretrained import (
    BUNDLED_NAMESPACE,
    BUNDLED_PIPELINES,
    RETIRED_PIPELINES,
    is_bundled_name,
    resolve_pretrained,
)
from sar_zero123.runs.manifest import MANIFEST_FILE, manifest_problem, unlisted_files, write_manifest

__all__ = ["PipelineLoadingMixin", "anchored_proxy", "check_recorded_settings"]

logger = logging.getLogger(__name__)

PipelineType = TypeVar("PipelineType", bound="PipelineLoadingMixin")

#: Files of a pipeline folder that loading may read: one its manifest does not list is named in a warning.
_SEALED_SUFFIXES = (".json", ".safetensors", ".bin", ".pt", ".pth", ".ckpt", ".pkl", ".py", ".msgpack")


class PipelineLoadingMixin:
    """``from_pretrained``, ``save_pretrained`` and ``from_zero123``; listed before ``DiffusionPipeline``,
    whose loading and saving it wraps.
    """

    @classmethod
    def from_pretrained(
        cls: type[PipelineType], pretrained_model_name_or_path: str | os.PathLike, **kwargs: Any
    ) -> PipelineType:
        """diffusers' ``from_pretrained``, after resolving the name of a pipeline bundled with the package.

        Args:
            pretrained_model_name_or_path: A bundled name such as ``"sar-zero123/sim-prior-rotated"``, a
                ``save_pretrained`` folder, or anything else diffusers loads (an existing path wins).
            **kwargs: diffusers' loading options, and ``verify_manifest`` (default True): a local folder's
                files must match its ``manifest.json``; ``False`` loads a changed folder with a warning. A
                folder without a manifest loads with a warning.

        Raises:
            FileNotFoundError: For a bundled name whose weights are missing, a retired one (naming its
                replacement), an unknown ``"sar-zero123/"`` name (listing the bundled ones), or a missing
                ``model_index.json`` or component folder, config or weights, naming them.
            ValueError: For invalid JSON, a component that does not load, or (unless
                ``verify_manifest=False``) a file that differs from the manifest, naming it.
        """
        if isinstance(pretrained_model_name_or_path, str | os.PathLike) and (
            is_bundled_name(pretrained_model_name_or_path)
            or os.fspath(pretrained_model_name_or_path).startswith(BUNDLED_NAMESPACE)
        ):  # a bundled name, or a refusal listing them (never a hub lookup of an unknown bundled name)
            pretrained_model_name_or_path = resolve_pretrained(pretrained_model_name_or_path)
        folder = pretrained_model_name_or_path
        verify_manifest = kwargs.pop("verify_manifest", True)
        if isinstance(folder, str | os.PathLike) and not os.path.isdir(folder):
            _refuse_a_missing_local_name(os.fspath(folder))
        if not (isinstance(folder, str | os.PathLike) and os.path.isdir(folder)):
            return super().from_pretrained(folder, **kwargs)  # type: ignore[misc]
        # 1. a local folder: its files against its manifest (a changed file would give other views), then
        # each component's files, named before diffusers reads them
        _check_manifest(folder, verify_manifest)
        components = check_pipeline_folder(folder, given=kwargs)
        try:
            return super().from_pretrained(folder, **kwargs)  # type: ignore[misc]
        except (OSError, ValueError, RuntimeError, TypeError, KeyError):
            # 2. the files are there but something does not load: say which component
            find_failing_component(folder, components)
            raise

    def save_pretrained(self, save_directory: str | os.PathLike, **kwargs: Any) -> None:
        """diffusers' ``save_pretrained``, then ``manifest.json`` (written last, atomically): the size and
        SHA-256 of every file. A writer adding a file later seals the folder again (``write_manifest``).
        """
        super().save_pretrained(save_directory, **kwargs)  # type: ignore[misc]
        write_manifest(save_directory)

    @classmethod
    def from_zero123(
        cls: type[PipelineType],
        path: str | Path,
        use_ema: bool = True,
        image_encoder_path: str | Path | None = None,
        torch_dtype: torch.dtype | None = None,
        **conversion: Any,
    ) -> PipelineType:
        """Load an Objaverse zero-1-to-3 checkpoint in any layout
        (:func:`~sar_zero123.model.zero123_checkpoints.load_zero123_components`, which takes ``use_ema``,
        ``image_encoder_path`` and the LDM-only ``**conversion`` overrides).

        Returns:
            The pipeline in eval mode (``torch_dtype`` where given), with a DDIM scheduler for LDM files.
        """
        components = load_zero123_components(
            path, use_ema=use_ema, image_encoder_path=image_encoder_path, **conversion
        )
        pipe = cls(**components)
        if torch_dtype is not None:
            pipe.to(dtype=torch_dtype)  # type: ignore[attr-defined]
        return pipe


def check_recorded_settings(
    sampler: dict[str, Any] | None, proxy: dict[str, Any] | None, lineage: dict[str, Any] | None
) -> dict[str, Any] | None:
    """Refuse what ``model_index.json`` records beside the weights where a call could not use it: a
    sampler out of a call's range, a proxy start without proxy settings, invalid proxy settings, or a
    lineage that is not strings.

    Returns:
        The proxy settings, checked and completed, or ``None``.

    Raises:
        ValueError: Naming the record and the field.
    """
    if sampler is not None:
        if not isinstance(sampler, dict) or set(sampler) - set(SAMPLER_DEFAULTS):
            raise ValueError(f"`sampler` must be a dict of some of {list(SAMPLER_DEFAULTS)}, got {sampler!r}")
        if sampler.get("start_from", "input") not in START_FROM:
            raise ValueError(
                f"`sampler.start_from` must be one of {START_FROM}, got {sampler['start_from']!r}"
            )
        try:  # each recorded value within what a call may ask for (steps, guidance, strength)
            SamplerSettings(**{key: value for key, value in sampler.items() if key != "proxy_strength"})
        except (TypeError, ValueError) as error:
            raise ValueError(f"`sampler` (recorded in model_index.json): {error}") from None
        if sampler.get("proxy_strength") is not None:
            _check_strength(sampler["proxy_strength"], {}, "sampler.proxy_")
        if sampler.get("start_from") == "proxy" and proxy is None:
            raise ValueError("`sampler.start_from` is 'proxy', but the pipeline records no `proxy` settings")
    if proxy is not None:
        proxy = check_proxy_settings(proxy)
    if lineage is not None and not (
        isinstance(lineage, dict) and all(isinstance(v, str | None) for v in lineage.values())
    ):
        raise ValueError(f"`lineage` must be a dict of strings (where the weights began), got {lineage}")
    return proxy


def anchored_proxy(proxy: Mapping[str, Any] | None, folder: str | None) -> Mapping[str, Any] | None:
    """A pipeline's proxy settings with a relative ``retrieval`` folder read against the pipeline's own
    folder, never the working directory.
    """
    retrieval = None if proxy is None else proxy.get("retrieval")
    if (
        not isinstance(retrieval, str)
        or retrieval.startswith(BUNDLED_NAMESPACE)
        or os.path.isabs(retrieval)
        or not (isinstance(folder, str) and os.path.isdir(folder))
    ):
        return proxy
    return {**proxy, "retrieval": os.path.join(folder, retrieval)}


def _check_manifest(folder: str | os.PathLike, verify: bool) -> None:
    """Refuse (``verify``) or warn about a pipeline folder whose files differ from its ``manifest.json``."""
    if not (Path(folder) / MANIFEST_FILE).is_file():
        logger.warning(
            "pipeline %s has no %s (saved before manifests): its files are loaded unchecked; "
            "save it again with save_pretrained to seal it", folder, MANIFEST_FILE,
        )  # fmt: skip
        return
    added = [name for name in unlisted_files(folder) if name.endswith(_SEALED_SUFFIXES)]
    if added:  # files beside the sealed ones (a scaling written after save_pretrained): loaded, named
        logger.warning("pipeline %s: %s not in its %s (added after it was saved)", folder, added,
                       MANIFEST_FILE)  # fmt: skip
    problem = manifest_problem(folder)
    if problem is None:
        return
    if verify:
        raise ValueError(
            f"pipeline {os.fspath(folder)!r}: {problem}. A pipeline's files are loaded only as they were "
            "saved; pass verify_manifest=False to load it anyway"
        )
    logger.warning("pipeline %s loaded with verify_manifest=False although %s", folder, problem)


def _refuse_a_missing_local_name(text: str) -> None:
    """Refuse, listing the bundled pipelines, a name meant as a local folder or bundled pipeline that is
    neither (a hub lookup would answer with a network error).

    Raises:
        FileNotFoundError: For a path-like name (``./x``, ``../x``, ``/x``, ``~/x``), a bundled or retired
            name in another case or without its namespace (a retired one's hint is its replacement).
    """
    bundled = sorted(BUNDLED_PIPELINES)
    listing = f"the bundled pipelines are {bundled}"
    known = [*bundled, *RETIRED_PIPELINES]
    short_names = {name.split("/")[-1] for name in known}
    if text.lower().startswith(BUNDLED_NAMESPACE.lower()) or text in short_names:
        matches = [name for name in known if name.lower() == text.lower() or name.endswith("/" + text)]
        # a retired name's match is its replacement
        matches = [RETIRED_PIPELINES.get(name, name) for name in matches]
        hint = f"did you mean {matches[0]!r}? " if matches else ""
        raise FileNotFoundError(f"{text!r} is neither a pipeline folder nor a bundled name: {hint}{listing}")
    if text.startswith(("./", "../", "/", "~", ".\\")) or text in (".", ".."):
        raise FileNotFoundError(f"{text!r}: no such pipeline folder (a save_pretrained folder); {listing}")
