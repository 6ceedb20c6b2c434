"""Gap closed against training minutes for several model sizes: which one learns fastest per CPU minute?

    python benchmarks/learning_curve.py --data RUN/data --vae RUN/vae/vae --evaluators RUN/evaluators \\
        --protocol ood-TANK --sizes micro compact small --chunk_steps 600 --max_steps 3000 \\
        --work_dir CURVES --out learning_curve.jsonl [--plot learning_curve.png]

For each size, the fine-tune stage (`sar_zero123.stages.finetune.run_finetune`) trains one lambda = 0 model
from scratch on the SAR-sized pose path (`estimate_input_azimuth`) in chunks of `--chunk_steps`: each chunk
resumes the previous chunk's checkpoint (at a constant learning rate, so the chunks train as one long call
would), validates (pose sensitivity and pose following, `sar_zero123.training.validation`) and exports its
pipeline; the evaluate stage (`sar_zero123.stages.evaluate.run_evaluate`) then scores that pipeline on the
same `--n` pairs (Table III with the input-copy floor and the VAE-round-trip ceiling). One JSON line per
(size, steps): cumulative training seconds (the finetune calls: training, checkpoint, validation and
export; evaluation excluded), UNet parameters, and the seen/unseen azimuth error, accuracy and gap closed
with standard errors. Lines already in `--out` are kept and skipped, so a
killed benchmark continues where it stopped (and a run whose points are all in `--out` only plots them).

A curve is one (size, learning rate, batch size): its run folder is ``WORK_DIR/<size>_lr<lr>_b<batch>``,
so invocations with another `--learning_rate` or `--train_batch_size` can share `--work_dir` and `--out`
without resuming each other's checkpoints; the plot names them apart.

The training seconds depend on the machine and on what shares it: compare sizes only from one invocation
(or from invocations run side by side under the same thread count).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from safetensors import safe_open

from sar_zero123.config import write_json_atomic
from sar_zero123.model.build import SAR_ZERO123_SIZES
from sar_zero123.stages.evaluate import EvaluateConfig, load_evaluation, run_evaluate
from sar_zero123.stages.finetune import FinetuneConfig, run_finetune

ROW_KEYS = ("azimuth_error_deg", "azimuth_error_deg_se", "azimuth_gap_closed", "accuracy", "accuracy_se")
VALIDATION_KEYS = ("sensitivity_pose_t500", "sensitivity_input_t500", "pose_following_error_deg")


def read_rows(path: Path) -> list[dict]:
    """The JSON lines already written to `path` (none when it does not exist)."""
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def last_validation(run_dir: Path) -> dict[str, float]:
    """The last validation record of a finetune run, keyed without the ``validation/`` prefix."""
    metrics = run_dir / "validation" / "metrics.jsonl"
    if not metrics.is_file():
        return {}
    record = json.loads(metrics.read_text().splitlines()[-1])
    return {key: record[f"validation/{key}"] for key in VALIDATION_KEYS if f"validation/{key}" in record}


def model_row(results: dict[str, dict]) -> dict[str, float]:
    """Seen/unseen azimuth error, accuracy and gap closed (with standard errors) of one Table III row
    (``{"seen": {...}, "unseen": {...}}`` of ``load_evaluation``'s ``table3``)."""
    row = {}
    for views, result in results.items():
        for key in ROW_KEYS:
            row[f"{views}/{key}"] = result[key]
    return row


def finetune_config(args: argparse.Namespace, size: str, steps: int, run_dir: Path) -> FinetuneConfig:
    """The fine-tune of one chunk: lambda = 0 up to `steps`, resuming the last chunk."""
    return FinetuneConfig(
        data=args.data, protocol=args.protocol, size=size, estimate_input_azimuth=True, pfm_weight=0.0,
        vae=args.vae, image_size=64, seed=args.seed, train_batch_size=args.train_batch_size,
        learning_rate=args.learning_rate, max_train_steps=steps, use_ema=False,
        checkpointing_steps=args.chunk_steps, checkpoints_total_limit=1, resume_from_checkpoint="latest",
        validation_steps=args.chunk_steps, num_validation_images=8, evaluators=args.evaluators,
        report_to=None, output_dir=str(run_dir),
    )  # fmt: skip


def evaluate_config(args: argparse.Namespace, run_dir: Path, steps: int) -> EvaluateConfig:
    """The evaluation of one chunk's pipeline into `run_dir/eval_<steps>` (one that a kill interrupted is
    redone; a finished one is read as it is)."""
    return EvaluateConfig(
        pipeline=[str(run_dir / "pipeline")], pipeline_names=["model"], lambdas=[0.0], data=args.data,
        evaluators=args.evaluators, protocol=args.protocol, n=args.n,
        num_inference_steps=args.num_inference_steps, guidance_scale=args.guidance_scale,
        steps=[args.num_inference_steps], schedulers=["ddim"], speed_n=2, crop_size=64, seed=args.seed,
        output_dir=str(run_dir / f"eval_{steps}"), resume=True,
    )  # fmt: skip


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="chip folder with index.csv")
    parser.add_argument("--vae", required=True, help="AutoencoderKL folder of the VAE stage")
    parser.add_argument("--evaluators", required=True, help="folder of the evaluators stage")
    parser.add_argument("--protocol", required=True, help='"extended" or "ood-<CLASS>"')
    parser.add_argument("--sizes", nargs="+", required=True, help="build_sar_zero123 sizes")
    parser.add_argument("--chunk_steps", type=int, default=600, help="steps between two evaluations")
    parser.add_argument("--max_steps", type=int, default=3000, help="steps of the last evaluation")
    parser.add_argument("--train_batch_size", type=int, default=16)
    parser.add_argument("--learning_rate", type=float, default=1e-3)
    parser.add_argument("--n", type=int, default=128, help="evaluation pairs (half seen, half unseen)")
    parser.add_argument("--num_inference_steps", type=int, default=20, help="DDIM steps of the evaluation")
    parser.add_argument("--guidance_scale", type=float, default=3.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work_dir", required=True, help="one finetune run folder per size is made here")
    parser.add_argument("--out", required=True, help="JSON lines file (appended)")
    parser.add_argument("--plot", default=None, help="PNG of every row of --out after the run")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.sizes) - set(SAR_ZERO123_SIZES))
    if unknown:
        parser.error(f"--sizes: unknown {unknown}; expected some of {sorted(SAR_ZERO123_SIZES)}")
    if args.chunk_steps < 1 or args.max_steps < args.chunk_steps:
        parser.error(f"need 1 <= --chunk_steps <= --max_steps, got {args.chunk_steps} and {args.max_steps}")
    for name in ("data", "vae", "evaluators"):
        if not Path(getattr(args, name)).exists():
            raise FileNotFoundError(f"--{name}: no such folder {getattr(args, name)!r}")
    return args


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark (`argv`: the command-line flags); returns every row of `--out`."""
    args = parse_args(argv)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = read_rows(out)
    done = {(curve_key(row), row["steps"]) for row in rows}
    for size in args.sizes:
        key = (size, args.learning_rate, args.train_batch_size)
        run_dir = Path(args.work_dir) / f"{size}_lr{args.learning_rate:g}_b{args.train_batch_size}"
        timing_file = run_dir / "chunk_seconds.json"  # per chunk; survives a kill between training and eval
        for steps in range(args.chunk_steps, args.max_steps + 1, args.chunk_steps):
            if (key, steps) in done:
                continue
            chunk_seconds = json.loads(timing_file.read_text()) if timing_file.is_file() else {}
            if str(steps) not in chunk_seconds:
                start = time.perf_counter()
                run_finetune(finetune_config(args, size, steps, run_dir))
                chunk_seconds[str(steps)] = round(time.perf_counter() - start, 1)
                write_json_atomic(chunk_seconds, timing_file)
            result = load_evaluation(run_evaluate(evaluate_config(args, run_dir, steps)))
            trained = sum(seconds for chunk, seconds in chunk_seconds.items() if int(chunk) <= steps)
            row = {
                "size": size,
                "steps": steps,
                "learning_rate": args.learning_rate,
                "train_batch_size": args.train_batch_size,
                "train_seconds": round(trained, 1),  # cumulative: every chunk up to this one
                "unet_parameters": unet_parameters(run_dir / "pipeline" / "unet"),
                **model_row(result["table3"]["model"]),
                **last_validation(run_dir),
            }
            rows.append(row)
            with out.open("a") as handle:  # one complete line per point: a kill loses at most the point
                handle.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    if args.plot is not None:
        plot_curves(rows, args.plot)
    return rows


def curve_key(row: dict) -> tuple[str, float, int]:
    """The curve a row belongs to: (size, learning rate, batch size)."""
    return row["size"], row["learning_rate"], row["train_batch_size"]


def plot_curves(rows: list[dict], path: str | Path) -> Path:
    """Seen and unseen azimuth gap closed against training minutes, one line per curve; writes `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = list(dict.fromkeys(curve_key(row) for row in rows))
    settings_vary = len({key[1:] for key in curves}) > 1  # name lr and batch only when they differ
    figure, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for axis, views in zip(axes, ("seen", "unseen")):
        for key in curves:
            points = sorted((row for row in rows if curve_key(row) == key), key=lambda row: row["steps"])
            minutes = [row["train_seconds"] / 60 for row in points]
            gap = [100 * row[f"{views}/azimuth_gap_closed"] for row in points]
            label = f"{key[0]} ({points[0]['unet_parameters'] / 1e6:.1f} M)"
            if settings_vary:
                label += f", lr {key[1]:g}, batch {key[2]}"
            axis.plot(minutes, gap, marker="o", label=label)
        axis.axhline(0, color="grey", linewidth=0.8)
        axis.set_title(f"{views} views")
        axis.set_xlabel("training minutes")
    axes[0].set_ylabel("azimuth gap closed (%)")
    axes[0].legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return Path(path)


def unet_parameters(folder: Path) -> int:
    """Parameter count of a saved UNet, read from its safetensors header (no weights loaded)."""
    with safe_open(str(folder / "diffusion_pytorch_model.safetensors"), "pt") as weights:
        return sum(math.prod(weights.get_slice(name).get_shape()) for name in weights.keys())


if __name__ == "__main__":
    main()
