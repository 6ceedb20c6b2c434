"""Table III / IV as markdown, the speed/error table, and the figures of an evaluation (Fig. 7/8, Fig. 12).

The numbers come from :mod:`sar_zero123.evaluation.protocol`; this module only lays them out. Every
metric cell carries its standard error where one is known; the gap columns give the fraction of the
floor-to-ceiling gap a model closes (:func:`sar_zero123.evaluation.protocol.gap_closed`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from sar_zero123.evaluation.protocol import (
    BLUR_SIGMA_PX,
    INPUT_COPY,
    PAPER_TABLE3,
    REAL_TARGET,
    VAE_ROUND_TRIP,
    PairSet,
)

#: What separates a value from its standard error in every table cell (the plus-minus sign).
PLUS_MINUS = "\u00b1"

__all__ = [
    "DEPRESSION_METRICS",
    "GAP_LABELS",
    "METRICS",
    "METRIC_LABELS",
    "MIN_SPEED_PAIRS",
    "PLUS_MINUS",
    "plot_lambda_sweep",
    "plot_speed_error",
    "plot_views",
    "speed_markdown",
    "table3_markdown",
    "table4_markdown",
    "vae_round_trip_markdown",
]

# ms_ssim / kuan_ssim are paper-comparable (the authors' calls); the *_corrected columns sit beside them.
METRICS = (
    "accuracy",
    "azimuth_error_deg",
    "axis_error_deg",
    "sfd",
    "ms_ssim",
    "kuan_ssim",
    "ms_ssim_corrected",
    "kuan_ssim_corrected",
)
METRIC_LABELS = {
    "accuracy": "Acc. (%) ↑",
    "azimuth_error_deg": "Az. err. (deg) ↓",
    "axis_error_deg": "Axis err. (deg) ↓",
    "sfd": "SFD ↓",
    "ms_ssim": "MS-SSIM ↑",
    "kuan_ssim": "Kuan+SSIM ↑",
    "ms_ssim_corrected": "MS-SSIM corr. ↑",
    "kuan_ssim_corrected": "Kuan+SSIM corr. ↑",
    "depression_error_deg": "Dep. err. (deg) ↓",
    "depression_overshoot_deg": "Dep. overshoot (deg)",
    "closer_to_target_depression": "Closer to target dep. ↑",
    "template_azimuth_error_deg": "Template az. err. (deg) ↓",
    "front_back_right": "Front/back right (%) ↑",
    "turned_and_kept": "Turned and kept (%) ↑",
}
# columns only pairs with a depression change (and a depression regressor, for the error) give
DEPRESSION_METRICS = ("depression_error_deg", "depression_overshoot_deg", "closer_to_target_depression")
# columns of the template reading (the view against its vehicle's other chips), where the pairs have one
TEMPLATE_METRICS = ("template_azimuth_error_deg", "front_back_right", "turned_and_kept")
GAP_LABELS = {
    "azimuth_gap_closed": "Az. gap closed ↑",
    "accuracy_gap_closed": "Acc. gap closed ↑",
    "depression_gap_closed": "Dep. gap closed ↑",
    "template_gap_closed": "Template gap closed ↑",
}


def _format(metric: str, value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if metric in ("accuracy", "front_back_right", "template_azimuth_error_deg", "turned_and_kept"):
        return f"{value:.1f}"
    if metric in ("azimuth_error_deg", "axis_error_deg", "depression_error_deg", "depression_overshoot_deg"):
        return f"{value:.1f}"
    if metric in ("sfd", "closer_to_target_depression"):
        return f"{value:.2f}"
    return f"{value:.4f}"


def _cell(metric: str, values: dict[str, float]) -> str:
    """A metric with its standard error when known (``<value> PLUS_MINUS <se>``)."""
    text = _format(metric, values.get(metric))
    se = values.get(f"{metric}_se")
    if text == "-" or se is None or math.isnan(se):
        return text
    return f"{text} {PLUS_MINUS} {_format(metric, se)}"


def _fraction(value: float | None) -> str:
    if value is None:
        return ""
    return "no gap" if math.isnan(value) else f"{100 * value:.0f} %"


def table3_markdown(results: dict[str, dict[str, dict[str, float]]], include_paper: bool) -> str:
    """Markdown Table III: one row per (method, group), the paper's rows first when `include_paper`.

    Metrics carry their standard error (after :data:`PLUS_MINUS`); the gap columns give the fraction of the
    gap between the input copy (unturned, keeps identity) and the VAE round trip (ceiling) that each model
    closes. The depression columns appear when some row has them (a depression regressor, d_el != 0 pairs).
    """
    present = {key for groups in results.values() for values in groups.values() for key in values}
    metrics = [*METRICS, *(m for m in (*TEMPLATE_METRICS, *DEPRESSION_METRICS) if m in present)]
    optional_gaps = {
        "depression_gap_closed": "depression_error_deg",
        "template_gap_closed": "template_azimuth_error_deg",
    }
    gaps = [key for key in GAP_LABELS if key not in optional_gaps or optional_gaps[key] in present]
    labels = [METRIC_LABELS[m] for m in metrics] + [GAP_LABELS[key] for key in gaps]
    header = "| Method | Views | " + " | ".join(labels) + " | n |"
    lines = [header, "|" + " --- |" * (len(labels) + 3)]
    rows = dict(PAPER_TABLE3) if include_paper else {}
    rows.update(results)
    for method, groups in rows.items():
        for group, values in groups.items():
            n = values.get("n")
            cells = " | ".join(_cell(m, values) for m in metrics)
            fractions = " | ".join(_fraction(values.get(key)) for key in gaps)
            lines.append(f"| {method} | {group} | {cells} | {fractions} | {'' if n is None else int(n)} |")
    lines.append("")
    lines.append(
        f"Floor: `{INPUT_COPY}` returns the input view (a generator that ignores the pose). Ceilings: "
        f"`{REAL_TARGET}` scores the true target view, `{VAE_ROUND_TRIP}` the target encoded and decoded by "
        'the pipeline\'s VAE. Gap closed = (floor - model) / (floor - VAE round trip); "no gap" where '
        "the floor scores at least as well as the ceiling, or within one standard error of their difference "
        f"(accuracy: the input copy keeps the class). {PLUS_MINUS} is one standard error of the mean over "
        "the n pairs."
    )
    lines.append(
        "MS-SSIM and Kuan+SSIM are paper-comparable (`sar_zero123.evaluation.paper_metrics`, the authors' "
        "calls: 8-bit views resized to 256 px, centre 64 crop; torchmetrics MS-SSIM with its 9x9 window, "
        "findpeaks Kuan filter then scikit-image SSIM); the `corr.` columns are the corrected variants "
        "(`sar_zero123.evaluation.metrics`: true 7x7 Gaussian windows, centred 7x7 Kuan filter, generated "
        "resolution); SFD: Frechet distance of the azimuth regressor's pooled features at the n shown."
    )
    if "depression_error_deg" in present:
        lines.append(
            "Dep. err.: |depression regressor's prediction on the view - the target's true depression|."
        )
    if "depression_overshoot_deg" in present:
        lines.append(
            "Dep. overshoot: the same difference signed along the request, (prediction - target) x "
            "sign(target - input depression), over the pairs with d_el != 0: > 0 past the requested "
            "depression, < 0 short of it (-|d_el| stays at the input's)."
        )
    if "closer_to_target_depression" in present:
        lines.append(
            "Closer to target dep.: fraction of the pairs with d_el != 0 whose view, blurred (Gaussian, "
            f"sigma {BLUR_SIGMA_PX:g} px) like both truths, correlates more with the true target view than "
            "with the true view at the target azimuth but the input's depression (a model that ignores "
            "d_el returns the latter); counted over the pairs where that view exists "
            "(`closer_to_target_depression_n` in table3.json)."
        )
    return "\n".join(lines) + "\n"


def table4_markdown(results: dict[str, dict[str, dict[str, float]]]) -> str:
    """Markdown Table IV: azimuth error of generated views under every evaluator backbone."""
    backbones = sorted(
        {
            key.split("/", 1)[1]
            for groups in results.values()
            for v in groups.values()
            for key in v
            if "/" in key
        },
        key=lambda name: (name != "scratch", name),
    )
    lines = ["| Method | Views | " + " | ".join(f"Az. err. (deg), {b}" for b in backbones) + " |"]
    lines.append("|" + " --- |" * (len(backbones) + 2))
    for method, groups in results.items():
        for group, values in groups.items():
            cells = " | ".join(
                _format("azimuth_error_deg", values.get(f"azimuth_error_deg/{b}")) for b in backbones
            )
            lines.append(f"| {method} | {group} | {cells} |")
    return "\n".join(lines) + "\n"


def plot_views(
    pair_sets: dict[str, PairSet], generated: dict[str, dict[str, torch.Tensor]], count: int, path: Path
) -> Path:
    """Fig. 7/8-like grid: rows are pairs, columns input | each pipeline | target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(generated)
    rows = [(group, i) for group, pairs in pair_sets.items() for i in range(min(count, len(pairs)))]
    columns = ["input", *names, "target"]
    figure, axes = plt.subplots(
        len(rows), len(columns), figsize=(1.6 * len(columns), 1.6 * len(rows)), squeeze=False
    )
    for row, (group, i) in enumerate(rows):
        pairs = pair_sets[group]
        images = [pairs.inputs[i], *(generated[name][group][i] for name in names), pairs.targets[i]]
        for column, image in enumerate(images):
            axis = axes[row, column]
            axis.imshow(image[0].numpy(), cmap="gray", vmin=0.0, vmax=1.0)
            axis.set_xticks([])
            axis.set_yticks([])
            if row == 0:
                axis.set_title(columns[column], fontsize=8)
        label = f"{group}\nΔaz {pairs.d_az_deg[i]:.0f}°, Δel {pairs.d_el_deg[i]:.0f}°"
        axes[row, 0].set_ylabel(label, fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_lambda_sweep(
    results: dict[str, dict[str, dict[str, float]]], lambdas: dict[str, float], path: Path
) -> Path:
    """Fig. 12-like plot: each metric against the PFM weight lambda, one line per view group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(METRICS), figsize=(3.2 * len(METRICS), 3.0))
    order = sorted(lambdas, key=lambdas.get)
    groups = list(next(iter(results.values())))
    for axis, metric in zip(axes, METRICS):
        for group in groups:
            axis.plot(
                [lambdas[m] for m in order], [results[m][group][metric] for m in order], "o-", label=group
            )
        axis.set_xlabel("λ (PFM weight)")
        axis.set_title(METRIC_LABELS[metric], fontsize=9)
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


#: Pairs per row below which a speed/error table is labelled indicative (its errors' standard errors are
#: too wide to order the samplers).
MIN_SPEED_PAIRS = 256


def plot_speed_error(rows: list[dict[str, Any]], path: Path) -> Path:
    """Azimuth error and accuracy against images/s (one standard error as bars), one line per (pipeline,
    scheduler), points labelled by steps; rows on the speed/azimuth-error Pareto front (``row["pareto"]``)
    ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(9.0, 3.6))
    lines: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        lines.setdefault((row["pipeline"], row["scheduler"]), []).append(row)
    for (pipeline, scheduler), points in lines.items():
        points = sorted(points, key=lambda r: r["images_per_s"])
        speed = [p["images_per_s"] for p in points]
        for axis, metric in zip(axes, ("azimuth_error_deg", "accuracy")):
            errors = [p.get(f"{metric}_se", 0.0) for p in points]
            axis.errorbar(speed, [p[metric] for p in points], yerr=errors, fmt="o-", capsize=2, markersize=3,
                          label=f"{pipeline} / {scheduler}")  # fmt: skip
            for p in points:
                axis.annotate(
                    str(p["steps"]),
                    (p["images_per_s"], p[metric]),
                    fontsize=7,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
    front = [r for r in rows if r.get("pareto")]
    if front:
        axes[0].scatter([r["images_per_s"] for r in front], [r["azimuth_error_deg"] for r in front], s=90,
                        facecolors="none", edgecolors="black", label="Pareto front")  # fmt: skip
    axes[0].set_ylabel("azimuth error (deg) ↓")
    axes[1].set_ylabel("accuracy (%) ↑")
    for axis in axes:
        axis.set_xlabel("images / s")
        axis.set_xscale("log")
        axis.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def speed_markdown(rows: list[dict[str, Any]], device: str, memory: str = "resident set size") -> str:
    """Markdown speed/error table: each error beside its standard error, UNet evaluations per image, peak
    memory, and the Pareto front of speed against azimuth error; labelled indicative below
    :data:`MIN_SPEED_PAIRS` pairs."""
    small = any(row["n"] < MIN_SPEED_PAIRS for row in rows)
    lines = [
        f"Device: {device}. Points use the seen pairs; images/s counts pipeline calls only; peak memory: "
        f"{memory}; front: on the Pareto front of images/s against azimuth error."
        + (f" **Indicative: fewer than {MIN_SPEED_PAIRS} pairs per row** (the standard errors overlap)."
           if small else "")
        + "\n",
        "| Pipeline | Scheduler | Steps | images/s | UNet evals / image | Az. err. (deg) ↓ | Acc. (%) ↑ | "
        "Peak mem. (MiB) | Front | n |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        evaluations = row.get("unet_evaluations_per_image")
        memory_mib = row.get("peak_memory_mib")
        lines.append(
            f"| {row['pipeline']} | {row['scheduler']} | {row['steps']} | {row['images_per_s']:.2f} | "
            f"{'-' if evaluations is None else f'{evaluations:.1f}'} | "
            f"{row['azimuth_error_deg']:.1f} {PLUS_MINUS} "
            f"{row.get('azimuth_error_deg_se', float('nan')):.1f} | "
            f"{row['accuracy']:.1f} {PLUS_MINUS} {row.get('accuracy_se', float('nan')):.1f} | "
            f"{'-' if memory_mib is None else f'{memory_mib:.0f}'} | {'yes' if row.get('pareto') else ''} | "
            f"{row['n']} |"
        )
    return "\n".join(lines) + "\n"


#: The columns of :func:`vae_round_trip_markdown`: metric key, title, digits.
VAE_ROUND_TRIP_COLUMNS = (
    ("accuracy", "Acc. (%)", 1), ("azimuth_error_deg", "Az. err. (deg)", 1), ("sfd", "SFD", 2),
    ("ms_ssim", "MS-SSIM", 4), ("kuan_ssim", "Kuan+SSIM", 4),
)  # fmt: skip


def vae_round_trip_markdown(rows: dict[str, dict[str, dict[str, float]]]) -> str:
    """One line per VAE (row) and pair group: each metric, its standard error where one is recorded, and n.

    Args:
        rows: Row name -> group (``seen``, ``unseen``) -> :func:`~sar_zero123.evaluation.protocol.score`'s
            metrics, with ``<metric>_se`` where known and ``n``.
    """
    columns = VAE_ROUND_TRIP_COLUMNS
    lines = ["| VAE | views | " + " | ".join(title for _, title, _ in columns) + " | n |",
             "| --- | --- |" + " --- |" * (len(columns) + 1)]  # fmt: skip
    for name, groups in rows.items():
        for group, values in groups.items():
            cells = []
            for key, _, digits in columns:
                se = values.get(f"{key}_se")
                cells.append(f"{values[key]:.{digits}f}" + (f" {PLUS_MINUS} {se:.{digits}f}" if se else ""))
            lines.append(f"| {name} | {group} | " + " | ".join(cells) + f" | {int(values['n'])} |")
    return "\n".join(lines) + "\n"
