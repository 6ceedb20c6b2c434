"""Hostile and careless inputs at the command line, each through a real command's console entry point.

Each probe runs ``cli.console.<command>()`` on its argv in this process (as the installed launcher does,
``sys.exit(entry_point())``) against tiny inputs (a 32 px pipeline, a simulated dataset of 4 chips), and
asserts its exit status and the one line it ends with: a refusal (2) names the field or file before any
work; a file-system failure (74) names the path and what to do; a bad flag is argparse's (2). The kinds:
loosely written numbers, values past any physical bound, YAML that says something other than it seems,
output paths that cannot be folders, full and read-only disks. ``docs/results/reliability.md`` maps each
reported case to its test, here or elsewhere.

Run them: ``OMP_NUM_THREADS=1 python -m pytest -q -p no:xdist tests/test_reliability_probes.py``.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import re
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import torch
from dummies import get_dummy_components

from sar_zero123 import cli
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.sim import simulate_dataset


@dataclasses.dataclass
class Ending:
    status: int | str | None  # the exit status (argparse's SystemExit code included)
    line: str  # the last line on stderr ("" when none)
    out: str  # stdout


def run_console(command: str, argv: list[str], capsys: pytest.CaptureFixture[str]) -> Ending:
    """``command``'s console script on ``argv``, as its launcher runs it."""
    saved = sys.argv
    sys.argv = [f"sar-zero123-{command.replace('_', '-')}", *argv]
    try:
        status: int | str | None = getattr(cli.console, command)()
    except SystemExit as done:  # argparse: a bad flag
        status = done.code
    finally:
        sys.argv = saved
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    return Ending(status, lines[-1] if lines else "", captured.out)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("probes")
    pipeline = root / "pipeline"
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(pipeline)
    chip = root / "chip.png"
    pixels = np.random.default_rng(0).integers(0, 256, (40, 40), dtype=np.uint8)
    PIL.Image.fromarray(pixels, mode="L").save(chip)
    data = simulate_dataset(root / "data", classes=("TANK",), instances=1, azimuth_step_deg=90,
                            depressions_deg=(17.0,), size=32)  # fmt: skip
    (root / "a_file").write_text("not a folder")
    (root / "dangling").symlink_to(root / "nowhere")
    return {"root": root, "pipeline": pipeline, "chip": chip, "data": data}


def _yaml(inputs: dict[str, Path], name: str, text: str) -> str:
    path = inputs["root"] / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return str(path)


def _index_with(inputs: dict[str, Path], name: str, column: str, value: str) -> str:
    """A copy of the simulated dataset whose first row's ``column`` reads ``value``."""
    folder = inputs["root"] / name
    if not folder.exists():
        shutil.copytree(inputs["data"], folder)
        lines = (folder / "index.csv").read_text().splitlines()
        header = lines[0].split(",")
        row = lines[1].split(",")
        row[header.index(column)] = value
        (folder / "index.csv").write_text("\n".join([lines[0], ",".join(row), *lines[2:]]) + "\n")
    return str(folder)


def _generate(inputs: dict[str, Path], out: str, *extra: str) -> list[str]:
    return ["--pipeline", str(inputs["pipeline"]), "--image", str(inputs["chip"]), "--d_az", "30",
            "--num_inference_steps", "2", "--output_dir", str(inputs["root"] / out), *extra]  # fmt: skip


def _simulate(inputs: dict[str, Path], out: str, *extra: str) -> list[str]:
    return ["--out", str(inputs["root"] / out), "--classes", "TANK", "--instances", "1",
            "--azimuth_step_deg", "180", "--depressions_deg", "17", "--size", "32", *extra]  # fmt: skip


def _augment(inputs: dict[str, Path], out: str, *extra: str, data: str | None = None) -> list[str]:
    return ["--data", data or str(inputs["data"]), "--pipeline", str(inputs["pipeline"]), "--out",
            str(inputs["root"] / out), "--d_az", "90", "--num_inference_steps", "2", *extra]  # fmt: skip


def _interpolate(inputs: dict[str, Path], out: str, *extra: str, start: str = "x", finetuned: str = "y"
                 ) -> list[str]:
    return ["--start", start, "--finetuned", finetuned, "--output_dir", str(inputs["root"] / out), *extra]


