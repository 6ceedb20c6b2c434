"""Issue 64's cases (exit status, moved inputs, loaders that trust what they read), retried on one tree.

    python benchmarks/reliability_issue64.py <source tree> <output.json>

``<source tree>`` is a checkout of this repository (``.`` for this one; an older state:
``git archive <commit> | tar -x -C /tmp/before``). Every case runs the tree's own code in a subprocess (its
console scripts as pip's launcher calls them, ``python -m sar_zero123...``, or a few lines of Python against
its API) on fabricated inputs in a temporary folder, and records the exit status, the last line of its error,
whether any file of the inputs it was pointed at changed, and case-specific facts. ``RELIABILITY_THREADS``
sets each command's torch threads (default 2). About 4 minutes on 2 CPU cores. Results:
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
from pathlib import Path

import numpy as np
import tomllib
from PIL import Image

ROOT = Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else Path(".").resolve()
OUTPUT = Path(sys.argv[2]) if len(sys.argv) > 2 else Path("reliability_issue64.json")
THREADS = os.environ.get("RELIABILITY_THREADS", "2")
TMP = Path(tempfile.mkdtemp(prefix="issue64-"))
RESULTS: dict[str, dict] = {}
BUNDLED = ROOT / "sar_zero123" / "pretrained" / "sim_prior_rotated"


def environment() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": THREADS}


def outcome(done: subprocess.CompletedProcess, seconds: float) -> dict:
    """Exit status, seconds, the last error line, how many lines the error took, the last output line."""
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    errors = [
        line
        for line in lines
        if not line.startswith(" ") and ("rror" in line.split(":")[0] or ": error:" in line)
    ]
    output = done.stdout.strip().splitlines()
    return {
        "rc": done.returncode,
        "seconds": round(seconds, 1),
        "error": (errors[-1] if errors else "").replace(str(TMP), "…").replace(str(ROOT), "<tree>")[:240],
        "traceback": any(line.startswith("Traceback") for line in lines),
        "stdout_last_line": (output[-1] if output else "").replace(str(TMP), "…")[:160],
    }


def run(args: Sequence[str], timeout: float = 300.0, max_file_bytes: int | None = None) -> dict:
    """``python <args>`` in the tree, each file it writes limited to ``max_file_bytes`` when given."""

    def limit_files() -> None:
        resource.setrlimit(
            resource.RLIMIT_FSIZE, (max_file_bytes, resource.getrlimit(resource.RLIMIT_FSIZE)[1])
        )

    begin = time.perf_counter()
    try:
        done = subprocess.run(
            [sys.executable, *args],
            cwd=ROOT,
            env=environment(),
            capture_output=True,
            text=True,
            timeout=timeout,
            preexec_fn=limit_files if max_file_bytes is not None else None,
        )
    except subprocess.TimeoutExpired:
        return {"rc": None, "seconds": timeout, "error": f"still running after {timeout:.0f} s (killed)"}
    return outcome(done, time.perf_counter() - begin)


def launcher(script: str, args: Sequence[str], timeout: float = 300.0) -> dict:
    """The tree's console script as pip's launcher runs it: ``sys.exit(entry_point())``."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    module, attribute = scripts[script].split(":")
    code = (
        "import importlib, sys\n"
        f"target = importlib.import_module({module!r})\n"
        f"for part in {attribute!r}.split('.'):\n    target = getattr(target, part)\n"
        f"sys.argv = [{script!r}, *{list(map(str, args))!r}]\n"
        "sys.exit(target())\n"
    )
    return run(["-c", code], timeout)


def python(code: str, timeout: float = 300.0) -> dict:
    return run(["-c", code], timeout)


def snapshot(*paths: Path) -> str:
    digest = hashlib.sha256()
    for root in paths:
        for path in sorted(p for p in root.rglob("*") if p.is_file()) if root.is_dir() else [root]:
            digest.update(str(path).encode() + path.read_bytes())
    return digest.hexdigest()


