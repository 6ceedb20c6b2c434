"""Run folders and the newer entry points: retry each bad input as a user would, on one source tree.

    python benchmarks/reliability_run_folders.py <source tree> <output.json> [groups]

``<source tree>`` is a checkout of this repository (``.`` for this one; an older state:
``git archive <commit> | tar -x -C /tmp/before``). Every case runs the tree's own command line in a
subprocess (``python train/...``, ``python -m sar_zero123...``) on tiny fabricated data in a temporary
folder, and records the exit status, the last line of its error, whether any file of the folders it was
pointed at changed, and case-specific facts (rows of an index, the report's total time, seconds before a
refusal). ``groups`` (comma-separated: ``overwrite``, ``lying_report``, ``late_refusal``, ``unbounded_work``,
``accepted_nonsense``, ``unclear_error``, ``issue39``) runs only those; ``RELIABILITY_THREADS`` sets each
command's torch threads (default 2). Flags a tree does not know (``--resume``, ``--restart``) make that
case fail with argparse's message, which is itself the outcome on that tree. About 5 minutes on 2 CPU
cores (``issue39`` alone: about 4). Results:
``docs/results/reliability.md``.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

ROOT = Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else Path(".").resolve()
OUTPUT = Path(sys.argv[2]) if len(sys.argv) > 2 else Path("reliability_run_folders.json")
#: Groups to run (comma-separated third argument, e.g. ``issue39``); all by default.
GROUPS = set(sys.argv[3].split(",")) if len(sys.argv) > 3 else None
THREADS = os.environ.get("RELIABILITY_THREADS", "2")  # torch threads of each command
TMP = Path(tempfile.mkdtemp(prefix="runfolders-"))
RESULTS: dict[str, dict] = {}
SMOKE = ["--preset", "smoke"]


def environment() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": THREADS}


def run(
    args: Sequence[str], timeout: float = 300.0, cwd: Path | None = None, max_file_bytes: int | None = None
) -> dict:
    """Runs ``python <args>`` in the tree (or in ``cwd``, the tree on ``PYTHONPATH``), each file it writes
    limited to ``max_file_bytes`` when given; exit status, seconds and the last line of stderr."""
    begin = time.perf_counter()

    def limit_files() -> None:  # in the child: a write beyond the limit fails with EFBIG
        resource.setrlimit(
            resource.RLIMIT_FSIZE, (max_file_bytes, resource.getrlimit(resource.RLIMIT_FSIZE)[1])
        )

    try:
        done = subprocess.run(
            [sys.executable, *args], cwd=cwd or ROOT, env=environment(), capture_output=True, text=True,
            timeout=timeout, preexec_fn=limit_files if max_file_bytes is not None else None,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        return {"rc": None, "seconds": timeout, "error": f"still running after {timeout:.0f} s (killed)"}
    return outcome(done.returncode, done.stdout, done.stderr, time.perf_counter() - begin)


def outcome(rc: int, stdout: str, stderr: str, seconds: float) -> dict:
    """A finished command's exit status, last output line, seconds and last error line."""
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith(" ")]
    errors = [line for line in lines if "Error" in line.split(":")[0] or line.startswith("usage:")]
    last = errors[-1] if errors else ""
    output = stdout.strip().splitlines()
    return {
        "rc": rc,
        "stdout_last_line": (output[-1] if output else "").replace(str(TMP), "…")[:120],
        "seconds": round(seconds, 1),
        "error": last.replace(str(TMP), "…")[:300],
    }


def snapshot(*folders: Path) -> str:
    """One digest of every file's path and bytes under ``folders``."""
    digest = hashlib.sha256()
    for folder in folders:
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            digest.update(str(path).encode() + path.read_bytes())
    return digest.hexdigest()


def case(
    name: str,
    args: Sequence[str],
    watch: Sequence[Path] = (),
    facts: Callable[[], dict] | None = None,
    timeout: float = 300.0,
    **options: Any,
) -> None:
    before = snapshot(*watch)
    result = run(args, timeout, **options)
    if watch:
        result["files_changed"] = snapshot(*watch) != before
    if facts is not None:
        try:
            result.update(facts())
        except Exception as error:  # noqa: BLE001 - a missing file is a fact too
            result["facts_error"] = f"{type(error).__name__}: {error}"[:200]
    RESULTS[name] = result
    print(f"{name}\t{json.dumps(result)}", flush=True)