Argv = Callable[[dict[str, Path]], list[str]]
DEEP_JSON = '{"seed": ' + "[" * 100_000 + "]" * 100_000 + "}"
#: (id, command, argv, exit status, a regex the last stderr line matches).
PROBES: list[tuple[str, str, Argv, int, str]] = [
    # --- numbers written loosely: Python and YAML 1.1 read these as numbers nobody meant
    ("flag integer with digit separators", "simulate", lambda i: _simulate(i, "p1", "--seed", "1_0"), 2,
     r"argument --seed/?.*: invalid integer value: '1_0'"),
    ("flag integer in full-width digits", "simulate",
     lambda i: _simulate(i, "p2", "--size", "\uff13\uff12"), 2, r"argument --size: invalid integer value"),
    ("flag float with digit separators", "generate", lambda i: _generate(i, "p3", "--d_az", "3_0"), 2,
     r"argument --d_az/?.*: invalid finite_float value: '3_0'"),
    ("--set float with digit separators", "simulate",
     lambda i: _simulate(i, "p4", "--set", "azimuth_step_deg=1_80"), 2,
     r"error: --set azimuth_step_deg=1_80: not a value of azimuth_step_deg \(not a number: '1_80'\)"),
    ("--config YAML 1.1 integer 1_0", "simulate",
     lambda i: _simulate(i, "p5", "--config", _yaml(i, "p5.yaml", "seed: 1_0\n")), 2,
     r"error: --config .*p5.yaml.*'1_0' \(line 1\) is a number only in YAML 1.1's loose forms \(read as 10"),
    ("--config YAML 1.1 hexadecimal", "simulate",
     lambda i: _simulate(i, "p6", "--config", _yaml(i, "p6.yaml", "size: 0x20\n")), 2,
     r"'0x20' \(line 1\) is a number only in YAML 1.1's loose forms \(read as 32\)"),
    ("--config YAML 1.1 base 60", "simulate",
     lambda i: _simulate(i, "p7", "--config", _yaml(i, "p7.yaml", "azimuth_jitter_deg: 1:30\n")), 2,
     r"'1:30' \(line 1\) is a number only in YAML 1.1's loose forms \(read as 90\)"),
    ("--config YAML 1.1 octal", "simulate",
     lambda i: _simulate(i, "p8", "--config", _yaml(i, "p8.yaml", "instances: 017\n")), 2,
     r"'017' \(line 1\) is a number only in YAML 1.1's loose forms \(read as 15\)"),
    ("--config 1e2 is the number 100 (YAML 1.1 reads text)", "simulate",
     lambda i: _simulate(i, "p9", "--config", _yaml(i, "p9.yaml", "azimuth_step_deg: 1e2\n")), 0, r"^$"),
    ("--config float for an integer field", "generate",
     lambda i: _generate(i, "p10", "--config", _yaml(i, "p10.yaml", "seed: 1e3\n")), 2,
     r"error: seed: expected an integer within int64, got 1000.0"),
    ("index azimuth in full-width digits", "augment",
     lambda i: _augment(i, "p11", data=_index_with(i, "idx_fw", "azimuth_deg", "\uff13\uff10")), 2,
     r"column 'azimuth_deg' must be a number, got '\uff13\uff10'"),
    ("index height in full-width digits", "augment",
     lambda i: _augment(i, "p12", data=_index_with(i, "idx_h", "height", "\uff13\uff12")), 2,
     r"column 'height' must be an integer, got '\uff13\uff12'"),
    ("index azimuth 3_0 (issue 75)", "augment",
     lambda i: _augment(i, "p13", data=_index_with(i, "idx_us", "azimuth_deg", "3_0")), 2,
     r"column 'azimuth_deg' must be a number, got '3_0'"),
    # --- values past any physical or numeric bound, for other fields and commands
    ("seed past int64 (issue 75)", "generate",
     lambda i: _generate(i, "p14", "--seed", "18446744073709551616"), 2,
     r"error: seed: expected an integer within int64, got 18446744073709551616"),
    ("azimuth step 1e-9 (issue 75)", "simulate",
     lambda i: _simulate(i, "p15", "--azimuth_step_deg", "1e-9"), 2,
     r"azimuth_step_deg=1e-09 .* would write 3.6e\+11 chips, more than 200000"),
    ("proxy-retrieval learning rate 1e999 (issue 75)", "proxy_retrieval",
     lambda i: ["--output_dir", str(i["root"] / "p16"), "--set", "learning_rate=1e999"], 2,
     r"--set learning_rate=1e999: not a value of learning_rate \(expected a finite number"),
    ("simclr learning rate nan", "simclr", lambda i: ["--output_dir", str(i["root"] / "p17"),
                                                      "--learning_rate", "nan"], 2,
     r"argument --learning_rate/?.*: invalid finite_float value: 'nan'"),
    ("vae learning rate inf by --set", "vae", lambda i: ["--output_dir", str(i["root"] / "p18"),
                                                        "--set", "learning_rate=inf"], 2,
     r"--set learning_rate=inf: not a value of learning_rate \(expected a finite number"),
    ("finetune snr_gamma 1e999 by --config", "finetune",
     lambda i: ["--output_dir", str(i["root"] / "p19"), "--config",
                _yaml(i, "p19.yaml", "snr_gamma: 1e999\n")], 2,
     r"error: snr_gamma: expected a finite number, got inf"),
    ("evaluators seed past int64", "evaluators", lambda i: ["--output_dir", str(i["root"] / "p20"),
                                                           "--seed", "99999999999999999999"], 2,
     r"error: seed: expected an integer within int64, got 99999999999999999999"),
    ("interpolate alpha nan", "interpolate", lambda i: ["--start", "x", "--finetuned", "y", "--output_dir",
                                                       str(i["root"] / "p21"), "--alpha", "nan"], 2,
     r"argument --alpha: invalid finite_float value: 'nan'"),
    ("generate input azimuth nan by --config", "generate",
     lambda i: _generate(i, "p22", "--config", _yaml(i, "p22.yaml", "input_azimuth: .nan\n")), 2,
     r"error: input_azimuth: expected a finite number, got nan"),
    ("generate guidance 1e999", "generate", lambda i: _generate(i, "p23", "--guidance_scale", "1e999"), 2,
     r"argument --guidance_scale/--guidance-scale: invalid finite_float value: '1e999'"),
    ("proxy-retrieval batch larger than its chips", "proxy_retrieval",
     lambda i: ["--output_dir", str(i["root"] / "p24"), "--chips_per_bucket", "1", "--depressions_deg", "17",
                "--set", "batch_size=100000"], 2,
     r"error: batch_size: expected at most the 69 training chips of 1 depression\(s\) x 1 chips per bucket"),
    # --- YAML that says something other than it seems, for --config
    ("--config alias bomb (issue 75)", "generate",
     lambda i: _generate(i, "p25", "--config", _yaml(i, "p25.yaml", "a: &a [1, 1]\nd_az: [*a, *a]\n")), 2,
     r"YAML anchors and aliases \(& and \*\) are not read"),
    ("--config nested 5,000 deep (issue 75)", "generate",
     lambda i: _generate(i, "p26", "--config", _yaml(i, "p26.yaml", "d_az: " + "[" * 5000 + "]" * 5000)), 2,
     r"nested deeper than 16 levels"),
    ("--config key given twice (issue 75)", "simulate",
     lambda i: _simulate(i, "p27", "--config", _yaml(i, "p27.yaml", "seed: 1\nseed: 2\n")), 2,
     r"'seed' is given twice \(line 2\)"),
    ("--config input_domain decibel (issue 75)", "generate",
     lambda i: _generate(i, "p28", "--config", _yaml(i, "p28.yaml", "input_domain: decibel\n")), 2,
     r"error: input_domain: expected one of \['magnitude', 'normalized_db'\], got 'decibel'"),
    ("--config a Python tag", "simulate",
     lambda i: _simulate(i, "p29", "--config",
                         _yaml(i, "p29.yaml", "seed: !!python/object/apply:os.getpid []\n")), 2,
     r"--config .*p29.yaml"),
    ("--config a list, not a mapping", "simulate",
     lambda i: _simulate(i, "p30", "--config", _yaml(i, "p30.yaml", "- seed\n- 1\n")), 2,
     r"--config .*p30.yaml"),
    ("--config not UTF-8", "simulate",
     lambda i: _simulate(i, "p31", "--config", _yaml(i, "p31.yaml", b"seed: \xff\xfe\n")), 2,
     r"--config .*p31.yaml"),
    ("--config a folder", "simulate", lambda i: _simulate(i, "p32", "--config", str(i["root"])), 2,
     r"--config: '.*probes\d*' is a folder; expected a YAML or JSON file"),
    ("--config JSON key given twice", "simulate",
     lambda i: _simulate(i, "p33", "--config", _yaml(i, "p33.json", '{"seed": 1, "seed": 2}')), 2,
     r"--config '.*p33.json': \['seed'\] given twice; give each field once"),
    ("--config JSON nested 100,000 deep", "simulate",
     lambda i: _simulate(i, "p34", "--config", _yaml(i, "p34.json", DEEP_JSON)), 2,
     r"--config '.*p34.json': nested too deep to read"),
    ("--config JSON NaN", "simulate",
     lambda i: _simulate(i, "p35", "--config", _yaml(i, "p35.json", '{"azimuth_jitter_deg": NaN}')), 2,
     r"error: azimuth_jitter_deg: expected a finite number, got nan"),
    # --- output paths that cannot be folders
    ("generate output a dangling link (issue 75)", "generate", lambda i: _generate(i, "dangling"), 2,
     r"output_dir: '.*dangling' is a link to '.*nowhere', which does not exist; expected a folder"),
    ("generate output a file", "generate", lambda i: _generate(i, "a_file"), 2,
     r"output_dir: '.*a_file' is a file; expected a folder to write into"),
    ("simulate out a dangling link", "simulate", lambda i: _simulate(i, "dangling"), 2,
     r"out: '.*dangling' is a link to '.*nowhere', which does not exist; expected a folder"),
    ("simulate out inside a file", "simulate", lambda i: _simulate(i, "a_file/sub"), 2,
     r"out: '.*a_file/sub' is inside '.*a_file', which is a file; expected a folder to write into"),
    ("augment out a file", "augment", lambda i: _augment(i, "a_file"), 2,
     r"out: '.*a_file' is a file; expected a folder to write into"),
    ("augment out a dangling link", "augment", lambda i: _augment(i, "dangling"), 2,
     r"out: '.*dangling' is a link to '.*nowhere', which does not exist"),
    ("image_size off the pipeline's grid (issue 75: named `image`)", "generate",
     lambda i: _generate(i, "p41", "--set", "image_size=10"), 2,
     r"error: image_size: a multiple of 4 px for this pipeline \(its VAE and UNet downsampling\), got 10"),
    ("generate on the meta device (issue 75)", "generate",
     lambda i: _generate(i, "p42", "--set", "device=meta"), 2,
     r"error: device: 'meta' cannot compute here; expected one of \['cpu', 'cuda', 'mps', 'xpu'\]"),
    ("generate on a device name that is none", "generate",
     lambda i: _generate(i, "p43", "--set", "device=nonsense"), 2,
     r"error: device: 'nonsense' is not a torch device"),
    ("generate on a CUDA device past the last (issue 75: cuda without a GPU)", "generate",
     lambda i: _generate(i, "p44", "--set", "device=cuda:4096"), 2,
     r"error: device: 'cuda:4096', but this machine has \d+ cuda device\(s\)"),
    ("augment on the meta device", "augment", lambda i: _augment(i, "p45", "--set", "device=meta"), 2,
     r"error: device: 'meta' cannot compute here"),
    ("generate image a folder", "generate", lambda i: _generate(i, "p39", "--image", str(i["root"])), 2,
     r"error: .*image"),
    ("generate image missing", "generate",
     lambda i: _generate(i, "p40", "--image", str(i["root"] / "no.png")), 2, r"error: .*no.png"),
    # --- more commands and fields: bounds, types and names through flags, --set and --config
    ("interpolate alpha inf", "interpolate", lambda i: _interpolate(i, "p46", "--alpha", "inf"), 2,
     r"argument --alpha: invalid finite_float value: 'inf'"),
    ("interpolate alpha above 1", "interpolate", lambda i: _interpolate(i, "p47", "--alpha", "1.5"), 2,
     r"error: alpha must lie in \[0, 1\] \(1: the fine-tune\), got 1.5"),
    ("interpolate alpha negative", "interpolate", lambda i: _interpolate(i, "p48", "--alpha", "-0.5"), 2,
     r"error: alpha must lie in \[0, 1\] \(1: the fine-tune\), got -0.5"),
    ("interpolate alpha text by --set", "interpolate", lambda i: _interpolate(i, "p49", "--set", "alpha=abc"),
     2, r"error: --set alpha=abc: not a value of alpha \(not a number: 'abc'\)"),
    ("interpolate start missing", "interpolate",
     lambda i: _interpolate(i, "p50", "--alpha", "0.5", start=str(i["root"] / "nothere")), 2,
     r"error: start: expected a pipeline folder with model_index.json, got .*nothere"),
    ("interpolate finetuned a chip file", "interpolate",
     lambda i: _interpolate(i, "p51", "--alpha", "0.5", start=str(i["pipeline"]), finetuned=str(i["chip"])),
     2,
     r"error: finetuned: expected a pipeline folder with model_index.json, got .*chip.png"),
    ("evaluators learning rate negative", "evaluators",
     lambda i: ["--output_dir", str(i["root"] / "p52"), "--learning_rate", "-1"], 2,
     r"error: learning_rate must be > 0, got -1.0"),
    ("evaluators epochs negative", "evaluators",
     lambda i: ["--output_dir", str(i["root"] / "p53"), "--epochs", "-1"], 2,
     r"error: epochs must be >= 1, got -1"),
    ("evaluators image size 0", "evaluators",
     lambda i: ["--output_dir", str(i["root"] / "p54"), "--image_size", "0"], 2,
     r"error: image_size must be >= 1, got 0"),
    ("evaluators batch 0", "evaluators",
     lambda i: ["--output_dir", str(i["root"] / "p55"), "--train_batch_size", "0"], 2,
     r"error: train_batch_size must be >= 1, got 0"),
    ("evaluators learning rate 1e999 by --set", "evaluators",
     lambda i: ["--output_dir", str(i["root"] / "p56"), "--set", "learning_rate=1e999"], 2,
     r"--set learning_rate=1e999: not a value of learning_rate \(expected a finite number, got '1e999'\)"),
    ("table1 epochs negative", "table1", lambda i: ["--output_dir", str(i["root"] / "p57"), "--epochs", "-5"],
     2, r"error: epochs must be >= 1, got -5"),
    ("table1 learning rate nan", "table1",
     lambda i: ["--output_dir", str(i["root"] / "p58"), "--learning_rate", "nan"], 2,
     r"argument --learning_rate/--learning-rate: invalid finite_float value: 'nan'"),
    ("table1 steps 1e999 for an integer", "table1",
     lambda i: ["--output_dir", str(i["root"] / "p59"), "--set", "max_train_steps=1e999"], 2,
     r"--set max_train_steps=1e999: not a value of max_train_steps \(not an integer: '1e999'\)"),
    ("table1 an unknown preset", "table1",
     lambda i: ["--output_dir", str(i["root"] / "p60"), "--presets", "nonesuch"], 2,
     r"error: presets must be non-empty names from \['gaussian', .*\], got \['nonesuch'\]"),
    ("table1 image size 100000 (refused before any chip)", "table1",
     lambda i: ["--output_dir", str(i["root"] / "p61"), "--set", "image_size=100000"], 2,
     r"error: image_size must be <= 1024, got 100000"),
    ("synth-to-real epochs 0", "synth_to_real",
     lambda i: ["--output_dir", str(i["root"] / "p62"), "--sample", str(i["root"]), "--epochs", "0"], 2,
     r"error: epochs must be >= 1, got 0"),
    ("synth-to-real an unknown row", "synth_to_real",
     lambda i: ["--output_dir", str(i["root"] / "p63"), "--sample", str(i["root"]), "--rows", "nonesuch"], 2,
     r"error: rows must be non-empty names from \['none', .*\], got \['nonesuch'\]"),
    ("synth-to-real sample missing", "synth_to_real",
     lambda i: ["--output_dir", str(i["root"] / "p64"), "--sample", str(i["root"] / "nothere")], 2,
     r"error: sample: '.*nothere' is not a folder"),
    ("simclr epochs 0", "simclr", lambda i: ["--output_dir", str(i["root"] / "p65"), "--epochs", "0"], 2,
     r"error: epochs must be >= 1, got 0"),
    ("simclr a field it does not have by --set", "simclr",
     lambda i: ["--output_dir", str(i["root"] / "p66"), "--set", "batch_size=-1"], 2,
     r"error: --set 'batch_size=-1': no field 'batch_size'; expected one of \["),
    ("simclr image size 100000 (was simulated, then resized)", "simclr",
     lambda i: ["--output_dir", str(i["root"] / "p67"), "--set", "image_size=100000"], 2,
     r"error: image_size must be <= 1024, got 100000"),
    ("vae learning rate negative by --set", "vae",
     lambda i: ["--output_dir", str(i["root"] / "p68"), "--set", "learning_rate=-1"], 2,
     r"error: learning_rate must be > 0, got -1.0"),
    ("vae image size 100000", "vae",
     lambda i: ["--output_dir", str(i["root"] / "p69"), "--set", "image_size=100000"], 2,
     r"error: image_size must be <= 1024, got 100000"),
    ("prior learning rate nan by --set", "prior",
     lambda i: ["--output_dir", str(i["root"] / "p70"), "--set", "learning_rate=nan"], 2,
     r"--set learning_rate=nan: not a value of learning_rate \(expected a finite number, got 'nan'\)"),
    ("prior a bank of -1 vehicles", "prior",
     lambda i: ["--output_dir", str(i["root"] / "p71"), "--set", "num_vehicles=-1"], 2,
     r"error: num_vehicles must be >= 2, got -1"),
    ("simulate a class that is a path", "simulate",
     lambda i: [*_simulate(i, "p72"), "--classes", "../x"], 2,
     r"error: classes: \['../X'\] not among the simulator's classes \['TANK', 'APC', .*'SCOUT'\] \(--"),
    ("simulate an empty class name", "simulate", lambda i: [*_simulate(i, "p73"), "--classes", ""], 2,
     r"error: classes: \[''\] not among the simulator's classes \['TANK', 'APC', "),
    ("simulate a class given twice", "simulate",
     lambda i: [*_simulate(i, "p74"), "--classes", "TANK", "TANK"],
     2, r"error: classes: duplicate names in \['TANK', 'TANK', 'TANK'\] \(each would be written twice\)"),
    ("simulate size 0", "simulate", lambda i: _simulate(i, "p75", "--size", "0"), 2,
     r"error: size: expected an integer in \[16, 1024\] \(pixels\), got 0"),
    ("simulate instances -1", "simulate", lambda i: _simulate(i, "p76", "--instances", "-1"), 2,
     r"error: instances: expected an integer >= 1, got -1"),
    ("simulate 10^8 instances (counted, not listed)", "simulate",
     lambda i: _simulate(i, "p77", "--instances", "100000000"), 2,
     r"would write 2e\+08 chips, more than 200000; use a larger azimuth step"),
    ("simulate depression 95", "simulate", lambda i: _simulate(i, "p78", "--depressions_deg", "95"), 2,
     r"error: depressions_deg: expected values in \(0, 90\), got \[17.0, 95.0\]"),
    ("simulate depression nan", "simulate", lambda i: _simulate(i, "p79", "--depressions_deg", "nan"), 2,
     r"argument --depressions_deg/--depressions-deg: invalid finite_float value: 'nan'"),
    ("simulate azimuth step negative", "simulate", lambda i: _simulate(i, "p80", "--azimuth_step_deg", "-90"),
     2, r"error: azimuth_step_deg: expected a value in \(0, 360\], got -90.0"),
    ("generate d_el 1e999", "generate", lambda i: _generate(i, "p81", "--d_el", "1e999"), 2,
     r"argument --d_el/--d-el: invalid finite_float value: '1e999'"),
    ("generate d_el 91", "generate", lambda i: _generate(i, "p82", "--d_el", "91"), 2,
     r"error: `d_el` must lie in \(-90, 90\) degrees \(a difference of two depression angles in \(0, 90\)\), "
     r"got 91 "),
    ("generate d_el 90, no input depression", "generate", lambda i: _generate(i, "p82b", "--d_el", "90"), 2,
     r"error: `d_el` must lie in \(-90, 90\) degrees \(a difference of two depression angles in \(0, 90\)\), "
     r"got 90 "),
    ("generate three d_el for one d_az", "generate",
     lambda i: _generate(i, "p83", "--d_el", "0", "0", "0"), 2,
     r"error: d_el: give 1 value or one per d_az \(1\), got 3"),
    ("generate strength 0", "generate", lambda i: _generate(i, "p84", "--strength", "0"), 2,
     r"error: strength must lie in \(0, 1\], got 0.0"),
    ("generate strength 1.5", "generate", lambda i: _generate(i, "p85", "--strength", "1.5"), 2,
     r"error: strength must lie in \(0, 1\], got 1.5"),
    ("generate start_from a name that is none", "generate",
     lambda i: _generate(i, "p86", "--start_from", "bogus"), 2,
     r"argument --start_from/--start-from: invalid choice: 'bogus'"),
    ("generate 0 steps by --set", "generate",
     lambda i: _generate(i, "p87", "--set", "num_inference_steps=0"), 2,
     r"error: num_inference_steps must be an integer in \[1, 1,000\], got 0"),
    ("generate 10^9 steps by --set", "generate",
     lambda i: _generate(i, "p88", "--set", "num_inference_steps=1000000000"), 2,
     r"error: num_inference_steps must be an integer in \[1, 1,000\], got 1000000000"),
    ("generate num_images_per_prompt (not a generate field)", "generate",
     lambda i: _generate(i, "p89", "--set", "num_images_per_prompt=0"), 2,
     r"error: --set 'num_images_per_prompt=0': no field 'num_images_per_prompt'; expected one of \["),
    ("generate input depression 95", "generate", lambda i: _generate(i, "p90", "--input_depression", "95"), 2,
     r"error: input_depression must lie in \(0, 90\) degrees, got 95.0"),
    ("augment d_az nan", "augment", lambda i: [*_augment(i, "p91"), "--d_az", "nan"], 2,
     r"argument --d_az/--d-az: invalid finite_float value: 'nan'"),
    ("augment depression 1e999", "augment", lambda i: _augment(i, "p92", "--depressions_deg", "1e999"), 2,
     r"argument --depressions_deg/--depressions-deg: invalid finite_float value: '1e999'"),
    ("augment depression no chip has", "augment", lambda i: _augment(i, "p93", "--depressions_deg", "45"), 2,
     r"error: depressions_deg: no chip of the selected classes at \[45.0\] deg"),
    ("augment chips per class -1", "augment", lambda i: _augment(i, "p94", "--max_chips_per_class", "-1"), 2,
     r"error: max_chips_per_class must be >= 1 or None, got -1"),
    ("augment a class the data lacks", "augment", lambda i: _augment(i, "p95", "--classes", "NOPE"), 2,
     r"error: classes: \['NOPE'\] not in the dataset, which lists \['TANK'\]"),
    ("augment an index row climbing out of its folder", "augment",
     lambda i: _augment(i, "p97", data=_index_with(i, "idx_dotdot", "path", "../chip.png")), 2,
     r"error: .*idx_dotdot/index.csv:2: column 'path' '../chip.png' leads out of the data folder"),
]  # fmt: skip


