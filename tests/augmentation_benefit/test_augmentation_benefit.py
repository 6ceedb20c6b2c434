"""``python -m sar_zero123.augmentation_benefit`` on a tiny simulated dataset and the tiny pipeline."""

from __future__ import annotations

import json

import pytest
import torch

from sar_zero123 import SARZero123Pipeline
from sar_zero123.augmentation_benefit import (
    AugmentationBenefitConfig,
    add_paired_gains,
    check_settings,
    paired_gain,
    real_baseline,
)
from sar_zero123.augmentation_benefit.__main__ import main
from sar_zero123.augmentation_benefit.generators import fill_offsets_deg
from sar_zero123.config import field_comments
from sar_zero123.data import SCALING_FILE, ChipRecord, DecibelScaling, load_index
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.sim import simulate_dataset


def record(target_class: str, azimuth_deg: float) -> ChipRecord:
    return ChipRecord(
        path=f"/x/{target_class}_{azimuth_deg}.npy", target_class=target_class, target_type="t", serial="s",
        depression_deg=17.0, azimuth_deg=azimuth_deg, height=64, width=64,
    )  # fmt: skip


def tiny_pipeline(tmp_path) -> str:
    """The tiny random pipeline, saved with the unit-magnitude scaling, as every generator's start."""
    torch.manual_seed(0)
    pipe = build_sar_zero123("tiny", input_depression=True, estimate_input_azimuth=True)
    pipe.save_pretrained(tmp_path / "pipeline")
    scaling = DecibelScaling.for_unit_magnitude().to_dict()
    (tmp_path / "pipeline" / SCALING_FILE).write_text(json.dumps(scaling))
    return str(tmp_path / "pipeline")


def test_fill_offsets_place_views_evenly_from_the_nearer_chip():
    assert fill_offsets_deg(30.0, 3) == [7.5, 15.0, -7.5]
    assert fill_offsets_deg(7.5, 1) == [3.75]


def test_config_refuses_bad_fields():
    with pytest.raises(ValueError, match="ks"):
        AugmentationBenefitConfig(ks=[1])
    with pytest.raises(ValueError, match="views_per_chip"):
        AugmentationBenefitConfig(views_per_chip=0)
    with pytest.raises(ValueError, match="strength"):
        AugmentationBenefitConfig(strength=1.0)
    with pytest.raises(ValueError, match="eoc1_ks must hold values >= 2"):
        AugmentationBenefitConfig(eoc1_ks=[1])
    with pytest.raises(ValueError, match="rehearsal_data: the EOC-1 arms ask for views at another"):
        AugmentationBenefitConfig(eoc1_data="eoc1")
    with pytest.raises(ValueError, match="rehearsal_data"):
        AugmentationBenefitConfig(eoc1_data="eoc1", rehearsal_data="corpus", rehearsal_fraction=0.0)


