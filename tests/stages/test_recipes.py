"""Recipes as files: small YAML files of per-stage sections, merged onto each stage config's defaults."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import yaml

from sar_zero123.config import parse_config
from sar_zero123.stages.presets import (
    MAX_RECIPE_BYTES,
    RECIPE_DIR,
    RECIPE_SECTIONS,
    RECIPES,
    REMOVED_RECIPE_FIELDS,
    QuickstartConfig,
    SharedSettings,
    apply_overrides,
    load_recipe,
    recipe_names,
)
from sar_zero123.stages.quickstart import plan_stages

#: The removed recipe fields of the bundled recipes' old names: every one is named with its replacement.
OLD_DEFAULT_FIELDS = 52


def test_the_default_recipe_sets_only_what_differs_from_each_stage_configs_defaults() -> None:
    default = yaml.safe_load((RECIPE_DIR / "default.yaml").read_text())
    assert "extends" not in default and set(default) <= set(RECIPE_SECTIONS)
    for section, values in default.items():
        cls = RECIPE_SECTIONS[section]
        defaults = {
            f.name: f.default for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING
        }
        flat = {**{k: v for k, v in values.items() if k != "sampler"}, **values.get("sampler", {})}
        for name, value in flat.items():
            assert defaults.get(name, "<factory>") != value, (section, name)
    assert len(REMOVED_RECIPE_FIELDS) == OLD_DEFAULT_FIELDS


def test_bundled_recipes_load_extend_a_parent_and_set_only_what_differs() -> None:
    assert {"default", "scratch", "long", "mstar", "mstar-prior", "smoke", "proxy"} <= set(recipe_names())
    for name in recipe_names():
        assert RECIPES[name] == load_recipe(name)
        if name == "default":
            continue
        raw = yaml.safe_load((RECIPE_DIR / f"{name}.yaml").read_text())
        parent = RECIPES[raw.pop("extends")]
        for section, values in raw.items():  # a value equal to the parent's is a default, not a recipe field
            flat = {**{k: v for k, v in values.items() if k != "sampler"},
                    **{f"sampler.{k}": v for k, v in values.get("sampler", {}).items()}}  # fmt: skip
            for field, value in flat.items():
                current = parent.value(section, field)
                assert (list(current) if isinstance(current, tuple) else current) != value, (name, field)
    assert RECIPES["proxy"].shared.prior == "sar-zero123/sim-prior-identity"
    assert RECIPES["proxy"].value("evaluate", "sampler.start_from") == "proxy"
    assert RECIPES["default"].value("evaluate", "sampler.heading_guidance_scale") == 1.5
    # two levels of extends: mstar-prior's VAE widths are mstar's, its prior the default's
    assert RECIPES["mstar-prior"].value("vae", "block_out_channels") == (32, 64, 128)
    assert RECIPES["mstar-prior"].shared == SharedSettings(depression_targets_deg=())
    # a field no recipe sets is its stage config's default
    assert RECIPES["default"].value("finetune", "lr_scheduler") == "constant"


def test_a_recipe_file_of_ones_own_extends_a_bundled_one(tmp_path: Path) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text("extends: default\nfinetune:\n  max_train_steps: 3000\n  learning_rate: 3.0e-4\n")
    mine = load_recipe(str(path))
    assert (
        mine.sections
        == apply_overrides(
            RECIPES["default"], ["finetune.max_train_steps=3000", "finetune.learning_rate=3e-4"]
        ).sections
    )
    assert mine.sections == RECIPES["gentle"].sections
    assert QuickstartConfig(output_dir=str(tmp_path / "run"), recipe=str(path)).resolved_recipe() == mine
    assert apply_overrides(mine, ["finetune.max_train_steps=10"]).value("finetune", "max_train_steps") == 10
    nested = apply_overrides(mine, ["evaluate.sampler.strength=1", "shared.prior=none"])
    assert nested.value("evaluate", "sampler.strength") == 1.0 and nested.shared.prior is None
    assert RECIPES["default"].shared.prior is not None  # the recipe itself is unchanged


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("extends: default\ntrain:\n  max_train_steps: 3\n", "unknown section 'train'"),
        ("extends: default\nfinetune:\n  steps: 3\n", "finetune.steps is not a field of finetune"),
        (
            "extends: default\nfinetune:\n  max_train_steps: many\n",
            "finetune.max_train_steps: expected an integer within int64, got 'many'",
        ),
        ("extends: ../default.yaml\n", "extends must name a bundled recipe"),
        ("- a\n- b\n", "expected a mapping of sections to fields, got list"),
        ("extends: default\nfinetune: 3\n", "finetune must map fields to values"),
        ("!!python/object/apply:os.system ['echo owned']\n", "not valid YAML"),
        ("extends: default\nfinetune: {max_train_steps: [1\n", "not valid YAML"),
        # an infinity is no setting (YAML reads .inf and 1e999 so): refused before any stage runs
        ("extends: default\nfinetune:\n  learning_rate: .inf\n", "finetune.learning_rate: expected a finite"),
        ("extends: default\nevaluators:\n  learning_rate: 1e999\n", "evaluators.learning_rate: expected a"),
        ("extends: default\nfinetune:\n  snr_gamma: .inf\n", "finetune.snr_gamma: expected a finite number"),
        ("extends: default\nfinetune:\n  max_train_steps: 2\n  max_train_steps: 5000000\n", "given twice"),
        # a sampler field lives in its nested section
        ("extends: default\nevaluate:\n  strength: 0.5\n", "name it evaluate.sampler.strength"),
        ("extends: default\nevaluate:\n  sampler: {steps: 2}\n", "evaluate.sampler.steps is not a field"),
        ("extends: default\nshared:\n  image_size: 8\n", "shared.image_size must be >= 16, got 8"),
        ("extends: default\nshared:\n  prior: null\n  rehearsal: true\n", "shared.rehearsal: needs a prior"),
        # the old names, each refused naming its replacement (the table of removed names)
        (
            "extends: default\nfinetune:\n  finetune_steps: 3\n",
            "finetune.finetune_steps was removed: it is now finetune.max_train_steps",
        ),
        ("extends: default\nevaluate:\n  eval_strength: 0.5\n", "it is now evaluate.sampler.strength"),
        ("extends: default\nmodel:\n  prior: null\n", "model.prior was removed: it is now shared.prior"),
        # a stage field removed as a constant: refused at another value than the one it keeps
        (
            "extends: default\nsimclr:\n  momentum: 0.5\n",
            r"^recipe '.*bad.yaml': simclr: momentum=0.5, but momentum was removed: SGD's momentum is 0.9$",
        ),
    ],
)
def test_a_bad_recipe_is_refused_by_name_before_any_stage(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        load_recipe(str(path))
    with pytest.raises(ValueError, match=match):
        QuickstartConfig(output_dir=str(tmp_path / "run"), recipe=str(path))


def test_a_stage_refuses_its_own_fields_and_the_quickstarts_plumbing(tmp_path: Path) -> None:
    out = str(tmp_path / "run")
    for item, words in (
        ("finetune.max_train_steps=0", "the finetune lambda=0 stage refuses this recipe .*max_train_steps"),
        (
            "evaluate.sampler.strength=0.01",
            "the evaluate stage refuses .*strength 0.01 x num_inference_steps",
        ),
        ("simclr.image_size=32", r"simclr.image_size is set by the quickstart itself"),
    ):
        with pytest.raises(ValueError, match=words):
            plan_stages(QuickstartConfig(output_dir=out, recipe="smoke", set=[item]))
    assert not Path(out).exists()


def test_a_recipe_setting_a_removed_field_to_the_value_it_keeps_reads_as_before(tmp_path: Path) -> None:
    path = tmp_path / "old.yaml"
    path.write_text("extends: default\nsimclr: {momentum: 0.9, depths: [1, 1]}\nvae: {kl_weight: 1.0e-6}\n")
    recipe = load_recipe(str(path))
    assert recipe.sections["simclr"] == {**RECIPES["default"].sections["simclr"], "depths": (1, 1)}
    assert recipe.sections["vae"] == RECIPES["default"].sections["vae"]


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
    json_recipe.write_text('{"extends": "default", "evaluate": {"n": 64}}')
    assert load_recipe(str(json_recipe)).value("evaluate", "n") == 64


def test_the_removed_flags_and_fields_are_refused_naming_their_replacement(tmp_path: Path) -> None:
    out = str(tmp_path / "run")
    with pytest.raises(ValueError, match=r"^--preset was removed: it is now recipe \(--recipe NAME\)$"):
        parse_config(QuickstartConfig, ["--output_dir", out, "--preset", "smoke"])
    with pytest.raises(ValueError, match=r"^--override was removed: it is now set \(--set SECTION.FIELD="):
        parse_config(QuickstartConfig, ["--output_dir", out, "--override", "eval_n=8"])
    old = tmp_path / "config.json"  # a run folder's config.json written under the old names
    old.write_text(json.dumps({"output_dir": str(tmp_path / "r"), "preset": "smoke", "seed": 0}))
    with pytest.raises(ValueError, match=r"config.json': preset='smoke', but preset was removed: it is now"):
        parse_config(QuickstartConfig, ["--config", str(old)])
    for item, words in (("base_steps=5", "base_steps was removed: it is now base.max_train_steps"),
                        ("evaluate.eval_n=8", "evaluate.eval_n was removed: it is now evaluate.n"),
                        ("model.model_size=tiny", "model.model_size was removed: it is now base.size"),
                        ("nope=1", "expected SECTION.FIELD=VALUE with SECTION one of shared")):  # fmt: skip
        with pytest.raises(ValueError, match=f"^set: {words}"):
            parse_config(QuickstartConfig, ["--output_dir", out, "--set", item])
    with pytest.raises(ValueError, match=r"^set: simclr.momentum was removed: SGD's momentum is 0.9 \(in "):
        parse_config(QuickstartConfig, ["--output_dir", out, "--set", "simclr.momentum=0.9"])
    config = parse_config(
        QuickstartConfig, ["--output_dir", out, "--recipe", "smoke", "--set", "evaluate.n=8"]
    )
    assert config.resolved_recipe() == apply_overrides(RECIPES["smoke"], ["evaluate.n=8"])