@pytest.mark.parametrize(("command", "argv", "status", "line"), [p[1:] for p in PROBES],
                         ids=[p[0] for p in PROBES])  # fmt: skip
def test_a_hostile_input_ends_in_one_line_and_its_exit_status(inputs, capsys, command, argv, status, line):
    args = argv(inputs)
    ending = run_console(command, args, capsys)
    assert ending.status == status, ending
    assert re.search(line, ending.line), ending.line
    out = Path(args[args.index("--output_dir" if "--output_dir" in args else "--out") + 1])
    if status and out.name.startswith("p"):  # refused before any work: nothing written
        assert not out.exists(), out


#: Where each command writes its chips or views (the write point a full or read-only disk fails).
WRITE_POINTS = {"generate": "numpy.save", "simulate": "numpy.save", "augment": "os.replace"}


@pytest.mark.parametrize("command", sorted(WRITE_POINTS))
@pytest.mark.parametrize(("code", "advice"), [(errno.ENOSPC, "free space on that disk"),
                                              (errno.EROFS, "that file system is read-only")])  # fmt: skip
def test_a_full_or_read_only_disk_part_way_ends_in_one_line_naming_the_path_and_the_run_continues(
    inputs, capsys, monkeypatch, command, code, advice
):
    """The disk fails at the command's first chip or view (simulated: the tests may run as root, whom a
    read-only folder does not stop): one line, exit 74, naming the file; once the disk is fixed, the same
    command with ``--resume`` finishes."""
    out = f"disk_{command}_{code}"
    argv = {"generate": _generate, "simulate": _simulate, "augment": _augment}[command](inputs, out)
    module, _, name = WRITE_POINTS[command].rpartition(".")
    target = sys.modules[module]
    real = getattr(target, name)
    failing = {"armed": True}

    def fail(*args, **kwargs):
        written = str(args[1] if name == "replace" else args[0])
        if failing["armed"] and written.endswith((".npy", ".png")):  # a chip or view, not a record
            raise OSError(code, os.strerror(code))
        return real(*args, **kwargs)

    monkeypatch.setattr(target, name, fail)
    ending = run_console(command, argv, capsys)
    assert ending.status == 74, ending
    folder = inputs["root"] / out
    assert ending.line.startswith(f"sar-zero123-{command}: error: [Errno {code}] could not write '{folder}/")
    assert f"{os.strerror(code)}; " in ending.line and advice in ending.line
    assert ending.line.endswith("(--traceback shows where)")
    failing["armed"] = False
    resume = [] if command == "augment" else ["--resume"]  # augment resumes by default
    again = run_console(command, [*argv, *resume], capsys)
    assert again.status == 0, again
    assert again.out.splitlines()[-1] == str(folder)