def index_rows(folder: Path) -> int:
    return len((folder / "index.csv").read_text().splitlines()) - 1


@dataclass
class Folders:
    """What the groups of cases share: the smoke quickstart's folders and, once drawn, one of its chips."""

    quick: Path  # the finished smoke quickstart
    data: Path  # its simulated dataset
    pipeline: Path  # its lambda = 0 pipeline
    evaluators: Path  # its evaluator models
    chip: Path | None = None  # one chip of `data`, drawn by the unbounded-work cases

    @property
    def quickstart(self) -> list[str]:
        """The smoke quickstart's command line, into `quick`."""
        return ["train/quickstart.py", "--output_dir", str(self.quick), *SMOKE]

    @property
    def evaluate(self) -> list[str]:
        """A tiny evaluation of `pipeline`, without its output folder."""
        return ["train/evaluate.py", "--pipeline", str(self.pipeline), "--evaluators", str(self.evaluators),
                "--data", str(self.data), "--protocol", "ood-TRUCK", "--n", "4", "--num_inference_steps",
                "2", "--image_size", "32", "--crop_size", "32"]  # fmt: skip


def finetune_args(data: Path, output_dir: Path) -> list[str]:
    """A two-step fine-tune of a tiny model on `data`, into `output_dir`."""
    return ["train/finetune_pfm.py", "--output_dir", str(output_dir), "--size", "tiny", "--image_size",
            "32", "--data", str(data), "--protocol", "ood-TRUCK", "--pfm_weight", "0",
            "--train_batch_size", "2", "--max_train_steps", "2", "--validation_steps", "0",
            "--report_to", "none"]  # fmt: skip


def generate_args(pipeline: Path, image: Path, d_az: Sequence[str], output_dir: Path) -> list[str]:
    """`python -m sar_zero123.generate` of `image` with `pipeline`, two DDIM steps."""
    return ["-m", "sar_zero123.generate", "--pipeline", str(pipeline), "--image", str(image),
            "--d_az", *d_az, "--num_inference_steps", "2", "--output_dir", str(output_dir)]  # fmt: skip


def run_smoke_quickstart() -> Folders:
    """Runs the smoke quickstart every case starts from; stops if it fails."""
    quick = TMP / "quickstart"
    setup = run(["train/quickstart.py", "--output_dir", str(quick), *SMOKE])
    if setup["rc"] != 0:
        raise SystemExit(f"the smoke quickstart failed on {ROOT}: {setup}")
    return Folders(
        quick=quick,
        data=quick / "data",
        pipeline=quick / "finetune_lambda0" / "pipeline",
        evaluators=quick / "evaluators",
    )


def overwrite_cases(folders: Folders) -> None:
    """Commands pointed at a finished run or an existing folder: do they overwrite it?"""
    finetune = finetune_args(folders.data, TMP / "ft")
    run(finetune)
    case("finetune --output_dir <a finished run>, no --resume_from_checkpoint", finetune, [TMP / "ft"])
    case(
        "finetune --output_dir <a finished run> --learning_rate 0.5",
        [*finetune, "--learning_rate", "0.5"],
        [TMP / "ft"],
    )
    case(
        "finetune --output_dir <a finished run> --restart (moves it aside)",
        [*finetune, "--restart"],
        facts=lambda: {"moved_aside": len(list(TMP.glob("ft.replaced-*")))},
    )
    sim = ["train/simulate.py", "--out", str(TMP / "sim"), "--instances", "1", "--azimuth_step_deg", "30",
           "--size", "16"]  # fmt: skip
    run([*sim, "--classes", "TANK", "APC", "TRUCK", "DOZER"])
    case(
        "sim --out <an existing dataset> with other classes",
        [*sim, "--classes", "TANK"],
        [TMP / "sim"],
        facts=lambda: {"index_rows": index_rows(TMP / "sim")},
    )
    case(
        "evaluate --output_dir <an evaluators folder>",
        [*folders.evaluate, "--output_dir", str(folders.evaluators)],
        [folders.evaluators],
    )


