"""Smoke test of the README main command: train/quickstart.py with the "smoke" recipe."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import warnings
from pathlib import Path

import pytest

from sar_zero123.config import removed_fields
from sar_zero123.config.json_io import config_to_dict
from sar_zero123.sim import simulate_dataset
from train import quickstart


def depression_sampled_with(out):
    """The depression guidance recorded by the azimuth and the depression evaluation."""
    return tuple(json.loads((out / f / "table3.json").read_text())["depression_guidance_scale"]
                 for f in ("eval", "eval_depression"))  # fmt: skip


def test_every_stage_config_is_built_before_any_work(tmp_path: Path) -> None:
    """plan_stages builds each stage's typed config; a setting a stage refuses fails before any folder."""
    out = tmp_path / "run"
    plans = quickstart.plan_stages(quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke"))
    names = [plan.name for plan in plans]
    assert names == ["simulate", "simulate depressions", "simclr", "vae", "base model", "finetune lambda=0",
                     "finetune lambda=4", "evaluators", "evaluate", "evaluate depressions"]  # fmt: skip
    by_name = {plan.name: plan.config for plan in plans}
    assert type(by_name["finetune lambda=4"]).__name__ == "FinetuneConfig"
    assert by_name["finetune lambda=4"].pfm_weight == 4.0
    assert by_name["finetune lambda=4"].pretrained == str(out / "base" / "pipeline")
    assert by_name["evaluate"].pipeline_names == ["lambda=0", "lambda=4"]
    paper = by_name["finetune lambda=4"]
    assert paper.pfm_min_snr == 0.004
    snr = quickstart.plan_stages(quickstart.QuickstartConfig(
        output_dir=str(out), recipe="smoke", set=["finetune.pfm_min_snr=2.0"]))
    assert {plan.name: plan.config for plan in snr}["finetune lambda=4"].pfm_min_snr == 2.0
    for stage in ("evaluate", "evaluate depressions"):  # the recipe's sampler, in both evaluations
        assert (by_name[stage].heading_guidance_scale, by_name[stage].strength) == (1.5, 0.5)
    guided = quickstart.plan_stages(quickstart.QuickstartConfig(
        output_dir=str(out), recipe="smoke", set=["evaluate.sampler.depression_guidance_scale=3"]))
    for plan in guided:
        if plan.name.startswith("evaluate"):
            assert plan.config.depression_guidance_scale == 3.0
    assert not out.exists()
    # refused by the stage config that owns the field, naming the stage, before any stage runs
    for item, words in (("base.max_train_steps=0", "base model stage .*max_train_steps must be >= 1, got 0"),
                        ("evaluate.n=2", "evaluate stage .*n must be >= 4 for an ood protocol"),
                        ("base.size=huge", "not a value of base.size \\(expected one of \\['tiny'"),
                        ("simulate.classes=APC", "simulate.classes must name at least two distinct classes"),
                        ("evaluate.speed_n=100", "speed_n must be <= the 2 seen pairs"),
                        ("evaluate.sampler.strength=0", "strength must lie in \\(0, 1\\]"),
                        ("evaluate.sampler.strength=0.4",
                         "strength 0.4 x num_inference_steps 2 leaves no denoising step"),
                        ("evaluate.sampler.heading_guidance_scale=-1", "heading_guidance_scale must lie in"),
                        ("evaluate.sampler.depression_guidance_scale=101",
                         "depression_guidance_scale must lie in")):  # fmt: skip
        with pytest.raises(ValueError, match=words):
            quickstart.plan_stages(
                quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", set=[item])
            )
    assert not out.exists()


def _planned(out: Path, override: list[str]) -> tuple[list[str], dict]:
    """The smoke recipe with ``override`` planned into ``out``: the stages between SimCLR and the
    evaluators, and every stage's config by name."""
    plans = quickstart.plan_stages(
        quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", set=override)
    )
    names = [plan.name for plan in plans]
    return names[names.index("simclr") + 1 : names.index("evaluators")], {p.name: p.config for p in plans}


def test_the_retired_decoder_fine_tune_and_evaluation_rows_are_refused_by_name(tmp_path: Path) -> None:
    """shared.decoder_fine_tune (with its vae_decoder section) and evaluate's speckle rows were retired: --set
    refuses each in one line naming it; a recipe or a run's record holding them at their old defaults reads
    as before, and one that set the switch is refused."""
    from sar_zero123.stages.presets import load_recipe, refuse_old_record

    for item, words in [
        ("shared.decoder_fine_tune=true", r"shared.decoder_fine_tune was removed: fine-tuning the prior"),
        ("vae_decoder.max_train_steps=3", r"^set: vae_decoder was removed with shared.decoder_fine_tune: "),
        ("evaluate.speckle_looks=1", r"evaluate.speckle_looks was removed: rows of views with speckle"),
        ("evaluate.vae=/x", r"evaluate.vae was removed: "),
    ]:
        with pytest.raises(ValueError, match=words):
            quickstart.apply_overrides(quickstart.RECIPES["default"], [item])
    old = tmp_path / "old.yaml"
    old.write_text("extends: default\nvae_decoder:\n  train_encoder: false\n")
    assert load_recipe(str(old)).sections == quickstart.RECIPES["default"].sections
    old.write_text("extends: default\nshared:\n  decoder_fine_tune: true\n")
    with pytest.raises(ValueError, match=r"decoder_fine_tune=True, but decoder_fine_tune was removed: "):
        load_recipe(str(old))
    record = {"config": {"recipe.shared.decoder_fine_tune": False, "recipe.vae_decoder.train_encoder": False,
                         "recipe.shared.rehearsal": False}}  # fmt: skip
    assert sorted(refuse_old_record(record, "out")) == [
        "recipe.shared.decoder_fine_tune", "recipe.vae_decoder.train_encoder"
    ]  # fmt: skip
    with pytest.raises(ValueError, match=r"^out: recipe.shared: decoder_fine_tune=True, but decoder_"):
        refuse_old_record({"config": {"recipe.shared.decoder_fine_tune": True}}, "out")


def test_the_removed_finetune_lora_rank_is_refused_by_name(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="finetune.lora_rank was removed: a low-rank update"):
        quickstart.plan_stages(quickstart.QuickstartConfig(output_dir=str(out), set=["finetune.lora_rank=8"]))
    assert not out.exists()


def test_rehearsal_vehicles_plan_a_corpus_stage_that_every_fine_tune_rehearses(tmp_path: Path) -> None:
    """shared.rehearsal (with a prior) renders a corpus before the fine-tunes, each of which mixes its
    whole training split into finetune.rehearsal_fraction of every batch; the corpus stage runs resumably."""
    out = tmp_path / "run"
    prior = ["shared.prior=sar-zero123/sim-prior-rotated", "shared.image_size=64", "shared.rehearsal=true"]
    override = [*prior, "corpus.num_vehicles=3", "finetune.rehearsal_fraction=0.5"]
    between, by_name = _planned(out, override)
    assert between == ["rehearsal corpus", "finetune lambda=0", "finetune lambda=4"]
    corpus = by_name["rehearsal corpus"]
    assert (corpus.num_vehicles, corpus.num_validation_vehicles, corpus.size) == (3, 1, 64)
    for name in ("finetune lambda=0", "finetune lambda=4"):
        finetune = by_name[name]
        assert finetune.rehearsal_data == str(out / "rehearsal" / "corpus")
        assert (finetune.rehearsal_fraction, finetune.rehearsal_max_chips) == (0.5, None)
    assert not out.exists()  # planned before the corpus exists: the fine-tune checks it when it runs
    refusals = (("corpus.num_vehicles=1", r"num_vehicles: expected an integer >= 2, got 1"),
                ("finetune.rehearsal_fraction=1.0",
                 r"rehearsal_fraction must lie in \[0, 1\), got 1.0"))  # fmt: skip
    for item, words in refusals:
        with pytest.raises(ValueError, match=words):
            config = quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", set=[*prior, item])
            quickstart.plan_stages(config)
    with pytest.raises(ValueError, match="shared.rehearsal: needs a prior"):
        quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", set=["shared.rehearsal=true"])
    # the stage: the corpus lands in output_dir/corpus; the same command again finds it finished
    from sar_zero123.data import load_index
    from sar_zero123.stages import CorpusConfig, run_corpus

    small = CorpusConfig(output_dir=str(tmp_path / "corpus"), num_vehicles=3, views_per_vehicle=2,
                         num_validation_vehicles=1, size=16, num_workers=1)  # fmt: skip
    folder = run_corpus(small)
    assert folder == tmp_path / "corpus" / "corpus"
    records = load_index(folder)
    assert len(records) == 6 and sorted({r.target_class for r in records}) == ["PROCEDURAL", "PROCVAL"]
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "corpus").rglob("*") if p.is_file()}
    assert run_corpus(small) == folder
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "corpus").rglob("*") if p.is_file()} == before
    with pytest.raises(ValueError, match="views_per_vehicle: folder 2, this run 3"):
        run_corpus(dataclasses.replace(small, views_per_vehicle=3))
    with pytest.raises(ValueError, match=r"num_validation_vehicles: expected 1 .. num_vehicles - 1, got 3"):
        CorpusConfig(num_vehicles=3, num_validation_vehicles=3)
    with pytest.raises(ValueError, match=r"size: expected an integer >= 16, got 8"):
        CorpusConfig(size=8)