def test_a_read_only_output_folder_is_refused_before_any_work(inputs, capsys):
    """A real read-only folder (chmod), where the file system enforces it: not for root, whom it does not
    stop (the simulated probe above covers that case)."""
    folder = inputs["root"] / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("running as a user whom chmod does not stop (root)")
        for command, argv in (("generate", _generate(inputs, "read_only")),
                              ("simulate", _simulate(inputs, "read_only")),
                              ("augment", _augment(inputs, "read_only"))):  # fmt: skip
            ending = run_console(command, argv, capsys)
            expected = r"'.*read_only' cannot be written; name a writable folder"
            assert ending.status == 2 and re.search(expected, ending.line), ending
    finally:
        folder.chmod(0o755)


#: (id, ``--set`` value or recipe text, a regex the refusal matches): quickstart settings and recipes,
#: refused while the stages are planned, before any runs.
QUICKSTART_PROBES: list[tuple[str, str, str]] = [
    ("azimuth step 1e-9 (issue 75)", "simulate.azimuth_step_deg=1e-9",
     r"azimuth_step_deg=1e-09 .* would write .* chips, more than 200000"),
    ("fine-tune learning rate 1e999 (issue 75)", "finetune.learning_rate=1e999",
     r"--set finetune.learning_rate=1e999: not a value of finetune.learning_rate \(expected a finite number"),
    ("pfm_min_snr 1e999 (issue 75)", "finetune.pfm_min_snr=1e999",
     r"not a value of finetune.pfm_min_snr \(expected a finite number, got '1e999'\)"),
    ("fine-tune steps 1_0", "finetune.max_train_steps=1_0",
     r"not a value of finetune.max_train_steps \(not an integer: '1_0'\)"),
    ("VAE learning rate 0x10", "vae.learning_rate=0x10",
     r"not a value of vae.learning_rate \(not a number: '0x10'\)"),
    ("classes count as a complex number", "simulate.instances=1j", r"not an integer: '1j'"),
    ("recipe repeating a key (issue 75)", "finetune:\n  finetune_steps: 2\n  finetune_steps: 5000000\n",
     r"'finetune_steps' is given twice \(line 3\)"),
    ("recipe repeating a section (issue 75)", "finetune:\n  finetune_steps: 2\nfinetune:\n  ema_decay: 0.9\n",
     r"'finetune' is given twice \(line 3\)"),
    ("recipe alias bomb (issue 75)", "x: &a [1]\ndata:\n  classes: [*a, *a]\n",
     r"YAML anchors and aliases \(& and \*\) are not read"),
    ("recipe nested 5,000 deep (issue 75)", "data:\n  classes: " + "[" * 5000 + "]" * 5000 + "\n",
     r"nested deeper than 16 levels"),
    ("recipe number in YAML 1.1's loose forms", "finetune:\n  finetune_steps: 1_000\n",
     r"'1_000' \(line 2\) is a number only in YAML 1.1's loose forms \(read as 1000\)"),
    ("recipe learning rate .inf", "evaluators:\n  evaluator_learning_rate: .inf\n",
     r"evaluator_learning_rate"),
    ("a class the simulator lacks", "simulate.classes=['NOPE', 'TANK']",
     r"classes: \['NOPE'\] not among the simulator's classes \['TANK', 'APC', 'TRUCK', .*'SCOUT'\]"),
    ("one class (the last is held out)", "simulate.classes=APC",
     r"must name at least two distinct classes, got \['APC'\]; expected names from \['TANK', 'APC', "),
]  # fmt: skip