def lying_report_cases(folders: Folders) -> None:
    """Quickstart re-runs whose report could describe settings that did not make its stages."""
    quick, qs = folders.quick, folders.quickstart
    case(
        "quickstart <finished> --protocol ood-APC",
        [*qs, "--protocol", "ood-APC"],
        [quick],
        facts=lambda: {
            "report_says_APC_never_seen": "APC is never seen" in (quick / "report.md").read_text()
        },
    )
    case("quickstart <finished> --seed 1", [*qs, "--seed", "1"], [quick])
    case("quickstart <finished> --resume --seed 1", [*qs, "--resume", "--seed", "1"], [quick])
    case("quickstart <finished>, same settings", qs, [quick])
    case(
        "quickstart <finished> --resume, same settings",
        [*qs, "--resume"],
        [quick],
        facts=lambda: {
            "report_total_line": next(
                line
                for line in (quick / "report.md").read_text().splitlines()
                if "min" in line and "Preset" in line
            )[:140]
        },
    )
    # killed during evaluation, after table3.json: views.png and the speed table not yet written
    for name in ("views.png", "speed_error.md", "speed_error.json", "speed_error.png", "lambda_sweep.png"):
        (quick / "eval" / name).unlink(missing_ok=True)
    record = quick / "eval" / "run.json"
    if record.is_file():  # the after tree records the stage; a kill leaves it unfinished
        state = json.loads(record.read_text())
        state["finished"] = False
        record.write_text(json.dumps(state))
    case(
        "quickstart killed during evaluation (after table3.json), re-run with --resume",
        [*qs, "--resume"],
        facts=lambda: {
            "views_png": (quick / "eval" / "views.png").is_file(),
            "report_has_speed_section": "## Speed against error" in (quick / "report.md").read_text(),
        },
    )
    case(
        "quickstart killed during evaluation, re-run without flags",
        qs,
        facts=lambda: {"views_png": (quick / "eval" / "views.png").is_file()},
    )


def late_refusal_cases() -> None:
    """Bad overrides: each must fail before any stage (no folder written)."""
    for item in (
        "base_steps=0",
        "finetune_steps=-1",
        "vae_steps=0",
        "eval_n=0",
        "evaluator_epochs=0",
        "model_size=huge",
        "classes=()",
    ):
        out = TMP / f"late_{item.split('=')[0]}"
        case(
            f"quickstart --override {item}",
            ["train/quickstart.py", "--output_dir", str(out), *SMOKE, "--override", item],
            facts=lambda out=out: {
                "stages_written": sorted(p.name for p in out.iterdir()) if out.exists() else []
            },
        )


def unbounded_work_cases(folders: Folders) -> None:
    """Requests for unbounded work: refused at once, or killed after two minutes."""
    case(
        "finetune --gradient_accumulation_steps 100000",
        [*finetune_args(folders.data, TMP / "ga"), "--gradient_accumulation_steps", "100000"],
        timeout=120,
    )
    case(
        "evaluate --n 100000000",
        [*folders.evaluate, "--n", "100000000", "--output_dir", str(TMP / "bign")],
        timeout=120,
    )
    folders.chip = next((folders.data / "chips").rglob("*.npy"))
    d_az = [str(a % 360) for a in range(5000)]
    case(
        "generate 5000 --d_az values",
        generate_args(folders.pipeline, folders.chip, d_az, TMP / "gen5000"),
        timeout=120,
    )


def accepted_nonsense_cases(folders: Folders) -> None:
    """Inputs outside any physical range: impossible depressions, a 1x1 image."""
    for depression in ("400", "-10", "91"):
        folder = TMP / f"dep{depression}"
        shutil.copytree(folders.data, folder, ignore=shutil.ignore_patterns("run.json"))
        lines = (folder / "index.csv").read_text().splitlines()
        fields = lines[1].split(",")
        fields[4] = depression
        (folder / "index.csv").write_text("\n".join([lines[0], ",".join(fields), *lines[2:]]) + "\n")
        train = ["train/train_evaluators.py", "--output_dir", str(TMP / f"ev{depression}"), "--data",
                 str(folder), "--epochs", "1", "--image_size", "32"]  # fmt: skip
        case(f"index.csv depression {depression} deg", train, timeout=120)
    Image.new("L", (1, 1), 128).save(TMP / "one.png")
    case("generate a 1x1 PNG", generate_args(folders.pipeline, TMP / "one.png", ["30"], TMP / "gen1"))