def test_a_proxy_prior_plans_a_proxies_stage_that_every_fine_tune_conditions_on(tmp_path: Path) -> None:
    """A prior whose UNet takes the simulator proxy: a proxies stage (the data's vehicles fitted, read only)
    before the fine-tunes, each of which reads its proxies; the evaluations start where their sampler says.
    The stage writes the proxies into its own folder and a second run finds them finished."""
    out = tmp_path / "run"
    override = ["shared.prior=sar-zero123/sim-prior-identity", "shared.image_size=64",
                "evaluate.sampler.start_from='proxy'"]
    between, by_name = _planned(out, override)
    assert between == ["proxies", "finetune lambda=0", "finetune lambda=4"]
    stage = by_name["proxies"]
    assert (stage.data, stage.output_dir) == (str(out / "data"), str(out / "proxies"))
    assert stage.image_size == 64  # the chips read as the fine-tunes read them (real chips: a centre crop)
    for name in ("finetune lambda=0", "finetune lambda=4"):
        assert by_name[name].proxies == str(out / "proxies" / "proxies")
    assert {by_name[name].start_from for name in ("evaluate", "evaluate depressions")} == {"proxy"}
    assert not out.exists()
    rotated = quickstart.plan_stages(quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke"))
    assert "proxies" not in [plan.name for plan in rotated]
    assert all(getattr(plan.config, "proxies", None) is None for plan in rotated)
    words = r"evaluate.sampler.start_from \(expected one of \['input', 'turned_input', 'proxy'\]"
    with pytest.raises(ValueError, match=words):
        quickstart.QuickstartConfig(
            output_dir=str(out), recipe="smoke", set=["evaluate.sampler.start_from=noise"]
        )
    # the stage, on a two-vehicle folder: read only, the proxies in its own folder, finished on a second run
    from chip_folders import write_chip_folder

    from sar_zero123.data.corpus_proxies import load_corpus_proxies
    from sar_zero123.data.index import load_index
    from sar_zero123.stages.proxies import ProxiesConfig, run_proxies

    data = write_chip_folder(tmp_path / "data", azimuths_deg=(0, 90, 180), size=16)
    before = {p: p.stat().st_mtime_ns for p in data.rglob("*")}
    config = ProxiesConfig(data=str(data), output_dir=str(tmp_path / "proxies"), num_vehicles=3,
                           num_workers=1)  # fmt: skip
    folder = run_proxies(config)
    assert folder == tmp_path / "proxies" / "proxies"
    paths = [record.path for record in load_index(data)]
    assert load_corpus_proxies(data, paths, folder).shape == (len(paths), 2, 16, 16)
    assert {p: p.stat().st_mtime_ns for p in data.rglob("*")} == before
    written = {p: p.stat().st_mtime_ns for p in folder.rglob("*")}
    assert run_proxies(config) == folder and {p: p.stat().st_mtime_ns for p in folder.rglob("*")} == written
    with pytest.raises(ValueError, match=r"candidates: at most num_vehicles \(1\), got 2"):
        ProxiesConfig(data=str(data), num_vehicles=1)
    with pytest.raises(FileNotFoundError, match="data: expected a folder with index.csv"):
        run_proxies(dataclasses.replace(config, data=str(tmp_path / "nothing")))


def test_quickstart_smoke_runs_every_stage(tmp_path: Path) -> None:
    out = tmp_path / "quickstart"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tiny sample counts: the Frechet distance warns about n <= D
        report = quickstart.main(["--output_dir", str(out), "--recipe", "smoke"])
    text = report.read_text()
    # with a depression regressor among the evaluators Table III has a Dep. err. column and its gap closed;
    # simulated pairs are read against their vehicle's other chips too (template azimuth, front/back)
    paper_row = "| paper: PFM (lambda=4) | seen | 89.0 | 23.5 | - | 1.84 | 0.6720 | 0.7374 |" + " - |" * 6
    assert ("| Template az. err. (deg) ↓ | Front/back right (%) ↑ | Turned and kept (%) ↑ "
            "| Dep. err. (deg) ↓ |") in text
    assert "| Dep. gap closed ↑ | Template gap closed ↑ | n |" in text
    # the recipe's sampler reaches both evaluations and the report names it
    sampler = "2 DDIM steps, guidance 3.0, heading guidance 1.5, from the input at strength 0.5"
    assert f"## Table III ({sampler})" in text
    for folder in ("eval", "eval_depression"):
        sampled = json.loads((out / folder / "table3.json").read_text())
        assert (sampled["heading_guidance_scale"], sampled["strength"]) == (1.5, 0.5)
    assert paper_row + "  |  |  |  |  |" in text
    # the depression table: 17 deg inputs asked for 30 deg; the from-scratch smoke model never saw d_el != 0
    assert "## Depression changes (17 deg inputs, targets at 30 deg)" in text
    assert "| Closer to target dep. ↑ |" in text and "never trained on these depression changes" in text
    assert "Sampled as Table III, with depression guidance 2 (each step pushed away" in text
    assert depression_sampled_with(out) == (2.0, 2.0)  # only the depression table names it; both record it
    depression = json.loads((out / "eval_depression" / "table3.json").read_text())
    assert depression["pairs_per_d_el_deg"]["seen"] == {"+13": 2}
    assert depression["outside_trained_range"]["lambda=0"]["trained_d_el_deg"] == [0.0, 0.0]
    rows = ("| lambda=0 | seen |", "| lambda=4 | unseen |")
    rows += ("| input copy (unturned, keeps identity) | seen |",)
    for row in (*rows, "| real target (ceiling) | seen |", "| VAE round trip (ceiling) | unseen |"):
        assert row in text
    assert "CPU quick-run numbers" in text and "## Speed against error" in text
    for name in ("views.png", "speed_error.png", "lambda_sweep.png"):
        assert (out / "eval" / name).stat().st_size > 0
    timings = json.loads((out / "timings.json").read_text())
    stages = {"simulate", "simclr", "finetune lambda=0", "finetune lambda=4", "evaluators", "evaluate"}
    assert stages | {"simulate depressions", "evaluate depressions"} <= set(timings)
    # the recipe's optional training settings reach every fine-tune
    for stage in ("base", "finetune_lambda0", "finetune_lambda4"):
        settings = json.loads((out / stage / "config.json").read_text())
        assert (settings["lr_scheduler"], settings["lr_warmup_steps"]) == ("cosine", 1)
        assert (settings["use_ema"], settings["ema_decay"]) == (True, 0.9)
        assert settings["train_image_encoder"]
        assert settings["snr_gamma"] == 5.0
        # the prediction type is the base model's; the fine-tunes inherit it from its scheduler
        assert settings["prediction_type"] == ("v_prediction" if stage == "base" else None)
        scheduler = json.loads((out / stage / "pipeline" / "scheduler" / "scheduler_config.json").read_text())
        assert scheduler["prediction_type"] == "v_prediction"
    metrics = json.loads((out / "evaluators" / "metrics.json").read_text())
    assert set(metrics["models"]) == {"classifier", "regressor", "depression_regressor", "probe:simclr"}
    assert metrics["class_names"] == ["APC", "TANK", "TRUCK"]  # the held-out TRUCK included
    assert all(t["seconds"] > 0 and t["ran"] for t in timings.values())
    # The same command again is refused (the run would be overwritten); --resume finds it finished.
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match=r"already holds a finished quickstart run.*\(--resume\)"):
        quickstart.main(["--output_dir", str(out), "--recipe", "smoke"])
    quickstart.main(["--output_dir", str(out), "--recipe", "smoke", "--resume"])
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before
    # Another protocol, seed or recipe value in the same folder is refused before any stage, each named:
    # its stages would be reused and the report would describe settings that did not make them.
    for flags, words in ((["--protocol", "ood-APC"], "protocol: folder None, this run 'ood-APC'"),
                         (["--seed", "3"], "seed: folder 0, this run 3"),
                         (["--set", "base.max_train_steps=5"],
                          "recipe.base.max_train_steps: folder 2, this run 5"),
                         ):  # fmt: skip
        with pytest.raises(ValueError, match=words):
            quickstart.main(["--output_dir", str(out), "--recipe", "smoke", "--resume", *flags])
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before
    # A lambda sweep in the same folder trains only the new fine-tune, then evaluates all three (the old
    # evaluations are moved aside); every stage keeps its recorded time.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = quickstart.main(
            ["--output_dir", str(out), "--recipe", "smoke", "--lambdas", "0", "4", "1", "--resume"]
        )
    text = report.read_text()
    timings = json.loads((out / "timings.json").read_text())
    evaluated = {"finetune lambda=1", "evaluate", "evaluate depressions"}
    assert {name for name, t in timings.items() if t["ran"]} == evaluated
    assert all(t["seconds"] > 0 for t in timings.values())
    assert "| lambda=1 | unseen |" in text and "(input | lambda=0 | lambda=4 | lambda=1 | target)" in text
    assert len(list(out.glob("eval.replaced-*"))) == 1


