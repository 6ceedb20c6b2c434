"""Loading saved components with errors that name the component, the file expected and the folder.

diffusers and transformers report a broken folder in their own terms (a missing safetensors file as a
missing ``.bin``, a config that does not fit its weights with the name left blank). Here a folder is checked
file by file before diffusers reads it (:func:`check_pipeline_folder`), and a load that still fails is
traced to its component (:func:`load_component`, :func:`find_failing_component`).
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import torch
from diffusers import ModelMixin
from diffusers.schedulers.scheduling_utils import SchedulerMixin
from safetensors import SafetensorError
from safetensors.torch import load_file
from transformers import PreTrainedModel
from transformers.image_processing_base import ImageProcessingMixin

from sar_zero123.config.json_io import read_json

__all__ = [
    "PIPELINE_INDEX",
    "PIPELINE_SETTINGS",
    "check_component_folder",
    "check_pipeline_folder",
    "expected_files",
    "find_failing_component",
    "load_component",
    "load_weights_file",
]

#: The file ``DiffusionPipeline.save_pretrained`` writes: component name -> [library, class name].
PIPELINE_INDEX = "model_index.json"
#: Entries of :data:`PIPELINE_INDEX` that are a pipeline's recorded settings, not components.
PIPELINE_SETTINGS = ("sampler", "proxy", "lineage")
# Weight file stems; each may end in .safetensors or .bin, carry a variant (`.fp16`) or be sharded (index).
_WEIGHT_SUFFIXES = (".safetensors", ".bin", ".safetensors.index.json", ".bin.index.json")
# diffusers' shape-mismatch message: "Cannot load <name> because <param> expected shape torch.Size([..]),
# but got torch.Size([..]). If you want to ..."
_SHAPE_MISMATCH = re.compile(
    r"because (?P<param>\S+) expected shape torch\.Size\((?P<config>\[[^\]]*\])\), "
    r"but got torch\.Size\((?P<weights>\[[^\]]*\])\)"
)


def expected_files(component_class: type) -> tuple[str | None, tuple[str, ...]]:
    """The config file and the weight file stems a ``from_pretrained`` folder of ``component_class`` holds.

    Returns:
        ``(config_name, weight_stems)``, e.g. ``("config.json", ("diffusion_pytorch_model",))``; no stems
        for classes without weights, ``None`` for a class this module does not know.
    """
    if issubclass(component_class, ModelMixin):
        return component_class.config_name, ("diffusion_pytorch_model",)
    if issubclass(component_class, PreTrainedModel):
        return "config.json", ("model", "pytorch_model")
    if issubclass(component_class, SchedulerMixin):
        return component_class.config_name, ()
    if issubclass(component_class, ImageProcessingMixin):
        return "preprocessor_config.json", ()
    return getattr(component_class, "config_name", None), ()


def _describe(name: str, component_class: type) -> str:
    return f"component '{name}' ({component_class.__name__})"


def check_component_folder(folder: str | os.PathLike, name: str, component_class: type) -> None:
    """Refuse a component folder (``<pipeline>/<name>``) lacking its config or weights, or whose config is
    not JSON.

    Raises:
        FileNotFoundError: If the folder, its config file or its weights are missing; the message names
            the component, the file expected and the folder.
        ValueError: If the config file is not a JSON object (naming the file).
    """
    folder = Path(folder)
    what = _describe(name, component_class)
    if not folder.is_dir():
        raise FileNotFoundError(f"{what} is missing: no folder {str(folder)!r}")
    config_name, weight_stems = expected_files(component_class)
    if config_name is not None:
        config = read_json(folder / config_name, what=f"the {config_name} of {what}")
        if not isinstance(config, dict):
            raise ValueError(f"{folder / config_name}: expected a JSON object (the config of {what})")
    if weight_stems:
        names = [file.name for file in folder.iterdir() if file.is_file()]
        found = any(
            file_name.startswith(f"{stem}.") and file_name.endswith(_WEIGHT_SUFFIXES)
            for stem in weight_stems
            for file_name in names
        )
        if not found:
            raise FileNotFoundError(
                f"{what} has no weights: expected {weight_stems[0]}.safetensors in {str(folder)!r} "
                f"(it holds {sorted(names)})"
            )


#: The libraries a component may come from: ``model_index.json`` is data, and naming any other module
#: would make loading import (run) it.
COMPONENT_LIBRARIES = ("diffusers", "transformers", "sar_zero123")


#: Component modules that no longer exist -> the module that defines their classes now. A folder naming one
#: is refused in one line that says what to write instead.
REMOVED_COMPONENT_MODULES = {
    "sar_zero123.conditioning": "sar_zero123.model.conditioning",
    "sar_zero123.orientation": "sar_zero123.model.orientation",
}


def _import_class(library: str, class_name: str, name: str, index_path: Path) -> type:
    if library in REMOVED_COMPONENT_MODULES:
        raise ValueError(
            f"{index_path}: component '{name}' is listed as {library}.{class_name}, a module that was "
            f'removed; write "{REMOVED_COMPONENT_MODULES[library]}" in its place (weights load unchanged)'
        )
    if not isinstance(library, str) or library.split(".")[0] not in COMPONENT_LIBRARIES:
        raise ValueError(
            f"{index_path}: component '{name}' is listed as {library}.{class_name}; a component must come "
            f"from one of {list(COMPONENT_LIBRARIES)} (nothing else is imported)"
        )
    try:
        return getattr(importlib.import_module(library), class_name)
    except (ImportError, AttributeError):
        raise ValueError(
            f"{index_path}: component '{name}' is listed as {library}.{class_name}, which cannot be imported"
        ) from None


def check_pipeline_folder(folder: str | os.PathLike, given: Collection[str] = ()) -> dict[str, type]:
    """Check a ``save_pretrained`` pipeline folder file by file before diffusers loads it.

    Args:
        given: Components passed to ``from_pretrained`` as objects (their folders are not read).

    Returns:
        Component name -> class, for every non-``None`` component :data:`PIPELINE_INDEX` lists.

    Raises:
        FileNotFoundError: If :data:`PIPELINE_INDEX`, a listed component's folder, its config file or its
            weights are missing, naming them.
        ValueError: If a JSON file is invalid (naming it) or a listed class cannot be imported.
    """
    folder = Path(folder)
    index_path = folder / PIPELINE_INDEX
    if not index_path.is_file():
        raise FileNotFoundError(
            f"{str(folder)!r} is not a saved pipeline folder: no {PIPELINE_INDEX} in it (the file "
            "save_pretrained writes beside the component folders)"
        )
    index = read_json(index_path, what="the pipeline's component list {name: [library, class]}")
    if not isinstance(index, dict):
        raise ValueError(f"{index_path}: expected a JSON object {{name: [library, class]}}")
    components: dict[str, type] = {}
    for name, entry in index.items():
        if name.startswith("_"):
            continue
        if name in PIPELINE_SETTINGS:  # settings, not components: null or an object, checked by the pipeline
            if entry is not None and not isinstance(entry, dict):
                raise ValueError(
                    f"{index_path}: '{name}' must be null or an object of settings, got {entry!r}"
                )
            continue
        if not (isinstance(entry, list) and len(entry) == 2):
            raise ValueError(f"{index_path}: component '{name}' must be [library, class], got {entry!r}")
        library, class_name = entry
        if library is None or class_name is None or name in given:
            continue
        component_class = _import_class(library, class_name, name, index_path)
        if not (folder / name).is_dir():
            raise FileNotFoundError(
                f"{_describe(name, component_class)} is missing: {PIPELINE_INDEX} lists it, but "
                f"{str(folder)!r} has no folder {name!r}"
            )
        check_component_folder(folder / name, name, component_class)
        components[name] = component_class
    return components


def _explain(error: BaseException) -> str:
    """The cause of a failed ``from_pretrained``, without diffusers' blank-named shape message."""
    message = str(error)
    mismatch = _SHAPE_MISMATCH.search(message)
    if mismatch is not None:
        return (
            f"its config does not match its weights: the config builds {mismatch['param']} with shape "
            f"{mismatch['config']}, the weights hold {mismatch['weights']} (config and weights come from "
            "different models)"
        )
    return message.split(". If you want to instead overwrite")[0].strip()


