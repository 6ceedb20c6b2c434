"""The bounded YAML reader of recipes and --config files: data only, no aliases, bounded depth, no repeats."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from sar_zero123.config import read_config_file
from sar_zero123.stages.presets import load_recipe
from sar_zero123.yaml_data import MAX_YAML_DEPTH, read_yaml

# nine levels of aliases: 2**9 leaves per level, ~1e25 nodes when expanded
ALIAS_BOMB = 'a: &a ["xxxxxxxx","xxxxxxxx"]\n' + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join([f'*{chr(97 + i)}'] * 9)}]\n" for i in range(9)
)


def test_plain_data_reads_as_safe_load_does() -> None:
    text = (
        "data:\n  classes: [TANK, TRUCK]\n  azimuth_step_deg: 7.5\nfinetune: {finetune_steps: 3, x: null}\n"
    )
    assert read_yaml(text, "recipe") == {
        "data": {"classes": ["TANK", "TRUCK"], "azimuth_step_deg": 7.5},
        "finetune": {"finetune_steps": 3, "x": None},
    }
    assert read_yaml("", "recipe") is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (ALIAS_BOMB, "recipe 'r': YAML anchors and aliases"),
        ("data: &d {classes: [TANK]}\n", "anchors and aliases"),  # an anchor alone is refused too
        (
            "finetune:\n  finetune_steps: 2\n  finetune_steps: 5000000\n",
            r"'finetune_steps' is given twice \(line 3\)",
        ),
        ("finetune: {a: 1}\ndata: {b: 2}\nfinetune: {c: 3}\n", r"'finetune' is given twice \(line 3\)"),
        ("[" * 5000 + "]" * 5000, f"nested deeper than {MAX_YAML_DEPTH} levels"),
        ("{a: " * 5000 + "1" + "}" * 5000, f"nested deeper than {MAX_YAML_DEPTH} levels"),
        ("a: !!python/object:os.system ls\n", "not valid YAML"),
        ("a: [1, 2\n", "not valid YAML"),
    ],
)
def test_hostile_yaml_is_refused_in_one_line_naming_the_file(text: str, message: str) -> None:
    start = time.perf_counter()
    with pytest.raises(ValueError, match=message) as caught:
        read_yaml(text, "recipe 'r'")
    assert str(caught.value).startswith("recipe 'r': ") and "\n" not in str(caught.value)  # one line
    assert time.perf_counter() - start < 30  # bounded: the alias bomb is never expanded (not a speed test)


def test_recipes_and_config_files_use_the_bounded_reader(tmp_path: Path) -> None:
    recipe = tmp_path / "mine.yaml"
    recipe.write_text("extends: smoke\nfinetune:\n  finetune_steps: 2\n  finetune_steps: 5000000\n")
    with pytest.raises(ValueError, match="'finetune_steps' is given twice"):
        load_recipe(str(recipe))
    recipe.write_text(ALIAS_BOMB)
    with pytest.raises(ValueError, match="anchors and aliases"):
        load_recipe(str(recipe))
    config = tmp_path / "config.yaml"
    config.write_text("seed: 1\nseed: 2\n")
    with pytest.raises(ValueError, match=r"--config .*config.yaml.*'seed' is given twice"):
        read_config_file(config)
    config.write_text("seed: 3\nd_az: [30, 60]\n")
    assert read_config_file(config) == {"seed": 3, "d_az": [30, 60]}