@pytest.mark.parametrize(("setting", "line"), [p[1:] for p in QUICKSTART_PROBES],
                         ids=[p[0] for p in QUICKSTART_PROBES])  # fmt: skip
def test_a_hostile_quickstart_setting_is_refused_in_one_line_before_any_stage_runs(
    tmp_path, capsys, monkeypatch, setting, line
):
    import sar_zero123.stages.quickstart as quickstart

    def plan_only(config):  # what run_quickstart does first; a probe never runs a stage
        quickstart.plan_stages(config)
        pytest.fail("the quickstart planned its stages: the setting was accepted")

    monkeypatch.setattr(quickstart, "run_quickstart", plan_only)
    if "\n" in setting:  # a recipe file
        (tmp_path / "recipe.yaml").write_text(setting)
        argv = ["--recipe", str(tmp_path / "recipe.yaml")]
    else:
        argv = ["--set", setting]
    ending = run_console("quickstart", ["--output_dir", str(tmp_path / "run"), *argv], capsys)
    assert ending.status == 2, ending
    assert re.search(line, ending.line), ending.line
    assert ending.line.startswith("sar-zero123-quickstart: error: ") and not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("bounds", "accepted"),
    [((-1e30, 0.0), False), ((-60.0, 1e308), False), ((-1e308, 1e308), False), ((-61.0, 0.0), False),
     ((-60.0, 0.0), True), ((-60.0, 24.4912), True)],
)  # fmt: skip
def test_proxy_decibel_bounds_past_any_view_are_refused_by_name(bounds, accepted):
    """Decibels below zero magnitude's or above the largest float32's make every view flat (or NaN)."""
    from sar_zero123.model.proxy import DEFAULT_PROXY, check_proxy_settings

    proxy = {**DEFAULT_PROXY, "min_db": bounds[0], "max_db": bounds[1]}
    if accepted:
        assert check_proxy_settings(proxy)["min_db"] == bounds[0]
        return
    with pytest.raises(ValueError, match=r"^proxy.min_db, proxy.max_db: expected decibels in \[-60, 770.6\]"):
        check_proxy_settings(proxy)