def test_quickstart_config_checks_data_and_protocol(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="data: expected a chip folder"):
        quickstart.QuickstartConfig(data=str(tmp_path / "missing"), protocol="ood-T72")
    with pytest.raises(ValueError, match="protocol: give 'extended' or 'ood-<CLASS>' with --data"):
        quickstart.QuickstartConfig(data=str(tmp_path))
    with pytest.raises(ValueError, match="protocol"):
        quickstart.QuickstartConfig(protocol="soc-T72")
    with pytest.raises(ValueError, match="evaluates 'extended' or 'ood-<CLASS>', got 'soc'"):
        quickstart.QuickstartConfig(data=str(tmp_path), protocol="soc")
    with pytest.raises(ValueError, match="lambdas must be distinct values >= 0"):
        quickstart.QuickstartConfig(lambdas=[0.0, 0.0])
    assert set(quickstart.RECIPES) == {"default", "scratch", "long", "mstar", "mstar-prior", "smoke", "proxy",
                                       "rehearsal", "gentle"}  # fmt: skip


def test_the_default_recipe_plans_the_settings_each_stage_ran_with_before_recipes_had_sections() -> None:
    """Every stage of the quickstart with no options gets the values it got from the 52-field preset (the
    plans recorded before recipes became sections of stage fields, in tests/data)."""
    import sar_zero123

    package = str(Path(sar_zero123.__file__).resolve().parent)
    recorded = json.loads((Path(__file__).parents[1] / "data" / "quickstart_default_plan.json").read_text())
    plans = quickstart.plan_stages(quickstart.QuickstartConfig(output_dir="runs/quickstart"))
    planned = {
        plan.name: {"class": type(plan.config).__name__,
                    "config": json.loads(json.dumps(config_to_dict(plan.config)).replace(package, "<pkg>"))}
        for plan in plans
    }  # fmt: skip
    assert sorted(planned) == sorted(recorded)
    for name, plan in planned.items():
        before = recorded[name]["config"]
        config_class = type(next(p.config for p in plans if p.name == name))
        gone = {field: value for field, value in before.items() if field not in plan["config"]}
        # a field removed since then was planned at the default its removal keeps as a constant
        defaults = {field: removed_fields(config_class)[field].default for field in gone}
        assert gone == json.loads(json.dumps(defaults)), name
        kept = {field: value for field, value in before.items() if field not in gone}
        # a field added since then is planned at its default, which computes what ran before it existed
        added = {field: value for field, value in plan["config"].items() if field not in before}
        field_defaults = {f.name: f.default for f in dataclasses.fields(config_class)}
        assert added == {field: field_defaults[field] for field in added}, name
        assert added.keys() <= {"proxy_geometry"}, name
        plan = {**plan, "config": {k: v for k, v in plan["config"].items() if k not in added}}
        assert plan == {"class": recorded[name]["class"], "config": kept}, name