def test_main_runs_every_arm_and_skips_finished_ones(tmp_path):
    data = simulate_dataset(tmp_path / "data", classes=("TANK", "APC"), instances=1, azimuth_step_deg=45,
                            depressions_deg=(15.0, 17.0), size=32)  # fmt: skip
    args = ["--data", str(data), "--out", str(tmp_path / "out"), "--pipeline", tiny_pipeline(tmp_path),
            "--ks", "4", "--seeds", "0", "1", "--image_size", "32", "--finetune_steps", "2",
            "--finetune_batch_size", "2", "--num_inference_steps", "2", "--classifier_steps", "3",
            "--classifier_batch_size", "4", "--quality_chips_per_class", "2", "--views_per_chip", "1",
            "--sector_deg", "180", "--unseen_class", "TANK", "--unseen_k", "4"]  # fmt: skip
    summary = main(args)
    arms = {arm["arm"]: arm for arm in summary["arms"]}
    assert list(arms) == ["all_chips", "real_k4", "generated_k4", "real_sector", "generated_sector",
                          "generated_k4_unseen_TANK"]  # fmt: skip
    assert arms["all_chips"]["n_train"] == 16 and arms["all_chips"]["n_test"] == 16
    assert arms["real_k4"]["n_train"] == 8
    # one view per kept chip, at +45 deg (gap 90 deg)
    assert arms["generated_k4"]["n_generated"] == 8 and arms["generated_k4"]["n_train"] == 16
    assert arms["generated_k4"]["d_az_deg"] == [45.0]
    assert arms["real_sector"]["n_train"] == 8 and arms["generated_sector"]["n_generated"] == 8
    assert arms["generated_k4_unseen_TANK"]["n_generated"] == 8
    # each generated arm carries its seed-by-seed gain over the real-only arm it adds views to
    gain = arms["generated_k4"]["gain_over_real"]
    assert gain["against"] == "real_k4" and len(gain["per_seed"]) == 2
    difference = arms["generated_k4"]["test_accuracy_mean"] - arms["real_k4"]["test_accuracy_mean"]
    assert gain["mean"] == pytest.approx(difference)
    assert arms["generated_k4_unseen_TANK"]["gain_over_real"]["against"] == "real_k4"
    assert arms["generated_sector"]["gain_over_real"]["against"] == "real_sector"
    for arm in arms.values():
        assert len(arm["seeds"]) == 2 and 0.0 <= arm["test_accuracy_mean"] <= 1.0
        assert arm["total_cpu_s"] >= arm["classifier_cpu_s"] > 0.0
    quality = arms["generated_k4"]["view_quality"]
    assert quality["n_views"] == 8 and quality["n_round_trip"] == 4
    assert 0.0 <= quality["vae_round_trip_accuracy"] <= 1.0
    # the generator of the unseen variant was trained on APC chips only
    rows = (tmp_path / "out" / "generator_k4_without_TANK" / "data" / "index.csv").read_text().splitlines()
    assert {row.split(",")[1] for row in rows[1:]} == {"APC"}
    # a second run finds every arm finished and retrains nothing
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "out").glob("*/result.json")}
    again = main(args)
    accuracies = [arm["test_accuracy_mean"] for arm in summary["arms"]]
    assert [arm["test_accuracy_mean"] for arm in again["arms"]] == accuracies
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    # more K is a resume; other classifier settings are another benchmark
    with pytest.raises(ValueError, match="classifier_steps: 3 -> 4"):
        main([*args, "--classifier_steps", "4"])
    # starting the views from the kept chips (SDEdit) is more arms: the same fine-tune, its own views,
    # recorded in the views' options
    finetuned = tmp_path / "out" / "generator_k4" / "finetune" / "pipeline"
    stamp = max(p.stat().st_mtime_ns for p in finetuned.rglob("*"))
    started = main([*args, "--strength", "0.5", "--same_azimuth_control"])
    started = {arm["arm"]: arm for arm in started["arms"]}
    assert list(started)[2:6] == ["generated_k4", "generated_k4_d_az0", "generated_k4_strength0.5",
                                  "generated_k4_strength0.5_d_az0"]  # fmt: skip
    # the control: the same start, at the kept chip's own azimuth
    assert started["generated_k4_strength0.5_d_az0"]["d_az_deg"] == [0.0]
    assert started["generated_k4_unseen_TANK_strength0.5"]["n_generated"] == 8
    # every plain arm gets the same variants: the missing sector's and the unseen class's too
    for plain in ("generated_sector", "generated_k4_unseen_TANK"):
        for suffix in ("_d_az0", "_strength0.5", "_strength0.5_d_az0"):
            assert started[plain + suffix]["generator"] == started[plain]["generator"]
    assert started["generated_sector_strength0.5_d_az0"]["d_az_deg"] == [0.0]
    assert started["generated_k4_d_az0"]["d_az_deg"] == [0.0]
    assert started["generated_k4"]["gain_over_same_azimuth"]["against"] == "generated_k4_d_az0"
    assert started["generated_sector_strength0.5"]["d_az_deg"] == [180.0]
    # heading guidance: the plain views again, sampled with the pull away from the flipped heading
    guided = {arm["arm"]: arm for arm in main([*args, "--heading_guidance", "2"])["arms"]}
    assert guided["generated_k4_heading2"]["generator"] == guided["generated_k4"]["generator"]
    assert guided["generated_sector_heading2"]["gain_over_real"]["against"] == "real_sector"
    # filtered views: the same views, fewer of them; validation accuracy on 17 deg chips outside the K
    filtered = {arm["arm"]: arm for arm in main([*args, "--view_filters", "confident", "ratio1"])["arms"]}
    confident = filtered["generated_k4_confident"]
    assert confident["view_filter"] == "confident" and confident["n_generated_before_filter"] == 8
    assert confident["n_generated"] <= 8 and confident["gain_over_real"]["against"] == "real_k4"
    assert filtered["generated_k4_ratio1"]["n_generated"] == 8  # views_per_chip 1: every view kept
    assert filtered["generated_k4_ratio1"]["generator"] == filtered["generated_k4"]["generator"]
    for name in ("real_k4", "generated_k4", "generated_k4_confident"):
        assert 0.0 <= filtered[name]["validation_accuracy_seed0"] <= 1.0
    assert "validation_accuracy_seed0" not in filtered["real_sector"]
    heading = json.loads((tmp_path / "out" / "generator_k4" / "views_heading2" / "augment.json").read_text())
    assert heading["heading_guidance_scale"] == 2.0
    pose = started["generated_k4_strength0.5"]["gain_over_same_azimuth"]
    assert pose["against"] == "generated_k4_strength0.5_d_az0"
    control = tmp_path / "out" / "generator_k4" / "views_strength0.5_d_az0" / "provenance.csv"
    assert {row.split(",")[-5] for row in control.read_text().splitlines()[1:]} == {"0.0"}
    views = tmp_path / "out" / "generator_k4" / "views_strength0.5"
    options = json.loads((views / "augment.json").read_text())
    assert options["strength"] == 0.5 and "speckle_looks" not in options
    assert max(p.stat().st_mtime_ns for p in finetuned.rglob("*")) == stamp