def load_component(component_class: type, folder: str | os.PathLike, name: str, **kwargs: Any) -> Any:
    """``component_class.from_pretrained(folder, **kwargs)``, with errors that name the component ``name``.

    Raises:
        FileNotFoundError: If the folder, its config or its weights are missing.
        ValueError: If the files are there but do not load (a config that does not fit its weights, a
            truncated weight file), naming the component and the folder.
    """
    check_component_folder(folder, name, component_class)
    try:
        return component_class.from_pretrained(folder, **kwargs)
    except (OSError, ValueError, RuntimeError, TypeError, KeyError) as error:
        raise ValueError(
            f"{_describe(name, component_class)} cannot be loaded from {str(folder)!r}: {_explain(error)}"
        ) from error


def find_failing_component(folder: str | os.PathLike, components: Mapping[str, type]) -> None:
    """After a whole-pipeline load failed, load each component alone and raise for the first that fails.

    Raises:
        ValueError: For the first component that does not load; returns when each loads alone.
    """
    for name, component_class in components.items():
        load_component(component_class, Path(folder) / name, name)


def load_weights_file(
    module: torch.nn.Module, path: str | os.PathLike, what: str, device: str | torch.device = "cpu"
) -> None:
    """Load a ``.safetensors`` state dict into ``module`` strictly, with errors that name the file (``what``).

    Raises:
        FileNotFoundError: If ``path`` is not a file.
        ValueError: If the file is not readable safetensors, or its tensors do not fit ``module``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; expected the weights of {what}")
    try:
        state_dict = load_file(str(path), device=str(device))
    except (SafetensorError, OSError) as error:
        raise ValueError(
            f"{path}: cannot read the weights of {what} ({error}); the file is truncated or corrupt"
        ) from None
    try:
        module.load_state_dict(state_dict)
    except RuntimeError as error:
        first = str(error).strip().splitlines()
        detail = "; ".join(line.strip() for line in first[1:4]) or first[0]
        raise ValueError(
            f"{path}: the weights do not fit {what} as its config describes it ({detail}); the config and "
            "the weights come from different models"
        ) from None