def files_under(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")} if folder.exists() else set()


def case(
    name: str, probe: Callable[[], dict], watch: Sequence[Path] = (), facts: Callable[[], dict] | None = None
) -> None:
    before = snapshot(*watch)
    result = probe()
    if watch:
        result["inputs_changed"] = snapshot(*[p for p in watch if p.exists()]) != before or not all(
            p.exists() for p in watch
        )
    if facts is not None:
        try:
            result.update(facts())
        except Exception as error:  # noqa: BLE001 - a missing file is a fact too
            result["facts_error"] = f"{type(error).__name__}: {error}"[:200]
    RESULTS[name] = result
    print(f"{name}\t{json.dumps(result)}", flush=True)


def loads(folder: Path) -> dict:
    """Whether a pipeline folder still loads (in the tree, in a subprocess)."""
    done = python(
        f"from sar_zero123 import SARZero123Pipeline; SARZero123Pipeline.from_pretrained({str(folder)!r})"
    )
    return {"still_loads": done["rc"] == 0}


def pipeline_copy(name: str) -> Path:
    target = TMP / name
    shutil.copytree(BUNDLED, target)
    return target


def main() -> None:
    chip = TMP / "chip.png"
    rng = np.random.default_rng(0)
    Image.fromarray((rng.random((64, 64)) * 80 + 20 * np.eye(64)).astype(np.uint8)).save(chip)
    data = TMP / "data"
    run(
        [
            "train/simulate.py",
            "--out",
            str(data),
            "--classes",
            "TANK",
            "APC",
            "--instances",
            "1",
            "--azimuth_step_deg",
            "120",
            "--depressions_deg",
            "17",
            "--size",
            "64",
        ]
    )
    restart_data, escape = TMP / "restart_data", TMP / "escape_data"
    shutil.copytree(data, restart_data)
    shutil.copytree(data, escape)
    interp_tuned = pipeline_copy("pipe_interp")
    generate = [
        "--pipeline",
        "sar-zero123/sim-prior-rotated",
        "--image",
        str(chip),
        "--d_az",
        "30",
        "--num_inference_steps",
        "2",
    ]

    # 1. exit status of a successful console script
    case(
        "1. sar-zero123-generate succeeds: the installed launcher's exit status",
        lambda: launcher("sar-zero123-generate", [*generate, "--output_dir", str(TMP / "gen")]),
        facts=lambda: {"writes_views_json": (TMP / "gen" / "views.json").is_file()},
    )
    # 2. --restart with the output folder inside an input
    pipe_dir = pipeline_copy("pipe_restart")
    case(
        "2. generate --output_dir <its pipeline>/unet --restart",
        lambda: launcher(
            "sar-zero123-generate",
            [
                *generate[:1],
                str(pipe_dir),
                *generate[2:],
                "--output_dir",
                str(pipe_dir / "unet"),
                "--restart",
            ],
        ),
        watch=[pipe_dir],
        facts=lambda: loads(pipe_dir),
    )
    case(
        "2. augment --out <its data>/chips --restart",
        lambda: launcher(
            "sar-zero123-augment",
            [
                "--data",
                str(restart_data),
                "--out",
                str(restart_data / "chips"),
                "--d_az",
                "30",
                "--num_inference_steps",
                "2",
                "--restart",
            ],
        ),
        watch=[restart_data],
    )
    # 3. security
    index = (escape / "index.csv").read_text().splitlines()
    header = index[0].split(",")
    column = header.index("target_class")
    rows = [line.split(",") for line in index[1:]]
    for row in rows:
        row[column] = "../../escaped"
    (escape / "index.csv").write_text("\n".join([index[0], *[",".join(r) for r in rows]]) + "\n")
    case(
        "3. augment: a target_class that is a path (../../escaped)",
        lambda: launcher(
            "sar-zero123-augment",
            [
                "--data",
                str(escape),
                "--out",
                str(TMP / "aug_escape" / "out"),
                "--d_az",
                "30",
                "--num_inference_steps",
                "2",
            ],
        ),
        facts=lambda: {
            "written_outside_out": sorted(
                f for f in files_under(TMP / "aug_escape") if not f.startswith("out")
            )[:5]
        },
    )
    zen = pipeline_copy("pipe_zen")
    model_index = json.loads((zen / "model_index.json").read_text())
    (zen / "model_index.json").write_text(json.dumps({**model_index, "zen": ["this", "s"]}))
    load_zen = f"from sar_zero123 import SARZero123Pipeline; SARZero123Pipeline.from_pretrained({str(zen)!r})"

    def zen_probe() -> dict:
        begin = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-c", load_zen], cwd=ROOT, env=environment(), capture_output=True, text=True
        )
        return outcome(done, time.perf_counter() - begin) | {
            "zen_printed": "Beautiful is better" in done.stdout
        }

    case("3. a model_index.json naming a module (['this', 's'])", zen_probe)
    # 4. trusted without checking
    zeroed = pipeline_copy("pipe_zeroed")
    weights = zeroed / "unet" / "diffusion_pytorch_model.safetensors"
    python(
        f"from safetensors.torch import load_file, save_file; w = load_file({str(weights)!r}); "
        f"[t.view(-1)[: t.numel() // 2].zero_() for t in w.values()]; "
        f"save_file(w, {str(weights)!r}, metadata={{'format': 'pt'}})"
    )
    case(
        "4. a pipeline with half its UNet weights zeroed",
        lambda: python(
            f"from sar_zero123 import SARZero123Pipeline; SARZero123Pipeline.from_pretrained({str(zeroed)!r})"
        ),
    )
    case(
        "4. a pipeline built with another run's azimuth estimator",
        lambda: python(
            "from sar_zero123 import SARZero123Pipeline\n"
            "from sar_zero123.model.build import build_sar_zero123\n"
            "from sar_zero123.data import DecibelScaling\n"
            "from sar_zero123.training.finetuning import export_finetuned\n"
            f"pipe = build_sar_zero123('tiny', estimate_input_azimuth=True, seed=3)\n"
            f"export_finetuned({str(TMP / 'est')!r}, pipe, DecibelScaling())\n"
            f"loaded = SARZero123Pipeline.from_pretrained({str(TMP / 'est')!r})\n"
            "other = build_sar_zero123('tiny', estimate_input_azimuth=True, seed=4).azimuth_estimator\n"
            "SARZero123Pipeline(**{**loaded.components, 'azimuth_estimator': other})\n"
        ),
    )
    # 5. unbounded
    case(
        "5. generate --image_size 1024",
        lambda: launcher(
            "sar-zero123-generate",
            [*generate, "--image_size", "1024", "--output_dir", str(TMP / "big")],
            timeout=60,
        ),
    )
    # 6. unclear errors
    case(
        "6. generate --pipeline sim-prior-rotated (no namespace)",
        lambda: launcher(
            "sar-zero123-generate",
            ["--pipeline", "sim-prior-rotated", *generate[2:], "--output_dir", str(TMP / "n")],
        ),
    )
    truncated = pipeline_copy("pipe_truncated")
    weights = truncated / "unet" / "diffusion_pytorch_model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    case(
        "6. interpolate with a truncated weight file",
        lambda: launcher(
            "sar-zero123-interpolate",
            [
                "--start",
                "sar-zero123/sim-prior-rotated",
                "--finetuned",
                str(truncated),
                "--output_dir",
                str(TMP / "interp_trunc"),
            ],
        ),
        facts=lambda: {"left_behind": sorted(files_under(TMP / "interp_trunc"))[:5]},
    )
    header_only = TMP / "huge.npy"
    with open(header_only, "wb") as handle:
        np.lib.format.write_array_header_1_0(
            handle, {"descr": "<f8", "fortran_order": False, "shape": (100_000, 100_000)}
        )
    case(
        "6. generate --image <an .npy header claiming 100,000 x 100,000>",
        lambda: launcher(
            "sar-zero123-generate",
            [*generate[:2], "--image", str(header_only), *generate[4:], "--output_dir", str(TMP / "npy")],
        ),
    )
    bomb = TMP / "bomb.png"
    Image.new("L", (20_000, 20_000)).save(bomb, optimize=False)
    case(
        "6. generate --image <a 20,000 x 20,000 PNG>",
        lambda: launcher(
            "sar-zero123-generate",
            [*generate[:2], "--image", str(bomb), *generate[4:], "--output_dir", str(TMP / "png")],
        ),
    )
    api = (
        "import torch\nfrom sar_zero123 import SARZero123Pipeline\n"
        "pipe = SARZero123Pipeline.from_pretrained('sar-zero123/sim-prior-rotated')\n"
        "x = torch.rand(1, 1, 64, 64)\n"
    )
    case(
        "6. API: generator=42",
        lambda: python(
            api + "pipe(x, 30.0, 0.0, input_depression_deg=17.0, num_inference_steps=2, generator=42)"
        ),
    )
    case(
        "6. API: a callback that returns None",
        lambda: python(
            api + "pipe(x, 30.0, 0.0, input_depression_deg=17.0, num_inference_steps=2, "
            "callback_on_step_end=lambda p, s, t, k: None)"
        ),
    )
    case(
        "6. a refusal at the command line (generate --d_az nan)",
        lambda: launcher(
            "sar-zero123-generate", [*generate[:4], "--d_az", "nan", "--output_dir", str(TMP / "nan")]
        ),
    )
    # 7. consistency and knobs measured to do nothing
    case(
        "7. finetune --pfm_monotonic_q 512 (measured to change nothing)",
        lambda: python(
            "from sar_zero123.config import parse_config\n"
            "from sar_zero123.stages.finetune import FinetuneConfig\n"
            "print(parse_config(FinetuneConfig, ['--pfm_monotonic_q', '512', '--encoder', 'e']).pfm_weight)"
        ),
    )
    # last: on a tree that moves it, the bundled prior is gone for every later case
    case(
        "2. interpolate --output_dir <the bundled prior's folder> --restart",
        lambda: launcher(
            "sar-zero123-interpolate",
            [
                "--start",
                "sar-zero123/sim-prior-rotated",
                "--finetuned",
                str(interp_tuned),
                "--output_dir",
                str(BUNDLED),
                "--restart",
            ],
        ),
        watch=[BUNDLED],
    )
    OUTPUT.parent.mkdir(parents=True, exist_ok=True)
    OUTPUT.write_text(json.dumps({"tree": str(ROOT), "threads": THREADS, "cases": RESULTS}, indent=1) + "\n")
    shutil.rmtree(TMP, ignore_errors=True)


if __name__ == "__main__":
    main()