def arm(name: str, accuracies: list[float]) -> dict:
    return {"arm": name, "seeds": [{"seed": i, "test_accuracy": a} for i, a in enumerate(accuracies)]}


def test_real_baseline_names_the_arm_whose_chips_the_views_are_added_to():
    assert real_baseline("generated_k12") == "real_k12"
    assert real_baseline("eoc1_generated_all_d_el0") == "eoc1_real_all"
    assert real_baseline("eoc1_generated_k24") == "eoc1_real_k24" and real_baseline("eoc1_real_k24") is None
    assert real_baseline("generated_k12_strength0.5_d_az0") == "real_k12"
    assert real_baseline("generated_k12_unseen_T72_strength0.5") == "real_k12"
    assert real_baseline("generated_sector_speckle1") == "real_sector"
    assert real_baseline("real_k12") is None and real_baseline("all_chips") is None


def test_paired_gains_are_seed_by_seed_differences():
    arms = add_paired_gains([
        arm("real_k4", [0.5, 0.6, 0.4]), arm("generated_k4_strength0.5", [0.6, 0.6, 0.6]),
        arm("generated_k4_strength0.5_d_az0", [0.5, 0.7, 0.6]),
    ])  # fmt: skip
    gain = arms[1]["gain_over_real"]
    assert gain["against"] == "real_k4"
    assert gain["per_seed"] == pytest.approx([0.1, 0.0, 0.2])
    assert gain["mean"] == pytest.approx(0.1) and gain["std"] == pytest.approx(0.1)  # sample std
    pose = arms[1]["gain_over_same_azimuth"]
    assert pose["against"] == "generated_k4_strength0.5_d_az0"
    assert pose["per_seed"] == pytest.approx([0.1, -0.1, 0.0]) and pose["mean"] == pytest.approx(0.0)
    assert "gain_over_real" not in arms[0] and "gain_over_same_azimuth" not in arms[2]
    with pytest.raises(ValueError, match="share no classifier seed"):
        other_seed = {"arm": "real_k4", "seeds": [{"seed": 7, "test_accuracy": 0.1}]}
        paired_gain(arm("generated_k4", [0.5]), other_seed)


