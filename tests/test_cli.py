"""One command-line convention: every entry point is a console script with its stage's config as flags."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

from sar_zero123 import cli
from sar_zero123.config import advanced_fields, field_comments, parse_config
from sar_zero123.runs.refusals import REFUSED
from sar_zero123.stages.finetune import FinetuneConfig
from sar_zero123.stages.simclr import PretrainSimCLRConfig
from sar_zero123.stages.simulate import SimulateConfig
from sar_zero123.stages.vae import TrainVAEConfig

ROOT = Path(__file__).resolve().parents[1]


def test_every_command_is_a_console_script_calling_its_function():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    expected = {command.script: f"sar_zero123.cli:console.{command.function}" for command in cli.COMMANDS}
    assert scripts == {**expected, "sar-zero123-demo": "sar_zero123.demo:main"}  # the demo: no stage
    for command in cli.COMMANDS:
        assert callable(getattr(cli, command.function)) and callable(getattr(cli.console, command.function))
        assert command.script == "sar-zero123-" + command.function.replace("_", "-")
        also = command.also.split()[-1]
        if also.startswith("train/"):  # the train/ script calls the same function
            assert f"cli.{command.function}(argv)" in (ROOT / also).read_text()


def test_console_scripts_exit_0_when_their_command_returns_and_pass_failures_on(monkeypatch, capsys):
    """The launcher calls sys.exit(<what the entry point returns>): a Path or dict would print and exit 1. A
    returned path is the last line on stdout, for a shell to read."""
    for command in cli.COMMANDS:
        seen = []
        fake = lambda argv=None, seen=seen: seen.append(argv) or Path("out")  # noqa: E731
        monkeypatch.setattr(cli, command.function, fake)
        assert getattr(cli.console, command.function)() == 0 and seen == [None]  # argv: sys.argv
        assert capsys.readouterr().out.splitlines()[-1] == "out"
    monkeypatch.setattr(cli, "finetune", lambda argv=None: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):  # not a refusal: its traceback
        cli.console.finetune()
    with pytest.raises(AttributeError):
        cli.console.not_a_command  # noqa: B018


def test_a_refusal_at_the_command_line_is_one_line_and_exit_status_2_unless_asked_for_its_traceback(
    monkeypatch, capsys
):
    """A command that refuses its input (ValueError, FileNotFoundError, ...) prints one line naming the
    field on stderr and exits 2; ``--traceback`` (removed before the flags are parsed) lets it raise."""
    errors = (ValueError("pfm_weight: expected a value >= 0,\n  got -1"), FileNotFoundError("data: no index"))
    for error in errors:
        seen = []

        def refuse(argv=None, error=error, seen=seen):
            seen.append(list(sys.argv[1:]))
            raise error

        monkeypatch.setattr(cli, "finetune", refuse)
        monkeypatch.setattr(sys, "argv", ["finetune_pfm.py", "--pfm_weight", "-1"])
        assert cli.console.finetune() == REFUSED == 2
        expected = " ".join(str(error).split())
        line = f"sar-zero123-finetune: error: {expected} (--traceback shows where)\n"
        assert capsys.readouterr().err == line
        monkeypatch.setattr(sys, "argv", ["finetune_pfm.py", "--traceback", "--pfm_weight", "-1"])
        with pytest.raises(type(error)):
            cli.console.finetune()
        assert seen == [["--pfm_weight", "-1"]] * 2  # the flag never reaches the config parser
    # a real command (the lightest to import): a missing pipeline, refused in one line by its entry point
    done = subprocess.run([sys.executable, "-m", "sar_zero123.interpolate", "--start", "/nonexistent/start",
                           "--finetuned", "/nonexistent/tuned", "--output_dir", "/nonexistent/out"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        "sar-zero123-interpolate: error: start: expected a pipeline folder with model_index.json, got "
        "/nonexistent/start (--traceback shows where)"
    ]


@pytest.mark.parametrize("command", cli.COMMANDS, ids=lambda command: command.script)
def test_help_lists_every_field_of_the_config_with_underscores(command, capsys):
    config = cli.config_class(command)
    with pytest.raises(SystemExit) as done:
        getattr(cli, command.function)(["--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    fields = [field.name for field in dataclasses.fields(config) if field.init]
    # a flag per chosen setting; the settings without a flag (--set FIELD=VALUE) listed at the end
    advanced = advanced_fields(config)
    assert set(advanced) <= set(fields), (
        f"{command.script}: ADVANCED_FIELDS names no field {set(advanced) - set(fields)}"
    )
    flags, _, settings = text.partition("settings without a flag (--set FIELD=VALUE")
    missing = [name for name in fields if name not in advanced and not re.search(rf"--{name}\b", flags)]
    assert not missing, f"{command.script} --help lacks {missing}"
    unlisted = [name for name in advanced if not re.search(rf"^  {name} \(default: ", settings, re.M)]
    assert not unlisted and not any(re.search(rf"--{name}\b", flags) for name in advanced), unlisted
    assert "--set FIELD=VALUE" in flags or "set" in fields  # any field, on every command
    undocumented = [name for name in fields if name not in field_comments(config)]
    assert not undocumented, f"{command.script}: no help (a comment on or above the field): {undocumented}"
    # every command that writes a run folder continues it with --resume and starts over with --restart
    assert re.search(r"--resume\b", text) and re.search(r"--restart\b", text)


def test_the_readme_command_table_matches_the_commands():
    readme = (ROOT / "README.md").read_text()
    table = readme[readme.index("<!-- COMMANDS -->") : readme.index("<!-- /COMMANDS -->")]
    rows = [line for line in table.splitlines() if line.startswith("| `sar-zero123")]
    listed = [tuple(cell.strip().strip("`") for cell in row.strip("|").split("|")) for row in rows]
    expected = [(c.script, c.also, c.stage, c.config.split(":")[1], c.summary) for c in cli.COMMANDS]
    assert listed == expected


def test_resume_is_the_latest_checkpoint_for_training_stages():
    for config in (FinetuneConfig, TrainVAEConfig, PretrainSimCLRConfig):
        extra = ["--pfm_weight", "0"] if config is FinetuneConfig else []
        assert parse_config(config, ["--resume", *extra]).resume_from_checkpoint == "latest"
        assert parse_config(config, extra).resume_from_checkpoint is None


def test_simulate_takes_its_fields_with_underscores_or_dashes_and_refuses_its_first_flags():
    new = ["--azimuth_step_deg", "120", "--depressions_deg", "17", "--set", "azimuth_jitter_deg=0"]
    dashed = ["--azimuth-step-deg", "120", "--depressions-deg", "17"]
    configs = [parse_config(SimulateConfig, [*flags, "--out", "x"]) for flags in (new, dashed)]
    assert configs[0] == configs[1]
    assert (configs[0].azimuth_step_deg, configs[0].depressions_deg) == (120.0, [17.0])
    for old, replacement in (("--azimuth-step", "--azimuth_step_deg"), ("--depressions", "--depressions_deg"),
                             ("--azimuth-jitter=0", "azimuth_jitter_deg")):  # fmt: skip
        with pytest.raises(ValueError, match=f"was removed: it is now {replacement}"):
            parse_config(SimulateConfig, [old, "17", "--out", "x"])


def test_a_generated_command_runs_its_rows_stage_on_the_parsed_flags_then_its_report(
    monkeypatch, tmp_path, capsys
):
    """``cli.<function>`` is built from its COMMANDS row: the stage its ``run`` names gets the config parsed
    from argv, and the command returns what the stage returned (a folder) or what its report reads there."""
    from sar_zero123.stages import table1, vae

    runs = {command.function: command.run for command in cli.COMMANDS}
    assert runs["vae"] == "sar_zero123.stages.vae:run_vae"
    seen = []
    monkeypatch.setattr(vae, "run_vae", lambda config: seen.append(config) or tmp_path)
    assert cli.vae(["--output_dir", str(tmp_path / "vae"), "--seed", "3"]) == tmp_path
    assert type(seen[0]) is TrainVAEConfig
    assert (seen[0].output_dir, seen[0].seed) == (str(tmp_path / "vae"), 3)
    (tmp_path / "table1.json").write_text('{"rows": [1, 2]}')
    monkeypatch.setattr(table1, "run_table1", lambda config: tmp_path)
    assert cli.table1(["--output_dir", str(tmp_path / "t1")]) == {"rows": [1, 2]}  # its report: table1.json
    assert capsys.readouterr().out.splitlines()[-1] == str(tmp_path)  # the folder, printed last
    assert cli.table1.__name__ == "table1"
    assert cli.table1.__doc__.startswith("``sar-zero123-table1``: Table I")
