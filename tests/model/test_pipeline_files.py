"""Saved pipeline folders whose files name code or lie about themselves: refused by name, or loaded as named.

Each case edits one file of a saved tiny pipeline: ``model_index.json`` naming a module outside the
component libraries, a scheduler config naming another class, a ``manifest.json`` that is not JSON or that
lists a file outside the folder.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from dummies import get_dummy_components

from sar_zero123.model.pipeline import SARZero123Pipeline


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("pipeline") / "pipe"
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(folder)
    return folder


@pytest.fixture
def pipeline_copy(saved, tmp_path) -> Path:
    folder = tmp_path / "pipe"
    folder.mkdir()
    for path in saved.rglob("*"):
        if path.is_file():
            (folder / path.relative_to(saved)).parent.mkdir(parents=True, exist_ok=True)
            (folder / path.relative_to(saved)).write_bytes(path.read_bytes())
    return folder


def _edit_json(path: Path, **changes) -> None:
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


@pytest.mark.parametrize(("library", "class_name"), [("os", "system"), ("subprocess", "Popen")])
def test_a_model_index_naming_a_module_outside_the_component_libraries_is_refused_unimported(
    pipeline_copy, library, class_name
):
    _edit_json(pipeline_copy / "model_index.json", extra=[library, class_name])
    expected = rf"component 'extra' is listed as {library}\.{class_name}; a component must come from one of"
    with pytest.raises(ValueError, match=expected + r" \['diffusers'"):
        SARZero123Pipeline.from_pretrained(pipeline_copy, verify_manifest=False)


def test_a_model_index_naming_a_pipeline_as_its_unet_asks_for_that_pipeline_s_own_index(pipeline_copy):
    _edit_json(pipeline_copy / "model_index.json", unet=["diffusers", "StableDiffusionPipeline"])
    expected = r"unet/model_index\.json: no such file; expected the model_index\.json of component 'unet'"
    with pytest.raises(FileNotFoundError, match=expected):
        SARZero123Pipeline.from_pretrained(pipeline_copy, verify_manifest=False)


def test_a_scheduler_config_naming_another_class_loads_the_class_model_index_names(pipeline_copy):
    _edit_json(pipeline_copy / "scheduler" / "scheduler_config.json", _class_name="FlaxDDIMScheduler")
    pipe = SARZero123Pipeline.from_pretrained(pipeline_copy, verify_manifest=False)
    assert (
        type(pipe.scheduler).__name__
        == json.loads((pipeline_copy / "model_index.json").read_text())["scheduler"][1]
        == "DDIMScheduler"
    )


def test_a_manifest_that_is_not_json_is_refused_naming_it(pipeline_copy):
    (pipeline_copy / "manifest.json").write_text("{not json")
    with pytest.raises(
        ValueError, match=r"manifest\.json' is not a valid manifest \(Expecting property name"
    ):
        SARZero123Pipeline.from_pretrained(pipeline_copy)


def test_a_manifest_listing_a_file_outside_the_folder_is_refused_before_that_file_is_read(pipeline_copy):
    secret = pipeline_copy.parent / "secret.png"
    secret.write_bytes(b"not yours")
    files = json.loads((pipeline_copy / "manifest.json").read_text())["files"]
    entry = {"bytes": secret.stat().st_size, "sha256": "0" * 64}
    _edit_json(pipeline_copy / "manifest.json", files={**files, "../secret.png": entry})
    with pytest.raises(
        ValueError, match=r"manifest\.json of '.*pipe' lists '\.\./secret\.png', outside the folder"
    ):
        SARZero123Pipeline.from_pretrained(pipeline_copy)