def test_check_settings_takes_a_missing_setting_as_its_default_and_names_a_changed_one(tmp_path):
    config = AugmentationBenefitConfig(data="d", out=str(tmp_path))
    check_settings(config, tmp_path)
    record = json.loads((tmp_path / "settings.json").read_text())
    assert record["finetune_steps"] == 3000 and "ks" not in record  # arm selection is not recorded
    # a folder written before a setting existed resumes when this run keeps that setting's default
    del record["max_shift_px"]
    (tmp_path / "settings.json").write_text(json.dumps(record))
    check_settings(config, tmp_path)
    with pytest.raises(ValueError, match=r"max_shift_px: 4 -> 2"):
        check_settings(AugmentationBenefitConfig(data="d", out=str(tmp_path), max_shift_px=2), tmp_path)
    with pytest.raises(ValueError, match=r"finetune_steps: 3000 -> 1000"):
        check_settings(AugmentationBenefitConfig(data="d", out=str(tmp_path), finetune_steps=1000), tmp_path)


def test_eoc1_arms_train_at_17_deg_test_at_the_other_depression_and_pair_with_their_controls(tmp_path):
    from sar_zero123.sim.corpus import write_prior_corpus

    data = simulate_dataset(tmp_path / "data", classes=("TANK", "APC", "TRUCK"), instances=1,
                            azimuth_step_deg=45, depressions_deg=(15.0, 17.0), size=32)  # fmt: skip
    eoc1 = simulate_dataset(tmp_path / "eoc1", classes=("TANK", "APC"), instances=1, azimuth_step_deg=45,
                            depressions_deg=(30.0,), size=32, seed=1)  # fmt: skip
    corpus = write_prior_corpus(tmp_path / "corpus", num_vehicles=4, views_per_vehicle=4,
                                num_validation_vehicles=1, size=32, progress=False)  # fmt: skip
    args = ["--data", str(data), "--out", str(tmp_path / "out"), "--pipeline", tiny_pipeline(tmp_path),
            "--ks", "--no-sectors", "--unseen_class", "none", "--eoc1_data", str(eoc1), "--eoc1_ks", "4",
            "--rehearsal_data", str(corpus), "--rehearsal_fraction", "0.5", "--seeds", "0", "1",
            "--image_size", "32", "--finetune_steps", "2", "--finetune_batch_size", "2",
            "--num_inference_steps", "2", "--classifier_steps", "2",
            "--classifier_batch_size", "4"]  # fmt: skip
    arms = {arm["arm"]: arm for arm in main(args)["arms"]}
    assert list(arms) == ["all_chips", "eoc1_ceiling_cv", "eoc1_real_all", "eoc1_generated_all",
                          "eoc1_generated_all_d_el0", "eoc1_real_k4", "eoc1_generated_k4",
                          "eoc1_generated_k4_d_el0"]  # fmt: skip
    # 17 deg chips of the two objects the 30 deg chips show (TRUCK left out); tested on every 30 deg chip
    assert arms["eoc1_real_all"]["n_train"] == 16 and arms["eoc1_real_all"]["n_test"] == 16
    assert arms["eoc1_real_k4"]["n_train"] == 8
    # one view per chip: at d_el = 30 - 17 deg, and the control at d_el = 0
    plain, control = arms["eoc1_generated_k4"], arms["eoc1_generated_k4_d_el0"]
    assert (plain["d_el_deg"], control["d_el_deg"]) == (13.0, 0.0)
    assert plain["n_generated"] == control["n_generated"] == 8 and plain["d_az_deg"] == [0.0]
    assert plain["gain_over_real"]["against"] == "eoc1_real_k4"
    assert plain["gain_over_same_depression"]["against"] == "eoc1_generated_k4_d_el0"
    assert "gain_over_same_depression" not in control
    views = load_index(tmp_path / "out" / "eoc1_generator_k4" / "views_d_az0_d_el13")
    assert {r.depression_deg for r in views} == {30.0}
    # the ceiling: two folds of the 30 deg chips, each scored by the classifier that did not see it
    ceiling = arms["eoc1_ceiling_cv"]
    assert [s["fold"] for s in ceiling["seeds"]] == [0, 1] and ceiling["n_test"] == 16
    assert sum(s["n_held_out"] for s in ceiling["seeds"]) == 16
    quality = plain["view_quality"]
    assert (quality["n_generated"], quality["n_source_17deg"], quality["n_held_out_test"]) == (8, 8, 8)
    assert 0.0 <= quality["generated_accuracy"] <= 1.0
    # every generator rehearsed the corpus: its trained depressions reach 30 deg
    generator = tmp_path / "out" / "eoc1_generator_all" / "finetune" / "pipeline"
    finetuned = SARZero123Pipeline.from_pretrained(generator)
    assert finetuned.pose_projection.config.trained_depression_deg[1] >= 30.0
    with pytest.raises(ValueError, match=r"eoc1_data: expected chips at one depression"):
        main([*args[:-2], "--classifier_batch_size", "4", "--eoc1_data", str(data)])
    # added to the same folder: views started from the chip and three views per chip, K arms only
    added = main([*args, "--no-eoc1_all", "--strength", "0.5", "--eoc1_views_per_chip", "3"])["arms"]
    new = ["eoc1_generated_k4_strength0.5", "eoc1_generated_k4_strength0.5_d_el0", "eoc1_generated_k4_views3",
           "eoc1_generated_k4_views3_d_el0", "eoc1_generated_k4_views3_strength0.5",
           "eoc1_generated_k4_views3_strength0.5_d_el0"]  # fmt: skip
    names = [arm["arm"] for arm in added]
    # this invocation's arms first (the finished ones read back), then the earlier ones: every arm once
    assert names[:4] == ["all_chips", "eoc1_ceiling_cv", "eoc1_real_k4", "eoc1_generated_k4"]
    assert sorted(names) == sorted([*arms, *new])
    arms = {arm["arm"]: arm for arm in added}
    three = arms["eoc1_generated_k4_views3"]
    assert three["d_az_deg"] == [0.0, 30.0, -30.0] and three["n_generated"] == 24  # K = 4: 90 deg gaps
    assert arms["eoc1_generated_k4_views3_d_el0"]["d_az_deg"] == [0.0, 30.0, -30.0]
    assert three["gain_over_same_depression"]["against"] == "eoc1_generated_k4_views3_d_el0"
    assert three["gain_over_real"]["against"] == "eoc1_real_k4"
    started = arms["eoc1_generated_k4_views3_strength0.5"]
    assert started["gain_over_same_depression"]["against"] == "eoc1_generated_k4_views3_strength0.5_d_el0"
    out = tmp_path / "out" / "eoc1_generator_k4"
    assert len(load_index(out / "views_d_el13_views3")) == 24 and len(load_index(out / "views_views3")) == 24
    assert {r.depression_deg for r in load_index(out / "views_strength0.5_d_az0_d_el13")} == {30.0}
    # depression guidance: one more arm per view variant, paired with the plain control (the guidance leaves
    # d_el = 0 views unchanged), its views from the same generator with the guidance recorded
    guided = {arm["arm"]: arm for arm in main([*args, "--no-eoc1_all", "--depression_guidance", "2"])["arms"]}
    arm = guided["eoc1_generated_k4_depression2"]
    assert (arm["d_el_deg"], arm["n_generated"]) == (13.0, 8)
    assert arm["description"].endswith("at d_el = +13 deg, depression guidance 2")
    assert arm["gain_over_same_depression"]["against"] == "eoc1_generated_k4_d_el0"
    assert "eoc1_generated_k4_depression2_d_el0" not in guided
    record = json.loads((out / "views_depression2_d_az0_d_el13" / "augment.json").read_text())
    assert record["depression_guidance_scale"] == 2.0 and record["d_el"] == [13.0]


def test_help_gives_every_field_its_comment(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    comments = field_comments(AugmentationBenefitConfig)
    assert set(comments) == set(AugmentationBenefitConfig.__dataclass_fields__)  # every field has words
    assert "classifier seeds per arm" in text and "kept 17 deg chips per class" in text
