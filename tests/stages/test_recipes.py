"""Recipes as files: small YAML files of per-stage values, merged onto the default recipe."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import yaml

from sar_zero123.config import parse_config
from sar_zero123.stages.presets import (
    MAX_RECIPE_BYTES,
    PRESETS,
    RECIPE_DIR,
    RECIPE_STAGES,
    Preset,
    QuickstartConfig,
    apply_overrides,
    load_recipe,
    recipe_names,
)


def test_every_field_lies_under_exactly_one_stage_and_the_default_sets_them_all() -> None:
    staged = [name for names in RECIPE_STAGES.values() for name in names]
    assert sorted(staged) == sorted(f.name for f in dataclasses.fields(Preset))
    default = yaml.safe_load((RECIPE_DIR / "default.yaml").read_text())
    assert "extends" not in default
    assert sorted(n for section in default.values() for n in section) == sorted(staged)


def test_bundled_recipes_load_extend_a_parent_and_set_only_what_differs() -> None:
    assert {"default", "scratch", "long", "mstar", "mstar-prior", "smoke", "proxy"} <= set(recipe_names())
    for name in recipe_names():
        assert PRESETS[name] == load_recipe(name)
        if name == "default":
            continue
        raw = yaml.safe_load((RECIPE_DIR / f"{name}.yaml").read_text())
        parent = PRESETS[raw.pop("extends")]
        for section in raw.values():  # a value equal to the parent's is a default, not a recipe field
            for field, value in section.items():
                current = getattr(parent, field)
                assert (list(current) if isinstance(current, tuple) else current) != value, (name, field)
    assert PRESETS["proxy"].prior == "sar-zero123/sim-prior-proxy"
    assert PRESETS["proxy"].eval_start_from == "proxy"
    assert PRESETS["mstar-prior"].vae_widths == PRESETS["mstar"].vae_widths  # two levels of extends


def test_a_recipe_file_of_ones_own_extends_a_bundled_one(tmp_path: Path) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text("extends: default\nfinetune:\n  finetune_steps: 3000\n  finetune_learning_rate: 3.0e-4\n")
    mine = load_recipe(str(path))
    assert mine == apply_overrides(PRESETS["default"], ["finetune_steps=3000", "finetune_learning_rate=3e-4"])
    assert mine == PRESETS["gentle"]
    assert QuickstartConfig(output_dir=str(tmp_path / "run"), recipe=str(path)).preset() == mine
    # --set takes FIELD=VALUE or STAGE.FIELD=VALUE
    assert apply_overrides(mine, ["finetune.finetune_steps=10"]).finetune_steps == 10


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("extends: default\ntrain:\n  finetune_steps: 3\n", "unknown stage 'train'"),
        ("extends: default\nfinetune:\n  steps: 3\n", "finetune.steps is not a field of finetune"),
        ("extends: default\nvae:\n  finetune_steps: 3\n", "it belongs under finetune"),
        ("extends: default\nfinetune:\n  finetune_steps: many\n", "finetune_steps takes int, got 'many'"),
        ("extends: default\nfinetune:\n  finetune_steps: 0\n", "finetune_steps must be an integer >= 1"),
        ("extends: ../default.yaml\n", "extends must name a bundled recipe"),
        ("finetune:\n  finetune_steps: 3\n", "no value for"),
        ("- a\n- b\n", "expected a mapping of stages to fields, got list"),
        ("extends: default\nfinetune: 3\n", "finetune must map fields to values"),
        ("!!python/object/apply:os.system ['echo owned']\n", "not valid YAML"),
        ("extends: default\nfinetune: {finetune_steps: [1\n", "not valid YAML"),
        # an infinity is no setting (YAML reads .inf and 1e999 so): refused before any stage runs
        (
            "extends: default\nfinetune:\n  finetune_learning_rate: .inf\n",
            "finetune_learning_rate takes float",
        ),
        (
            "extends: default\nevaluators:\n  evaluator_learning_rate: 1e999\n",
            "evaluator_learning_rate takes",
        ),
        ("extends: default\nmodel:\n  snr_gamma: .inf\n", r"snr_gamma takes float \| None, got inf"),
        ("extends: default\nfinetune:\n  finetune_steps: 2\n  finetune_steps: 5000000\n", "given twice"),
    ],
)
def test_a_bad_recipe_is_refused_by_name_before_any_stage(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        load_recipe(str(path))
    with pytest.raises(ValueError, match=match):
        QuickstartConfig(output_dir=str(tmp_path / "run"), recipe=str(path))


def test_recipe_files_are_bounded_and_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"recipe: 'nope' is neither a bundled recipe \(default"):
        load_recipe("nope")
    script = tmp_path / "recipe.py"
    script.write_text("x = 1\n")
    with pytest.raises(ValueError, match="expected a .yaml/.yml/.json file"):
        load_recipe(str(script))
    big = tmp_path / "big.yaml"
    big.write_text("#" * (MAX_RECIPE_BYTES + 1))
    with pytest.raises(ValueError, match="more than a recipe's"):
        load_recipe(str(big))
    json_recipe = tmp_path / "r.json"
    json_recipe.write_text('{"extends": "default", "evaluate": {"eval_n": 64}}')
    assert load_recipe(str(json_recipe)).eval_n == 64


def test_the_removed_flags_and_fields_are_refused_naming_their_replacement(tmp_path: Path) -> None:
    out = str(tmp_path / "run")
    with pytest.raises(ValueError, match=r"^--preset was removed: it is now recipe \(--recipe NAME\)$"):
        parse_config(QuickstartConfig, ["--output_dir", out, "--preset", "smoke"])
    with pytest.raises(ValueError, match=r"^--override was removed: it is now set \(--set STAGE.FIELD=VALUE"):
        parse_config(QuickstartConfig, ["--output_dir", out, "--override", "eval_n=8"])
    old = tmp_path / "config.json"  # a run folder's config.json written under the old names
    old.write_text(json.dumps({"output_dir": str(tmp_path / "r"), "preset": "smoke", "seed": 0}))
    with pytest.raises(ValueError, match=r"config.json': preset='smoke', but preset was removed: it is now"):
        parse_config(QuickstartConfig, ["--config", str(old)])
    flags = ["--output_dir", out, "--recipe", "smoke", "--set", "evaluate.eval_n=8"]
    config = parse_config(QuickstartConfig, flags)
    assert config.preset() == apply_overrides(PRESETS["smoke"], ["eval_n=8"])