def generate_with_broken_pipeline(folders: Folders, edit: Callable[[Path], None], name: str) -> None:
    """Case `name`: generate with a copy of the pipeline that `edit` broke."""
    broken = TMP / "broken"
    shutil.rmtree(broken, ignore_errors=True)
    shutil.copytree(folders.pipeline, broken)
    edit(broken)
    assert folders.chip is not None, "the unbounded-work cases draw the chip"
    case(name, generate_args(broken, folders.chip, ["30"], TMP / "gen_broken"))
    shutil.rmtree(TMP / "gen_broken", ignore_errors=True)


def wrong_estimator(pipeline: Path) -> None:
    """Makes the azimuth estimator's config disagree with its weights."""
    config = json.loads((pipeline / "azimuth_estimator" / "config.json").read_text())
    config["code_dim"] = config.get("code_dim", 0) + 3
    (pipeline / "azimuth_estimator" / "config.json").write_text(json.dumps(config))


def unclear_error_cases(folders: Folders) -> None:
    """Broken pipelines, a truncated PNG and a metric call: does the error name the problem?"""
    generate_with_broken_pipeline(
        folders, lambda p: next((p / "unet").glob("*.safetensors")).unlink(), "pipeline without unet weights"
    )
    generate_with_broken_pipeline(
        folders, lambda p: shutil.rmtree(p / "azimuth_estimator"), "pipeline without its azimuth_estimator"
    )
    generate_with_broken_pipeline(folders, wrong_estimator, "pipeline with a wrong azimuth_estimator config")
    generate_with_broken_pipeline(
        folders,
        lambda p: (p / "decibel_scaling.json").write_text('{"min_db": -40, "max_db": }'),
        "pipeline with invalid JSON in decibel_scaling.json",
    )
    assert folders.chip is not None, "the unbounded-work cases draw the chip"
    png = TMP / "chip.png"
    Image.fromarray((np.load(folders.chip) * 255).astype(np.uint8)).save(png)
    png.write_bytes(png.read_bytes()[:-40])
    case("generate a truncated PNG", generate_args(folders.pipeline, png, ["30"], TMP / "gen_trunc"))
    case(
        "azimuth_error_deg(350.0, 10.0)",
        ["-c", "import sar_zero123.evaluation.metrics as m; print(m.azimuth_error_deg(350.0, 10.0))"],
    )


