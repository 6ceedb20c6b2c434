"""Paired comparisons of the protocol's arms: each classifier seed against the same seed of the arm it
adds views to (:func:`add_paired_gains`), and the arms as a Markdown table (:func:`format_table`)."""

from __future__ import annotations

import re
from typing import Any

import numpy as np

__all__ = ["add_paired_gains", "format_table", "paired_gain", "real_baseline", "seed_summary"]


def seed_summary(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """An arm's classifiers: accuracy mean and sample std over seeds, the per-seed records, CPU and wall s."""
    accuracies = np.array([s["test_accuracy"] for s in per_seed])
    return {
        "test_accuracy_mean": float(accuracies.mean()),
        "test_accuracy_std": float(accuracies.std(ddof=1)) if len(accuracies) > 1 else 0.0,
        "seeds": per_seed,
        "classifier_cpu_s": sum(s["cpu_s"] for s in per_seed),
        "classifier_wall_s": sum(s["wall_s"] for s in per_seed),
    }


def real_baseline(arm: str) -> str | None:
    """The real-only arm a generated arm adds views to: ``generated_k{K}...`` (the unseen-class variant too)
    -> ``real_k{K}``, ``generated_sector...`` -> ``real_sector``, ``eoc1_generated_{all,k{K}}...`` ->
    ``eoc1_real_{all,k{K}}``; None for a real arm."""
    match = re.match(r"(eoc1_)?generated_(k\d+|sector|all)", arm)
    return None if match is None else f"{match.group(1) or ''}real_{match.group(2)}"


def paired_gain(arm: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """Accuracy of `arm` minus `baseline`, seed by seed: both arms train their classifiers with the same
    seeds, so the difference removes the spread the seeds share. Per seed, mean and sample std (accuracy).

    Raises:
        ValueError: If the two arms share no seed.
    """
    base = {s["seed"]: s["test_accuracy"] for s in baseline["seeds"]}
    diffs = [s["test_accuracy"] - base[s["seed"]] for s in arm["seeds"] if s["seed"] in base]
    if not diffs:
        raise ValueError(f"arms {arm['arm']} and {baseline['arm']} share no classifier seed")
    values = np.asarray(diffs, dtype=np.float64)
    return {
        "against": baseline["arm"],
        "per_seed": diffs,
        "mean": float(values.mean()),
        "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
    }


def add_paired_gains(arms: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Adds ``gain_over_real`` to each generated arm (against its :func:`real_baseline`) and, to each arm
    whose same-azimuth control ran, ``gain_over_same_azimuth`` (what the requested pose adds), whose
    same-depression control (``..._d_el0``; for a ``..._depression{G}`` arm the unguided arm's) ran,
    ``gain_over_same_depression``; returns `arms`."""
    by_name = {arm["arm"]: arm for arm in arms}
    for arm in arms:
        baseline = real_baseline(arm["arm"])
        if baseline in by_name:
            arm["gain_over_real"] = paired_gain(arm, by_name[baseline])
        control = by_name.get(arm["arm"] + "_d_az0")
        if control is not None:
            arm["gain_over_same_azimuth"] = paired_gain(arm, control)
        # a depression-guided arm's control is the unguided one's (the guidance leaves d_el = 0 views as
        # they are)
        control = by_name.get(re.sub(r"_depression[0-9.e+-]+$", "", arm["arm"]) + "_d_el0")
        if control is not None:
            arm["gain_over_same_depression"] = paired_gain(arm, control)
    return arms


def format_table(summary: dict[str, Any]) -> str:
    """The arms as a Markdown table: accuracy (mean +- std over seeds, %), the paired gain over real-only
    (points), chips, times."""
    lines = [
        "| arm | real chips | generated views | test accuracy (%) | gain over real-only (points, paired) | "
        "seeds | generator CPU (min) | arm CPU (min) | arm wall (min) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for arm in summary["arms"]:
        generated = arm.get("n_generated", 0)
        gain = arm.get("gain_over_real")
        gain_text = "" if gain is None else f"{100 * gain['mean']:+.1f} +- {100 * gain['std']:.1f}"
        lines.append(
            f"| {arm['arm']} | {arm['n_train'] - generated} | {generated} | "
            f"{100 * arm['test_accuracy_mean']:.1f} +- {100 * arm['test_accuracy_std']:.1f} | {gain_text} | "
            f"{len(arm['seeds'])} | {arm.get('generator_cpu_s', 0.0) / 60:.1f} | "
            f"{arm['total_cpu_s'] / 60:.1f} | {arm['total_wall_s'] / 60:.1f} |"
        )
    return "\n".join(lines)