def test_the_largest_chip_side_is_declared_once_in_domain():
    """``MAX_IMAGE_SIZE`` has one declaration (``domain.py``); every stage and command that bounds a chip side
    imports it, so the bound cannot drift between them."""
    import sar_zero123
    import sar_zero123.domain as domain
    import sar_zero123.generate as generate
    import sar_zero123.stages.evaluate as evaluate
    import sar_zero123.stages.evaluators as evaluators

    root = Path(sar_zero123.__file__).parent
    declared = sorted(path.relative_to(root).as_posix() for path in root.rglob("*.py")
                      if re.search(r"^MAX_IMAGE_SIZE\s*[:=]", path.read_text(), re.MULTILINE))  # fmt: skip
    assert declared == ["domain.py"]
    assert domain.MAX_IMAGE_SIZE == 1024
    for module in (generate, evaluate, evaluators):
        assert module.MAX_IMAGE_SIZE == domain.MAX_IMAGE_SIZE and "MAX_IMAGE_SIZE" not in module.__all__


@pytest.fixture(scope="module")
def counted_pipe() -> tuple[SARZero123Pipeline, dict[str, int]]:
    """The tiny random pipeline, counting its UNet calls (a refusal comes before the first)."""
    pipe = SARZero123Pipeline(**get_dummy_components())
    pipe.set_progress_bar_config(disable=True)
    calls = {"unet": 0}
    forward = pipe.unet.forward

    def counting(*args, **kwargs):
        calls["unet"] += 1
        return forward(*args, **kwargs)

    pipe.unet.forward = counting
    return pipe, calls


