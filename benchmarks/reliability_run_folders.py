"""Run folders and the newer entry points: retry each bad input as a user would, on one source tree.

    python benchmarks/reliability_run_folders.py <source tree> <output.json>

``<source tree>`` is a checkout of this repository (``.`` for this one; an older state:
``git archive <commit> | tar -x -C /tmp/before``). Every case runs the tree's own command line in a
subprocess (``python train/...``, ``python -m sar_zero123...``) on tiny fabricated data in a temporary
folder, and records the exit status, the last line of its error, whether any file of the folders it was
pointed at changed, and case-specific facts (rows of an index, the report's total time, seconds before a
refusal). Flags a tree does not know (``--resume``, ``--restart``) make that case fail with argparse's
message, which is itself the outcome on that tree. About 5 minutes on 2 CPU cores. Results:
``docs/results/reliability.md``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else Path(".").resolve()
OUTPUT = Path(sys.argv[2]) if len(sys.argv) > 2 else Path("reliability_run_folders.json")
TMP = Path(tempfile.mkdtemp(prefix="runfolders-"))
RESULTS: dict[str, dict] = {}
SMOKE = ["--preset", "smoke"]


def run(args: Sequence[str], timeout: float = 300.0) -> dict:
    """Runs ``python <args>`` in the tree; exit status, seconds and the last line of stderr."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "2"}
    begin = time.perf_counter()
    try:
        done = subprocess.run(
            [sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return {"rc": None, "seconds": timeout, "error": f"still running after {timeout:.0f} s (killed)"}
    lines = [line for line in done.stderr.splitlines() if line.strip() and not line.startswith(" ")]
    errors = [line for line in lines if "Error" in line.split(":")[0] or line.startswith("usage:")]
    last = errors[-1] if errors else ""
    output = done.stdout.strip().splitlines()
    return {
        "rc": done.returncode,
        "stdout_last_line": (output[-1] if output else "").replace(str(TMP), "…")[:120],
        "seconds": round(time.perf_counter() - begin, 1),
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
) -> None:
    before = snapshot(*watch)
    result = run(args, timeout)
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
    sim = ["-m", "sar_zero123.sim", "--out", str(TMP / "sim"), "--instances", "1", "--azimuth-step", "30",
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


def main() -> None:
    # 1. the finished smoke quickstart every case starts from
    folders = run_smoke_quickstart()
    # 2. the cases, group by group, in the order of the results
    overwrite_cases(folders)
    lying_report_cases(folders)
    late_refusal_cases()
    unbounded_work_cases(folders)
    accepted_nonsense_cases(folders)
    unclear_error_cases(folders)
    # 3. the results
    OUTPUT.write_text(json.dumps({"tree": str(ROOT), "results": RESULTS}, indent=2) + "\n")
    shutil.rmtree(TMP, ignore_errors=True)


if __name__ == "__main__":
    main()