def test_set_items_replace_recipe_fields_with_typed_values() -> None:
    default = quickstart.RECIPES["default"]
    recipe = quickstart.apply_overrides(
        default,
        ["base.max_train_steps=4321", "finetune.lr_scheduler=cosine", "vae.block_out_channels=[8, 16, 32]",
         "finetune.ema_decay=0.999", "finetune.learning_rate=1", "simulate.classes=APC,TANK"],
    )  # fmt: skip
    assert recipe.value("base", "max_train_steps") == 4321
    assert recipe.value("vae", "block_out_channels") == (8, 16, 32)
    assert recipe.value("finetune", "ema_decay") == 0.999
    assert recipe.value("simulate", "classes") == ["APC", "TANK"]
    rate = recipe.value("finetune", "learning_rate")
    assert rate == 1.0 and isinstance(rate, float)
    assert recipe.value("base", "lr_scheduler") == "cosine"  # the base model is a fine-tune of lambda 0
    assert quickstart.RECIPES["default"] == default  # the recipe itself is unchanged
    for item, message in [
        ("nope=1", "expected SECTION.FIELD=VALUE"),
        ("base.max_train_steps", "expected SECTION.FIELD=VALUE"),
        ("base.max_train_steps=1.5", "not a value of base.max_train_steps"),
        ("base.estimate_input_azimuth=1", "not a value of base.estimate_input_azimuth"),
        ("vae.base_steps=3000", "vae.base_steps was removed: it is now base.max_train_steps"),
        ("shared.mixed_precision=fp8", "not a value of shared.mixed_precision"),
        ("base.prediction_type=sample", "not a value of base.prediction_type"),
        ("finetune.timestep_sampling=beta", "finetune.timestep_sampling was removed: logit-normal"),
        ("finetune.pfm_balance=auto", "finetune.pfm_balance was removed: rescaling PFM"),
    ]:
        with pytest.raises(ValueError, match=message):
            quickstart.apply_overrides(default, [item])
    with pytest.raises(ValueError, match="base.max_train_steps=many"):  # refused when the command is parsed
        quickstart.QuickstartConfig(set=["base.max_train_steps=many"])


