"""Bad inputs at the command line: each console script's exit status and the one line it prints.

Every case runs a console script's entry point (``sar_zero123.cli:console.<command>``, what pip's launcher
calls) in this process on ``sys.argv``, on a tiny pipeline and fabricated files: a refusal exits 2 with one
line ``sar-zero123-<command>: error: <message>`` on stderr, a success exits 0 with its output folder as the
last line on stdout. Where a case could move an input or run code a file smuggles in, the test also checks
that the input's bytes are unchanged and that no code ran.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
from dummies import get_dummy_components

from sar_zero123 import cli
from sar_zero123.data import SCALING_FILE, DecibelScaling
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.runs.lock import release_output_folder
from sar_zero123.sim import simulate_dataset


class _Payload:
    """A pickle that, when loaded, writes the file named by ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').write('ran')",))


def run_console(monkeypatch, capsys, command: str, *argv: str) -> tuple[int, list[str], list[str]]:
    """``sar-zero123-<command> argv`` as its console script: exit status, stdout lines, stderr lines."""
    monkeypatch.setattr(sys, "argv", [f"sar-zero123-{command}", *argv])
    status = getattr(cli.console, command.replace("-", "_"))()
    captured = capsys.readouterr()
    return status, captured.out.splitlines(), captured.err.splitlines()


def refusal(monkeypatch, capsys, command: str, *argv: str) -> str:
    """The one line a refused command prints: exit status 2, nothing on stdout, and on stderr (beside the
    loaders' progress bars) one error line, the last."""
    status, out, err = run_console(monkeypatch, capsys, command, *argv)
    prefix, suffix = f"sar-zero123-{command}: error: ", " (--traceback shows where)"
    errors = [line for line in err if ": error: " in line]
    assert (status, out, len(errors)) == (2, [], 1), (status, out, err)
    assert [line for line in err if line.strip()][-1] == errors[0], err
    assert errors[0].startswith(prefix) and errors[0].endswith(suffix), errors[0]
    return errors[0][len(prefix) : -len(suffix)]


def tree_digest(folder: Path) -> str:
    """SHA-256 over every file's relative path and bytes under ``folder``."""
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(folder)).encode() + path.read_bytes())
    return digest.hexdigest()


@pytest.fixture(scope="module")
def pipeline_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("pipeline") / "pipe"
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def chip_png(tmp_path_factory) -> Path:
    pixels = np.random.default_rng(0).integers(0, 256, size=(40, 40), dtype=np.uint8)
    path = tmp_path_factory.mktemp("chip") / "chip.png"
    PIL.Image.fromarray(pixels, mode="L").save(path)
    return path


def generate_args(pipeline_dir: Path, image: Path, out: Path, *extra: str) -> list[str]:
    return ["--pipeline", str(pipeline_dir), "--image", str(image), "--d_az", "30",
            "--num_inference_steps", "1", "--output_dir", str(out), *extra]  # fmt: skip


# ------------------------------------------------------------------------------------ chip files
def test_generate_refuses_an_npy_holding_a_pickled_object_without_unpickling_it(
    monkeypatch, capsys, pipeline_dir, tmp_path
):
    marker = tmp_path / "pwned"
    image = tmp_path / "pickled.npy"
    np.save(image, np.array([_Payload(marker)], dtype=object), allow_pickle=True)
    message = refusal(monkeypatch, capsys, "generate", *generate_args(pipeline_dir, image, tmp_path / "out"))
    assert message == f"{image}: .npy chip must hold real numbers, got dtype object"
    assert not marker.exists()


def test_generate_refuses_a_complex_npy_naming_its_dtype(monkeypatch, capsys, pipeline_dir, tmp_path):
    image = tmp_path / "complex.npy"
    np.save(image, np.ones((40, 40), dtype=np.complex64))
    message = refusal(monkeypatch, capsys, "generate", *generate_args(pipeline_dir, image, tmp_path / "out"))
    assert message == f"{image}: .npy chip must hold real numbers, got dtype complex64"


def test_generate_reads_an_rgba_png_as_one_channel_exits_0_and_prints_its_folder_last(
    monkeypatch, capsys, pipeline_dir, tmp_path
):
    image = tmp_path / "rgba.png"
    rgba = np.random.default_rng(1).integers(0, 256, size=(40, 40, 4), dtype=np.uint8)
    PIL.Image.fromarray(rgba, "RGBA").save(image)
    out = tmp_path / "out"
    status, lines, _ = run_console(monkeypatch, capsys, "generate", *generate_args(pipeline_dir, image, out))
    assert status == 0 and lines[-1] == str(out)
    assert np.load(out / "view_00_daz+030.00_del+00.00.npy").shape == (32, 32)


def test_generate_refuses_a_missing_config_file(monkeypatch, capsys, pipeline_dir, chip_png, tmp_path):
    missing = tmp_path / "nope.yaml"
    argv = generate_args(pipeline_dir, chip_png, tmp_path / "out", "--config", str(missing))
    assert refusal(monkeypatch, capsys, "generate", *argv) == f"--config: no such file {str(missing)!r}"
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------ bounds
def test_simulate_refuses_a_chip_size_beyond_its_bound_before_any_work(monkeypatch, capsys, tmp_path):
    message = refusal(monkeypatch, capsys, "simulate", "--out", str(tmp_path / "sim"), "--size", "100000")
    assert message == "size: expected an integer in [16, 1024] (pixels), got 100000"
    assert not (tmp_path / "sim").exists()