def issue39_cases(folders: Folders) -> None:
    """Issue 39: two writers, swapped parts, unclear errors and refusals that come after work was done."""
    pipeline, data, chip = folders.pipeline, folders.data, next((folders.data / "chips").rglob("*.npy"))
    # 1. a pipeline whose VAE is another model's (the bundled prior's: 64 px chips, the smoke model's 32)
    swapped = TMP / "swapped"
    shutil.copytree(pipeline, swapped)
    shutil.rmtree(swapped / "vae")
    shutil.copytree(ROOT / "sar_zero123" / "pretrained" / "sim_prior" / "vae", swapped / "vae")
    case(
        "1. evaluate a pipeline whose vae/ was copied from another pipeline",
        [*folders.evaluate[:2], str(swapped), *folders.evaluate[3:], "--output_dir", str(TMP / "ev_swapped")],
        facts=lambda: {"scored": (TMP / "ev_swapped" / "table3.json").is_file()},
    )
    # 2. augment_dataset killed before its index, resumed after the pipeline folder was replaced
    weights = TMP / "aug_pipeline"
    shutil.copytree(pipeline, weights)
    augment = [
        "-m",
        "sar_zero123.augment_dataset",
        "--data",
        str(data),
        "--pipeline",
        str(weights),
        "--out",
        str(TMP / "aug"),
        "--d_az",
        "30",
        "--max_chips_per_class",
        "1",
        "--num_inference_steps",
        "2",
    ]
    run(augment)
    for name in ("index.csv", "provenance.csv"):  # what a kill before the last writes leaves
        (TMP / "aug" / name).unlink(missing_ok=True)
    shutil.rmtree(weights)
    shutil.copytree(folders.quick / "finetune_lambda4" / "pipeline", weights)
    case(
        "2. augment_dataset killed, resumed after its pipeline folder was replaced",
        augment,
        facts=lambda: {"index_written": (TMP / "aug" / "index.csv").is_file()},
    )
    # 3. two augment_dataset runs started together into one new --out
    two = [*augment[:7], str(TMP / "aug_two"), *augment[8:]]
    two[5] = str(pipeline)
    begin = time.perf_counter()
    processes = [
        subprocess.Popen(
            [sys.executable, *two],
            cwd=ROOT,
            env=environment(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    results = [outcome(p.wait(), *p.communicate(), time.perf_counter() - begin) for p in processes]
    name = "3. two augment_dataset runs started together into one new --out"
    RESULTS[name] = {
        "rc": [r["rc"] for r in results],
        "error": " | ".join(r["error"] for r in results if r["error"]),
        "seconds": max(r["seconds"] for r in results),
    }
    print(f"{name}\t{json.dumps(RESULTS[name])}", flush=True)
    # 4. --restart of a folder that holds the run's --data
    inside = TMP / "restart_inside"
    shutil.copytree(data, inside / "data")
    (inside / "note.txt").write_text("an earlier run\n")
    case(
        "4. finetune --restart with --output_dir a parent of --data",
        [*finetune_args(inside / "data", inside), "--restart"],
        facts=lambda: {"data_in_place": (inside / "data" / "index.csv").is_file()},
    )
    # 5. an unknown bundled name
    case(
        "5. generate --pipeline sar-zero123/nope",
        generate_args(Path("sar-zero123/nope"), chip, ["30"], TMP / "gen_nope"),
    )
    # 6. the smoke quickstart at seeds 1 and 2
    for seed in ("1", "2"):
        out = TMP / f"smoke_seed{seed}"
        case(
            f"6. quickstart --preset smoke --seed {seed}",
            ["train/quickstart.py", "--output_dir", str(out), *SMOKE, "--seed", seed],
            facts=lambda out=out: {
                "stages_written": sorted(p.name for p in out.iterdir()) if out.exists() else []
            },
            timeout=600,
        )
    # 7. --output_dir . --restart, run inside a finished run (never in the tree itself)
    dot = TMP / "dot"
    run(finetune_args(data, dot))
    case(
        "7. finetune --output_dir . --restart (run inside the folder)",
        [str(ROOT / "train" / "finetune_pfm.py"), *finetune_args(data, Path("."))[1:], "--restart"],
        cwd=dot,
        facts=lambda: {"folder_in_place": (dot / "run.json").is_file()},
    )
    # 8. a --corpus folder that is not a prior corpus
    case(
        "8. pretrain_prior --corpus <a dataset that is not a prior corpus>",
        [
            "train/pretrain_prior.py",
            "--output_dir",
            str(TMP / "prior_nc"),
            "--corpus",
            str(data),
            "--base_steps",
            "2",
            "--vae_steps",
            "2",
        ],
        facts=lambda: {
            "written": sorted(p.name for p in (TMP / "prior_nc").iterdir())
            if (TMP / "prior_nc").exists()
            else []
        },
    )
    # 9. a meta tensor
    case(
        "9. pipe(torch.empty(1, 1, 32, 32, device='meta'), 30)",
        [
            "-c",
            "import torch; from sar_zero123.model.pipeline import SARZero123Pipeline as P; "
            f"p = P.from_pretrained({str(pipeline)!r}); p(torch.empty(1, 1, 32, 32, device='meta'), 30.0, "
            "num_inference_steps=2)",
        ],
    )
    # 10. settings a later stage refuses
    for name, args in (
        (
            "quickstart --override image_size=30",
            ["train/quickstart.py", *SMOKE, "--override", "image_size=30"],
        ),
        (
            "quickstart --override prior=/nonexistent",
            ["train/quickstart.py", *SMOKE, "--override", "prior=/nonexistent"],
        ),
        ("pretrain_prior --model_size tiny", ["train/pretrain_prior.py", "--model_size", "tiny"]),
        ("pretrain_prior --image_size 30", ["train/pretrain_prior.py", "--image_size", "30"]),
        (
            "pretrain_prior --train_batch_size 100000",
            ["train/pretrain_prior.py", "--train_batch_size", "100000"],
        ),
    ):
        out = TMP / f"late10_{len(RESULTS)}"
        small = (
            [
                "--num_vehicles",
                "8",
                "--views_per_vehicle",
                "4",
                "--num_validation_vehicles",
                "2",
                "--vae_steps",
                "2",
                "--base_steps",
                "2",
            ]
            if "pretrain_prior" in name
            else []
        )
        case(
            f"10. {name}",
            [*args, *small, "--output_dir", str(out)],
            timeout=600,
            facts=lambda out=out: {"written": sorted(p.name for p in out.iterdir()) if out.exists() else []},
        )
    # 11. a run refused at its start, then the corrected command
    refused = TMP / "refused"
    builtin = [
        arg for arg in finetune_args(data, refused) if arg not in ("--data", str(data))
    ]  # the simulator
    run([*builtin, "--train_batch_size", "100000"])
    case(
        "11. finetune on the built-in simulator refused (batch 100000), then the corrected command",
        builtin,
        timeout=600,
        facts=lambda: {
            "finished": json.loads((refused / "run.json").read_text()).get("finished")
            if (refused / "run.json").is_file()
            else None
        },
    )
    prior = TMP / "prior11"
    prior_args = [
        "train/pretrain_prior.py",
        "--output_dir",
        str(prior),
        "--num_vehicles",
        "8",
        "--views_per_vehicle",
        "4",
        "--num_validation_vehicles",
        "4",
        "--model_size",
        "tiny",
        "--vae_widths",
        "16",
        "32",
        "--vae_steps",
        "2",
        "--base_steps",
        "2",
        "--corpus_workers",
        "1",
    ]
    case(
        "11. pretrain_prior whose batch (16) the corpus's training pairs cannot fill",
        prior_args,
        timeout=600,
        facts=lambda: {"written": sorted(p.name for p in prior.iterdir())},
    )
    # minor: resumed with fewer steps than the checkpoint's; a file-size limit while writing a checkpoint
    steps = TMP / "steps"
    run([*finetune_args(data, steps), "--checkpointing_steps", "2"])
    case(
        "minor. finetune resumed with --max_train_steps 1 below its checkpoint-2",
        [*finetune_args(data, steps), "--max_train_steps", "1", "--resume_from_checkpoint", "latest"],
        [steps],
        facts=lambda: {
            "recorded_max_train_steps": json.loads((steps / "run.json").read_text())["config"][
                "max_train_steps"
            ]
        },
    )
    case(
        "minor. finetune writing its checkpoint past a 200 kB file-size limit",
        [*finetune_args(data, TMP / "fsize"), "--checkpointing_steps", "1"],
        max_file_bytes=200_000,
        facts=lambda: {"left": sorted(p.name for p in (TMP / "fsize").iterdir())},
    )


def main() -> None:
    # 1. the finished smoke quickstart every case starts from
    folders = run_smoke_quickstart()
    # 2. the cases, group by group, in the order of the results
    groups = [overwrite_cases, lying_report_cases, late_refusal_cases, unbounded_work_cases,
              accepted_nonsense_cases, unclear_error_cases, issue39_cases]  # fmt: skip
    for group in groups:
        if GROUPS is None or group.__name__.removesuffix("_cases") in GROUPS:
            group(*([] if group is late_refusal_cases else [folders]))
    # 3. the results
    OUTPUT.write_text(json.dumps({"tree": str(ROOT), "results": RESULTS}, indent=2) + "\n")
    shutil.rmtree(TMP, ignore_errors=True)


if __name__ == "__main__":
    main()