def test_a_missing_prior_and_an_image_size_the_models_refuse_fail_before_any_stage() -> None:
    message = r"shared.image_size must be a multiple of 16 for the prior 'sar-zero123/sim-prior-rotated' "
    with pytest.raises(ValueError, match=message + r"\(VAE x UNet downsampling\), got 30"):
        quickstart.plan_stages(quickstart.QuickstartConfig(set=["shared.image_size=30"]))
    with pytest.raises(FileNotFoundError, match=r"shared.prior: '/nonexistent' is not a pipeline folder"):
        quickstart.QuickstartConfig(set=["shared.prior='/nonexistent'"])
    with pytest.raises(ValueError, match=r"multiple of 16 for base.size 'micro'"):
        quickstart.plan_stages(quickstart.QuickstartConfig(recipe="scratch", set=["shared.image_size=40"]))
    with pytest.raises(ValueError, match=r"the vae stage refuses .*norm_num_groups=12 must divide every"):
        quickstart.plan_stages(quickstart.QuickstartConfig(recipe="scratch", set=["vae.norm_num_groups=12"]))


def test_a_run_folder_of_the_old_recipe_fields_is_refused_naming_the_replacement(tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    record = {"format": 1, "stage": "quickstart", "config": {"recipe": "smoke", "preset.base_steps": 2,
              "preset.classes": ["TANK", "APC", "TRUCK"]}, "finished": True}  # fmt: skip
    (out / "run.json").write_text(json.dumps(record))
    words = (r"^output_dir: '.*run': a run of the old recipe fields \(preset.base_steps was removed: it is "
             r"now base.max_train_steps\); --restart moves it aside$")
    with pytest.raises(ValueError, match=words):
        quickstart.main(["--output_dir", str(out), "--recipe", "smoke", "--resume"])


@pytest.mark.slow
def test_quickstart_smoke_on_a_given_folder_with_the_extended_protocol(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    data = tmp_path / "chips"
    simulate_dataset(data, classes=("TANK", "APC"), instances=1, azimuth_step_deg=60.0, size=32, seed=0)
    out = tmp_path / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = quickstart.main(
            ["--output_dir", str(out), "--recipe", "smoke", "--data", str(data), "--protocol", "extended",
             "--set", "base.max_train_steps=3"]
        )  # fmt: skip
    text = report.read_text()
    assert f"real chips from `{data}`" in text and "Protocol `extended`" in text
    assert "| lambda=0 | seen |" in text and "| lambda=0 | unseen |" not in text
    assert "simulate" not in json.loads((out / "timings.json").read_text())
    assert not (out / "data").exists()
    assert json.loads((out / "recipe.json").read_text())["base"]["max_train_steps"] == 3
    assert json.loads((out / "base" / "train_state.json").read_text())["global_step"] == 3
    # Interrupted after step 2 of the base stage: the re-run resumes from checkpoint-2 (the recipe keeps the
    # last two) and exports the same weights as the uninterrupted run; every later stage is reused.
    base = out / "base"
    assert sorted(path.name for path in base.glob("checkpoint-*")) == ["checkpoint-2", "checkpoint-3"]
    weights = (base / "pipeline" / "unet" / "diffusion_pytorch_model.safetensors").read_bytes()
    shutil.rmtree(base / "pipeline")
    shutil.rmtree(base / "checkpoint-3")
    with warnings.catch_warnings(), caplog.at_level(logging.INFO):
        warnings.simplefilter("ignore")
        quickstart.main(
            ["--output_dir", str(out), "--recipe", "smoke", "--data", str(data), "--protocol", "extended",
             "--set", "base.max_train_steps=3", "--resume"]
        )  # fmt: skip
    assert "resumed from" in caplog.text and "checkpoint-2 at step 2" in caplog.text
    assert (base / "pipeline" / "unet" / "diffusion_pytorch_model.safetensors").read_bytes() == weights
    timings = json.loads((out / "timings.json").read_text())
    assert {name for name, t in timings.items() if t["ran"]} == {"base model"}


def test_a_seed_whose_validation_split_misses_the_simulated_grid_is_refused_first(tmp_path: Path) -> None:
    """`--recipe smoke --seed 1` would fail after simulation and SimCLR with an empty 'val' split."""
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=r"--seed 1 .* azimuth_step_deg=60: choose another --seed, or a fin"):
        quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", seed=1)
    assert not out.exists()
    finer = ["simulate.azimuth_step_deg=3"]
    quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", seed=1, set=finer)
    quickstart.QuickstartConfig(output_dir=str(out), recipe="smoke", seed=1, protocol="extended")
