"""The quickstart's ``report.md``, written only from what its stages left on disk.

Every number comes from a stage's files (``table3.json``/``.md``, ``metrics.json``, the stages' run records
for their wall time); the setup lines come from the run's record, which the run-folder rule keeps equal to
the settings that made the stages.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from sar_zero123.model.sampler import describe_sampler
from sar_zero123.stages.presets import QuickstartConfig, Recipe

__all__ = ["write_report"]


def write_report(
    out: Path, recipe: Recipe, config: QuickstartConfig, held_out: str | None, timings: dict[str, Any]
) -> Path:
    """`report.md`: setup, evaluator quality, Table III, Table IV, speed/error, figures, timings.

    Args:
        timings: Per stage, ``{"seconds": wall time in all sessions (its run record), "ran": whether this
            session did work in it}``.
    """
    eval_dir = out / "eval"
    table3 = json.loads((eval_dir / "table3.json").read_text())
    evaluator_metrics = json.loads((out / "evaluators" / "metrics.json").read_text())["models"]
    lines = _setup_lines(recipe, config, held_out, timings)
    lines += _evaluator_lines(evaluator_metrics)
    lines += _table_lines(eval_dir, table3)
    lines += _speed_lines(eval_dir)
    lines += _view_lines(eval_dir, config.lambdas)
    lines += _depression_lines(out / "eval_depression", recipe.shared.depression_targets_deg)
    lines += _timing_lines(timings)
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    return report


def _data_sentence(recipe: Recipe, config: QuickstartConfig) -> str:
    """The setup's data sentence: the simulated classes and grid, or the given folder."""
    size = recipe.shared.image_size
    if config.data is None:
        classes, instances = recipe.value("simulate", "classes"), recipe.value("simulate", "instances")
        return (
            f"Data: simulator classes {list(classes)} ({instances} object each, azimuth step "
            f"{recipe.value('simulate', 'azimuth_step_deg'):g} deg, 15 and 17 deg depression, {size} px). "
        )
    return f"Data: `{config.data}`, {size} px centre crops. "


def _protocol_sentence(held_out: str | None) -> str:
    """The setup's protocol sentence: `extended` (no held-out class) or `ood-<class>`."""
    if held_out is None:
        return (
            "Protocol `extended`: the model trains on the 17 deg chips of every class and is evaluated on "
            "pairs of 15 deg test views (seen classes only). "
        )
    return (
        f"Protocol `ood-{held_out}`: {held_out} is never seen in SimCLR or fine-tuning; evaluation pairs "
        "are half seen (15 deg test views of the other classes) and half unseen (all views of the "
        "held-out class). "
    )


def _starting_model(recipe: Recipe) -> str:
    """What the fine-tunes start from: a base model trained from scratch, or the pretrained prior."""
    prior = recipe.shared.prior
    if prior is None:
        size, steps = recipe.value("base", "size"), recipe.value("base", "max_train_steps")
        return f"a `{size}` model trained from scratch for {steps} steps (lambda 0)"
    return f"the pretrained multi-view prior `{prior}` (procedural simulated vehicles)"


def _setup_lines(
    recipe: Recipe, config: QuickstartConfig, held_out: str | None, timings: dict[str, Any]
) -> list[str]:
    """The title and the setup paragraphs: recipe, seed, device, total stage time, data and protocol."""
    device = "CUDA " + torch.cuda.get_device_name() if torch.cuda.is_available() else "CPU"
    total = sum(t["seconds"] for t in timings.values())
    data_kind = "simulated data" if config.data is None else f"real chips from `{config.data}`"
    data_line = _data_sentence(recipe, config)
    protocol_line = _protocol_sentence(held_out)
    start = _starting_model(recipe)
    return [
        "# sar_zero123 quickstart report",
        "",
        f"Recipe `{config.recipe}`, seed {config.seed}, device {device} ({torch.get_num_threads()} threads), "
        f"{total / 60:.1f} min of stage time in all. **CPU quick-run numbers on {data_kind}**: {start}, "
        f"then fine-tuned for {recipe.value('finetune', 'max_train_steps')} steps with each lambda (PFM on "
        f"{recipe.value('finetune', 'pfm_fraction'):g} of the eligible samples, features projected to "
        f"{recipe.value('finetune', 'pfm_projection_dim')} dimensions as the authors "
        "did), not the paper's zero-1-to-3 fine-tune (Objaverse initialisation, 20,000 iterations, real "
        "MSTAR); compare the rows with each other, not with the paper.",
        "",
        data_line
        + protocol_line
        + "The evaluators are trained on the 17 deg chips of all classes, as in the paper.",
        "",
    ]