LATENT = (1, 4, 16, 16)  # one sample of the 32 px dummy pipeline
#: (id, call arguments, a regex the one-line ValueError matches): SARZero123Pipeline.__call__ refuses each
#: before any UNet call, naming the argument and what it expected, as diffusers' check_inputs does.
CALL_PROBES: list[tuple[str, dict, str]] = [
    ("d_el 80 from a 17 deg input (target 97)", {"d_el": 80.0, "input_depression_deg": 17.0},
     r"^`d_el` 80 from an input depression of 17 deg asks for a target depression of 97 deg; "
     r"input_depression_deg \+ d_el must lie in \(0, 90\) degrees$"),
    ("d_el -20 from a 17 deg input (target -3)", {"d_el": -20.0, "input_depression_deg": 17.0},
     r"^`d_el` -20 from an input depression of 17 deg asks for a target depression of -3 deg"),
    ("one of two targets at exactly 90", {"batch": 2, "d_el": [10.0, 50.0], "input_depression_deg": 40.0},
     r"^`d_el` 50 from an input depression of 40 deg asks for a target depression of 90 deg"),
    ("steps 0", {"num_inference_steps": 0}, r"^`num_inference_steps` must be an integer >= 1, got 0$"),
    ("steps -1", {"num_inference_steps": -1}, r"^`num_inference_steps` must be an integer >= 1, got -1$"),
    ("steps 1.5", {"num_inference_steps": 1.5}, r"^`num_inference_steps` must be an integer >= 1, got 1.5$"),
    ("steps True", {"num_inference_steps": True},
     r"^`num_inference_steps` must be an integer >= 1, got True$"),
    ("steps 10**9", {"num_inference_steps": 10**9},
     r"^`num_inference_steps` must be <= 1000 \(the scheduler's num_train_timesteps\), got 1000000000$"),
    ("guidance nan", {"guidance_scale": float("nan")}, r"^`guidance_scale` must be finite, got nan$"),
    ("guidance inf", {"guidance_scale": float("inf")}, r"^`guidance_scale` must be finite, got inf$"),
    ("guidance negative", {"guidance_scale": -1.0},
     r"^`guidance_scale` must be >= 0 \(<= 1 turns guidance off\), got -1.0$"),
    ("guidance a str", {"guidance_scale": "3"}, r"^`guidance_scale` must be a real number, got str '3'$"),
    ("guidance a bool", {"guidance_scale": True}, r"^`guidance_scale` must be a real number, got bool True$"),
    ("strength 0", {"strength": 0.0}, r"^strength must lie in \(0, 1\], got 0.0$"),
    ("strength -0.5", {"strength": -0.5}, r"^strength must lie in \(0, 1\], got -0.5$"),
    ("strength 1.5", {"strength": 1.5}, r"^strength must lie in \(0, 1\], got 1.5$"),
    ("strength nan", {"strength": float("nan")}, r"^strength must lie in \(0, 1\], got nan$"),
    ("latents of another shape", {"latents": torch.zeros(1, 4, 8, 8)},
     r"^`latents` must have shape \(1, 4, 16, 16\), got \(1, 4, 8, 8\)$"),
    ("latents NaN", {"latents": torch.full(LATENT, float("nan"))}, r"^`latents` contains NaN or inf values$"),
    ("latents int64", {"latents": torch.zeros(LATENT, dtype=torch.int64)},
     r"^`latents` must be a floating-point tensor \(Gaussian noise\), got torch.int64$"),
    ("latents bool", {"latents": torch.zeros(LATENT, dtype=torch.bool)},
     r"^`latents` must be a floating-point tensor \(Gaussian noise\), got torch.bool$"),
    ("latents complex", {"latents": torch.zeros(LATENT, dtype=torch.complex64)},
     r"^`latents` must be a floating-point tensor \(Gaussian noise\), got torch.complex64$"),
    ("latents a numpy array", {"latents": np.zeros(LATENT, np.float32)},
     r"^`latents` must be a torch.Tensor of shape \(1, 4, 16, 16\), got ndarray$"),
    ("two generators for one sample", {"generator": [torch.Generator(), torch.Generator()]},
     r"^`generator` is a list of 2 generators; expected one per output sample, batch 1 x "
     r"num_images_per_prompt 1 = 1$"),
    ("no generators in a list", {"generator": []}, r"^`generator` is a list of 0 generators"),
    ("a seed as the generator", {"generator": 0},
     r"^`generator` must be a torch.Generator .*got 0; a seed s is torch.Generator\(\).manual_seed\(s\)$"),
    ("a seed string as the generator", {"generator": "0"},
     r"^`generator` must be a torch.Generator .*got '0'"),
    ("images per prompt True", {"num_images_per_prompt": True},
     r"^`num_images_per_prompt` must be an integer in \[1, 1,024\], got True$"),
    ("images per prompt 10**6", {"num_images_per_prompt": 10**6},
     r"^`num_images_per_prompt` must be an integer in \[1, 1,024\], got 1000000$"),
]  # fmt: skip