# ------------------------------------------------------------------------------------ inputs never moved
@pytest.fixture(scope="module")
def augment_inputs(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny depression-conditioned pipeline with a unit-magnitude scaling, and a two-chip dataset."""
    root = tmp_path_factory.mktemp("augment")
    pipe = build_sar_zero123("tiny", input_depression=True)
    pipe.save_pretrained(root / "pipe")
    (root / "pipe" / SCALING_FILE).write_text(json.dumps(DecibelScaling.for_unit_magnitude().to_dict()))
    data = simulate_dataset(root / "data", classes=("TANK",), instances=1, azimuth_step_deg=180,
                            depressions_deg=(17.0,), size=32)  # fmt: skip
    return root / "pipe", data


def augment_args(pipeline: Path, data: Path, out: Path, *extra: str) -> list[str]:
    return ["--data", str(data), "--pipeline", str(pipeline), "--out", str(out), "--d_az", "30",
            "--num_inference_steps", "1", *extra]  # fmt: skip


def test_augment_restart_into_a_link_to_its_own_data_is_refused_and_moves_nothing(
    monkeypatch, capsys, augment_inputs, tmp_path
):
    pipeline, original = augment_inputs
    data = Path(shutil.copytree(original, tmp_path / "data"))
    link = tmp_path / "link_to_data"
    link.symlink_to(data, target_is_directory=True)
    before = tree_digest(data)
    message = refusal(monkeypatch, capsys, "augment", *augment_args(pipeline, data, link, "--restart"))
    assert message.startswith(f"restart: out {str(link)!r} holds this run's inputs (data: {data})")
    release_output_folder(link)  # what the command's process does at exit: its lock file goes
    assert tree_digest(data) == before and link.resolve() == data


@pytest.mark.parametrize("outside", ["absolute", "relative"])
def test_augment_reads_an_absolute_chip_path_refuses_one_climbing_out_and_writes_only_under_out(
    monkeypatch, capsys, augment_inputs, tmp_path, outside
):
    pipeline, original = augment_inputs
    data = Path(shutil.copytree(original, tmp_path / "data"))
    lines = (data / "index.csv").read_text().splitlines()
    header = lines[0].split(",")
    first = lines[1].split(",")
    secret = tmp_path / "secret.npy"
    shutil.copy(data / first[header.index("path")], secret)
    first[header.index("path")] = str(secret) if outside == "absolute" else "../secret.npy"
    (data / "index.csv").write_text("\n".join([lines[0], ",".join(first), *lines[2:]]) + "\n")
    before, secret_bytes = set(tmp_path.rglob("*")), secret.read_bytes()
    out = tmp_path / "out"
    if outside == "relative":  # a relative path is read under the folder, never above it
        message = refusal(monkeypatch, capsys, "augment", *augment_args(pipeline, data, out))
        assert message == (
            f"{data / 'index.csv'}:2: column 'path' '../secret.npy' leads out of the data folder {data}; a "
            "relative path must stay inside it"
        )
        release_output_folder(out)  # what the command's process does at exit: its lock file goes
        assert set(tmp_path.rglob("*")) == before and secret.read_bytes() == secret_bytes
        return
    # an absolute path names its file outright (augment lists the real chips it keeps in place so)
    status, printed, _ = run_console(monkeypatch, capsys, "augment", *augment_args(pipeline, data, out))
    assert status == 0 and printed[-1] == str(out)
    written = {path for path in set(tmp_path.rglob("*")) - before if path != out}
    assert written and all(path.is_relative_to(out) for path in written)
    assert secret.read_bytes() == secret_bytes


@pytest.fixture(scope="module")
def interpolate_start(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("interpolate") / "start"
    SARZero123Pipeline(**get_dummy_components()).save_pretrained(folder)
    return folder


@pytest.mark.parametrize(("inside", "expected"), [("unet", "lies inside"), ("", "holds")])
def test_interpolate_restart_into_its_finetuned_pipeline_is_refused_and_the_pipeline_still_loads(
    monkeypatch, capsys, interpolate_start, tmp_path, inside, expected
):
    tuned = Path(shutil.copytree(interpolate_start, tmp_path / "tuned"))
    out = tuned / inside if inside else tuned
    before = tree_digest(tuned)
    argv = [
        "--start",
        str(interpolate_start),
        "--finetuned",
        str(tuned),
        "--output_dir",
        str(out),
        "--restart",
    ]
    message = refusal(monkeypatch, capsys, "interpolate", *argv)
    assert message.startswith(
        f"restart: output_dir {str(out)!r} {expected} this run's inputs (finetuned: {tuned}"
    )
    release_output_folder(out)  # what the command's process does at exit: its lock file goes
    assert tree_digest(tuned) == before
    SARZero123Pipeline.from_pretrained(tuned)