def _evaluator_lines(evaluator_metrics: dict[str, Any]) -> list[str]:
    """The evaluators' section: test accuracy, test azimuth error and chip counts per model."""
    lines = [
        "## Evaluators (test split, 15 deg)",
        "",
        "| Model | Test accuracy (%) | Test azimuth error (deg) | train / test chips |",
        "| --- | --- | --- | --- |",
    ]
    for name, values in evaluator_metrics.items():
        accuracy = values.get("test_accuracy")
        error = values.get("test_azimuth_error_deg")
        lines.append(
            f"| {name} | {'-' if accuracy is None else f'{100 * accuracy:.1f}'} | "
            f"{'-' if error is None else f'{error:.1f}'} | {values.get('n_train')} / {values.get('n_test')} |"
        )
    return lines


def _table_lines(eval_dir: Path, table3: dict[str, Any]) -> list[str]:
    """The Table III and Table IV sections, from the evaluation stage's Markdown tables."""
    sampler = describe_sampler(table3)
    return [
        "",
        f"## Table III ({sampler})",
        "",
        "`input copy (unturned, keeps identity)` returns the input view unchanged (a generator that "
        "ignores the pose: every class kept, nothing turned, the azimuth floor); "
        "`real target (ceiling)` scores the true target view and `VAE round trip (ceiling)` the target "
        "encoded and decoded by the VAE, the best a latent model with this VAE can do. A model must beat the "
        "floor on azimuth error; `Az. gap closed` is the fraction of the floor-to-VAE-ceiling gap it closes. "
        "`Template az. err.` reads each view's azimuth off its vehicle's other chips at the requested "
        "depression (the best-correlating chip's azimuth, the target itself left out: the real target reads "
        "its nearest neighbour's), which a footprint turned in place cannot fool; `Front/back right` counts "
        "the readings within 90 deg of the request.",
        "",
        (eval_dir / "table3.md").read_text(),
        "## Table IV (azimuth error of generated views under each evaluator backbone)",
        "",
        (eval_dir / "table4.md").read_text(),
    ]


def _speed_lines(eval_dir: Path) -> list[str]:
    """The speed-against-error section, if the evaluation stage swept step counts."""
    if not (eval_dir / "speed_error.md").is_file():
        return []
    return ["## Speed against error", "", (eval_dir / "speed_error.md").read_text(),
            "![speed and error](eval/speed_error.png)", ""]  # fmt: skip


def _view_lines(eval_dir: Path, lambdas: list[float]) -> list[str]:
    """The generated-views figure (one column per lambda) and, if drawn, the metrics-against-lambda one."""
    columns = " | ".join(f"lambda={weight:g}" for weight in lambdas)
    lines = [f"## Generated views (input | {columns} | target)", "", "![views](eval/views.png)", ""]
    if (eval_dir / "lambda_sweep.png").is_file():
        lines += ["## Metrics against lambda", "", "![lambda](eval/lambda_sweep.png)", ""]
    return lines


def _depression_lines(depression_dir: Path, depression_targets_deg: tuple[float, ...]) -> list[str]:
    """The depression-change section, if that evaluation ran; it warns of models never trained on it."""
    if not (depression_dir / "table3.md").is_file():
        return []
    targets = ", ".join(f"{d:g}" for d in depression_targets_deg)
    depression_table3 = json.loads((depression_dir / "table3.json").read_text())
    lifted = depression_table3.get("outside_trained_range", {})
    guidance = depression_table3.get("depression_guidance_scale") or 0.0
    guided = (
        f"Sampled as Table III, with depression guidance {guidance:g} (each step pushed away from the same "
        "request at the input's depression). "
        if guidance
        else ""
    )
    outside = [
        name
        for name, ranges in lifted.items()
        if not all(
            ranges["trained_d_el_deg"][0] <= d - 17.0 <= ranges["trained_d_el_deg"][1]
            for d in depression_targets_deg
        )
    ]
    warning = (
        f"**{', '.join(outside)} never trained on these depression changes** (trained d_el range "
        f"{lifted[outside[0]]['trained_d_el_deg']} deg): a pipeline refuses such requests; they are "
        "scored here only to measure it. "
        if outside
        else ""
    )
    return [
        f"## Depression changes (17 deg inputs, targets at {targets} deg)",
        "",
        "The same models asked for a depression change (and the pair's azimuth change) on simulated "
        f"views of the same vehicles at {targets} deg. `Dep. err.` is the depression regressor's error "
        "on the generated view against the requested depression; `Closer to target dep.` the share of "
        "pairs whose blurred view correlates better with the true view at the requested depression than "
        "with the true view at the input's depression (same target azimuth). " + guided + warning,
        "",
        (depression_dir / "table3.md").read_text(),
        "![depression views](eval_depression/views.png)",
        "",
    ]


def _timing_lines(timings: dict[str, Any]) -> list[str]:
    """The stage-timings table, from each stage's run record."""
    lines = ["## Stage timings (from each stage's run record)", "",
             "| Stage | seconds | ran in this session |", "| --- | --- | --- |"]  # fmt: skip
    lines += [
        f"| {name} | {t['seconds']:.1f} | {'yes' if t['ran'] else 'no (finished before)'} |"
        for name, t in timings.items()
    ]
    return lines