@pytest.mark.parametrize(("kwargs", "line"), [p[1:] for p in CALL_PROBES], ids=[p[0] for p in CALL_PROBES])
def test_a_hostile_call_argument_is_refused_in_one_value_error_before_any_unet_call(
    counted_pipe, kwargs, line
):
    pipe, calls = counted_pipe
    calls["unet"] = 0
    arguments = {"d_az": 30.0, "num_inference_steps": 2, "output_type": "np", **kwargs}
    batch = arguments.pop("batch", 1)
    with pytest.raises(ValueError) as refused:
        pipe(torch.full((batch, 1, 32, 32), 0.5), **arguments)
    assert re.search(line, str(refused.value)) and "\n" not in str(refused.value), refused.value
    assert calls["unet"] == 0


@pytest.mark.parametrize(
    "kwargs",
    [{"num_inference_steps": np.int64(2)}, {"num_images_per_prompt": np.int64(2)}, {"guidance_scale": 0.0},
     {"guidance_scale": 1.0}, {"strength": 0.5}, {"strength": 1.0},
     {"latents": torch.zeros(LATENT, dtype=torch.float64)},
     {"latents": torch.zeros(LATENT, dtype=torch.float16)},
     {"d_el": 72.0, "input_depression_deg": 17.0}, {"d_el": -16.5, "input_depression_deg": 17.0}],
    ids=["steps np.int64", "images np.int64", "guidance 0", "guidance 1", "strength 0.5", "strength 1",
         "latents float64", "latents float16", "target 89", "target 0.5"],
)  # fmt: skip
def test_valid_edge_values_of_a_call_still_sample(counted_pipe, kwargs):
    pipe, calls = counted_pipe
    calls["unet"] = 0
    arguments = {"d_az": 30.0, "num_inference_steps": 2, "output_type": "np", **kwargs}
    generator = torch.Generator().manual_seed(0)
    images = pipe(torch.full((1, 1, 32, 32), 0.5), generator=generator, **arguments).images
    assert images.shape == (arguments.get("num_images_per_prompt", 1), 32, 32, 1)
    assert np.isfinite(images).all() and calls["unet"] >= 1


def test_generate_refuses_a_target_depression_past_the_horizon_from_a_depression_it_was_given(inputs, capsys):
    """The dummy pipeline's pose does not take the input's depression; a given one still bounds the target
    (40 + 60 = 100 deg) by the shared pose check (``view_request.check_target_depression``), before the
    pipeline is called or the folder opened."""
    argv = _generate(inputs, "p96", "--d_el", "60", "--input_depression", "40")
    ending = run_console("generate", argv, capsys)
    assert ending.status == 2, ending
    assert ending.line == (
        "sar-zero123-generate: error: `d_el` 60 from an input depression of 40 deg asks for a target "
        "depression of 100 deg; input_depression_deg + d_el must lie in (0, 90) degrees (--traceback shows "
        "where)"
    )
    assert not (inputs["root"] / "p96").exists()


@pytest.mark.parametrize(
    ("seed", "line"),
    [(1.5, r"^`seed` must be an integer \(view i uses seed \+ i\), got float 1.5$"),
     (True, r"^`seed` must be an integer \(view i uses seed \+ i\), got bool True$"),
     ("0", r"^`seed` must be an integer \(view i uses seed \+ i\), got str '0'$"),
     (2**63 - 1, r"^`seed` \+ view index must lie within int64 for 2 view\(s\), got 9223372036854775807$")],
)  # fmt: skip
def test_generate_views_refuses_a_seed_that_is_no_int64_integer(counted_pipe, seed, line):
    from sar_zero123.generate import generate_views
    from sar_zero123.model.sampler import SamplerSettings

    pipe, calls = counted_pipe
    calls["unet"] = 0
    chip = np.full((32, 32), 0.5, np.float32)
    with pytest.raises(ValueError, match=line):
        generate_views(pipe, chip, [0.0, 90.0], [0.0], SamplerSettings(num_inference_steps=1), seed)
    assert calls["unet"] == 0
