"""Tests for config dataclass -> CLI flags and the YAML/JSON config file."""

from __future__ import annotations

import errno
import json
import resource
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from sar_zero123.config import check_minimum, check_output_dir, field_comments, parse_config, read_config_file
from sar_zero123.config.json_io import save_config, write_json_atomic
from sar_zero123.domain import naming_write_errors


@dataclass
class DemoConfig:
    """Demo config."""

    output_dir: str = "runs/demo"  # where outputs go
    learning_rate: float = 1e-4  # AdamW learning rate
    max_steps: int = 10  # optimisation steps
    use_ema: bool = True  # keep an EMA copy
    presets: tuple[str, ...] = ("speckle", "monotonic")  # augmentation presets
    steps: list[int] | None = None  # optional list of ints
    data: str | None = None  # dataset folder or None for the simulator

    def __post_init__(self):
        if self.learning_rate <= 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")


@dataclass
class CommentedConfig(DemoConfig):
    """Help from a block of comment lines above a field."""

    # first line of the block,
    # second line
    blocked: float = 1.0
    plain: int = 0
    learning_rate: float = 1e-3  # the subclass's own words win

    def helper(self) -> None:
        # a method's comment
        plain: int = 1
        del plain


def test_field_help_from_trailing_comments_and_comment_blocks():
    comments = field_comments(CommentedConfig)
    assert comments["blocked"] == "first line of the block, second line"
    # no words: the block above belongs to `blocked`; the method's comment above its `plain` is no field's
    assert "plain" not in comments
    assert comments["learning_rate"] == "the subclass's own words win"
    assert comments["output_dir"] == "where outputs go"  # inherited


def test_defaults_and_flags():
    config = parse_config(DemoConfig, [])
    assert config == DemoConfig()
    config = parse_config(
        DemoConfig,
        [
            "--learning-rate",
            "0.5",
            "--max_steps",
            "3",
            "--no-use_ema",
            "--presets",
            "a",
            "b",
            "c",
            "--steps",
            "10",
            "20",
            "--data",
            "none",
        ],
    )
    assert config.learning_rate == 0.5 and config.max_steps == 3 and config.use_ema is False
    assert config.presets == ("a", "b", "c") and config.steps == [10, 20] and config.data is None


def test_yaml_then_flags_override(tmp_path: Path):
    path = tmp_path / "c.yaml"
    path.write_text("max_steps: 7\npresets: [x]\nlearning_rate: 0.25\n")
    config = parse_config(DemoConfig, ["--config", str(path), "--max_steps", "8"])
    assert config.max_steps == 8 and config.presets == ("x",) and config.learning_rate == 0.25


def test_bad_inputs(tmp_path: Path):
    with pytest.raises(ValueError, match="learning_rate"):
        parse_config(DemoConfig, ["--learning_rate", "-1"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("max_stpes: 3\n")
    with pytest.raises(ValueError, match="max_stpes"):
        parse_config(DemoConfig, ["--config", str(bad)])
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        read_config_file(tmp_path / "missing.yaml")


def test_save_config_round_trip(tmp_path: Path):
    config = parse_config(DemoConfig, ["--max_steps", "4"])
    path = save_config(config, tmp_path / "run")
    saved = json.loads(path.read_text())
    assert saved["max_steps"] == 4 and saved["presets"] == ["speckle", "monotonic"]
    assert parse_config(DemoConfig, ["--config", str(path)]) == config
    assert not list((tmp_path / "run").glob("*.tmp"))


def test_repeated_list_flag_adds_its_values() -> None:
    @dataclass
    class Repeated:
        pipeline: list[str] = field(default_factory=lambda: ["a"])  # pipeline folders

    config = parse_config(Repeated, ["--pipeline", "x", "--pipeline", "y", "z"])
    assert config.pipeline == ["x", "y", "z"]
    assert parse_config(Repeated, []).pipeline == ["a"]


@dataclass
class Ranges:
    steps: int = 1
    rate: float = 0.1
    limit: int | None = None


@pytest.mark.parametrize(
    ("values", "names", "kwargs", "message"),
    [
        ({"steps": 0}, ("steps",), {"minimum": 1}, "steps must be >= 1, got 0"),
        ({"rate": 0.0}, ("rate",), {"minimum": 0, "strict": True}, "rate must be > 0, got 0.0"),
        ({"rate": float("nan")}, ("rate",), {"minimum": 0}, "rate must be >= 0, got nan"),
        ({"limit": 0}, ("limit",), {"minimum": 1, "optional": True}, "limit must be >= 1 or None, got 0"),
        # an infinity is no setting (a learning rate of 1e999 trains to NaN), nor is a boolean or a name
        ({"rate": float("inf")}, ("rate",), {"minimum": 0}, "rate must be a finite number >= 0, got inf"),
        ({"limit": float("-inf")}, ("limit",), {"minimum": 1, "optional": True},
         "limit must be a finite number >= 1 or None, got -inf"),
        ({"steps": True}, ("steps",), {"minimum": 0}, "steps must be >= 0, got True"),
        ({"steps": "3"}, ("steps",), {"minimum": 0}, "steps must be >= 0, got 3"),
        # both bad: the first named is reported
        ({"steps": 0, "rate": -1.0}, ("rate", "steps"), {"minimum": 0}, "rate must be >= 0, got -1.0"),
    ],
)
def test_check_minimum_names_the_first_bad_field(values, names, kwargs, message) -> None:
    with pytest.raises(ValueError, match=f"^{message}$"):
        check_minimum(Ranges(**values), *names, **kwargs)


def test_check_minimum_accepts_the_bound_and_optional_none() -> None:
    check_minimum(Ranges(steps=1, rate=0.0), "steps", "rate", minimum=0)
    check_minimum(Ranges(limit=None), "limit", minimum=1, optional=True)
    with pytest.raises(ValueError, match="limit must be >= 1, got None"):
        check_minimum(Ranges(limit=None), "limit", minimum=1)


def test_a_write_past_the_file_size_limit_names_the_file_and_keeps_the_previous(tmp_path: Path) -> None:
    path = write_json_atomic({"old": 1}, tmp_path / "record.json")
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))  # Python ignores SIGXFSZ: the write fails
    try:
        with pytest.raises(
            OSError,
            match=r"^\[Errno 27\] could not write '.*/record.json': File too large; "
            r"the previous file, if any, is unchanged$",
        ):
            write_json_atomic({"new": "x" * 10_000}, path)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert json.loads(path.read_text()) == {"old": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.json"]  # the temporary file removed


def test_naming_write_errors_names_the_outer_path_and_the_inner_file_and_passes_other_errors() -> None:
    with pytest.raises(OSError, match=r"^\[Errno 28\] could not write 'run' \(run/a.npy\): No space left on "
                                      r"device; kept the rest$") as caught:  # fmt: skip
        with naming_write_errors("run", "kept the rest"), naming_write_errors("run/a.npy", "inner"):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert caught.value.errno == errno.ENOSPC and isinstance(caught.value.__cause__, OSError)
    from safetensors import SafetensorError

    with pytest.raises(OSError, match=r"^could not write 'w.safetensors': I/O error: File too large; none$"):
        with naming_write_errors("w.safetensors", "none"):
            raise SafetensorError("I/O error: File too large")
    # torch.save's writer on a full disk raises a RuntimeError; shutil.copytree a shutil.Error (an OSError)
    with pytest.raises(OSError, match=r"could not write 'ckpt': PyTorch's file writer failed .*disk full\?"):
        with naming_write_errors("ckpt", "kept"):
            raise RuntimeError("[enforce fail at inline_container.cc:595] . unexpected pos 64 vs 0")
    with pytest.raises(OSError, match=r"could not write 'out': .*No space left on device.*; kept"):
        with naming_write_errors("out", "kept"):
            raise shutil.Error([("a", "b", "[Errno 28] No space left on device")])
    with pytest.raises(RuntimeError, match="other"), naming_write_errors("x", "y"):  # not a write failure
        raise RuntimeError("other")
    with pytest.raises(KeyError), naming_write_errors("x", "y"):  # not a write failure: unchanged
        raise KeyError("z")


def test_an_output_folder_inside_the_installed_package_is_refused(tmp_path: Path) -> None:
    """Views written beside the bundled pipelines would be lost on a reinstall (or taken for one)."""
    import sar_zero123

    package = Path(sar_zero123.__file__).resolve().parent
    for path in (package / "pretrained" / "views", package):
        with pytest.raises(ValueError, match=r"output_dir: .* lies inside the installed sar_zero123 package"):
            check_output_dir(path)
    assert not (package / "pretrained" / "views").exists()
    assert check_output_dir(tmp_path / "views") == tmp_path / "views"


def test_a_dangling_link_as_output_folder_is_refused_before_any_work(tmp_path: Path) -> None:
    (tmp_path / "out").symlink_to(tmp_path / "gone")
    with pytest.raises(NotADirectoryError, match=r"output_dir: .*out' is a link to .*gone', which does not"):
        check_output_dir(tmp_path / "out")
    with pytest.raises(NotADirectoryError, match=r"is inside .*out', which is a link to"):
        check_output_dir(tmp_path / "out" / "views")
    assert not (tmp_path / "gone").exists()


@dataclass
class AdvancedConfig(DemoConfig):
    """A command with settings that are not flags."""

    mode: Literal["a", "b"] = "a"  # a choice

    ADVANCED_FIELDS = ("max_steps", "presets", "steps", "use_ema", "mode")


def test_settings_without_a_flag_take_set_and_config_and_are_listed_at_the_end_of_help(tmp_path, capsys):
    config = parse_config(
        AdvancedConfig,
        ["--set", "max_steps=3", "--set", "presets=[x, y]", "--set", "steps=10,20", "--set", "use_ema=false",
         "--set", "mode=b", "--set", "learning_rate=2e-3", "--set", "data=none"],
    )  # fmt: skip
    assert (config.max_steps, config.presets, config.steps, config.use_ema, config.mode) == (
        3, ("x", "y"), [10, 20], False, "b"
    )  # fmt: skip
    assert config.learning_rate == 2e-3 and config.data is None  # a flag's field too
    # the older spelling still parses (recorded commands run as they did); a later --set wins over --config
    path = tmp_path / "c.yaml"
    path.write_text("max_steps: 7\n")
    assert parse_config(AdvancedConfig, ["--max_steps", "5"]).max_steps == 5
    assert parse_config(AdvancedConfig, ["--config", str(path), "--set", "max_steps=8"]).max_steps == 8
    for argv, message in [
        (["--set", "max_steps"], r"--set 'max_steps': expected FIELD=VALUE"),
        (["--set", "max_stpes=3"], r"--set 'max_stpes=3': no field 'max_stpes'; expected one of \['data'"),
        (["--set", "max_steps=three"], r"--set max_steps=three: not a value of max_steps"),
        (["--set", "use_ema=maybe"], r"--set use_ema=maybe: not a value of use_ema \(expected true or false"),
        (["--set", "learning_rate=-1"], r"learning_rate must be > 0, got -1.0"),
        (["--set", "mode=c"], r"--set mode=c: not a value of mode \(expected one of \['a', 'b'\]\)"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_config(AdvancedConfig, argv)
    with pytest.raises(SystemExit):
        parse_config(AdvancedConfig, ["--help"])
    text = capsys.readouterr().out
    flags, _, settings = text.partition("settings without a flag (--set FIELD=VALUE, repeatable")
    assert "--learning_rate" in flags and "--set FIELD=VALUE" in flags and "--max_steps" not in flags
    assert "  max_steps (default: 10): optimisation steps" in settings
    assert "  mode (default: 'a'): a choice" in settings


@dataclass
class Typed:
    seed: int = 0
    rate: float = 0.1
    d_az: list[float] = field(default_factory=lambda: [30.0])
    domain: Literal["normalized_db", "linear"] = "normalized_db"
    flag: bool = False
    name: str | None = None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("seed: '0'\n", "seed: expected an integer within int64, got '0'"),
        ("seed: 1.5\n", "seed: expected an integer within int64, got 1.5"),
        ("seed: true\n", "seed: expected an integer within int64, got True"),
        ("seed: 18446744073709551616\n", "seed: expected an integer within int64, got 18446744073709551616"),
        ("rate: .inf\n", "rate: expected a finite number, got inf"),
        ("rate: abc\n", "rate: expected a finite number, got 'abc'"),
        ("d_az: 60\n", "d_az: expected a list of a finite number, got 60"),
        ("d_az: [true, false]\n", "d_az: expected a finite number, got True"),
        ("domain: decibel\n", r"domain: expected one of \['normalized_db', 'linear'\], got 'decibel'"),
        ("flag: 1\n", "flag: expected true or false, got 1"),
        ("name: 12345\n", "name: expected a name, got 12345"),
    ],
)
def test_config_file_values_are_type_checked_by_field(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=f"^{message}$"):
        parse_config(Typed, ["--config", str(path)])


def test_typed_values_pass_through_and_float_flags_are_finite(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text("seed: 3\nrate: 1\nd_az: [60, 90.5]\ndomain: linear\nflag: true\nname: null\n")
    config = parse_config(Typed, ["--config", str(path)])
    assert (config.seed, config.rate, config.d_az, config.domain, config.flag, config.name) == (
        3, 1.0, [60.0, 90.5], "linear", True, None
    )  # fmt: skip
    assert type(config.rate) is float and all(type(v) is float for v in config.d_az)
    with pytest.raises(SystemExit):  # argparse: "argument --rate: invalid finite_float value: '1e999'"
        parse_config(Typed, ["--rate", "1e999"])
    with pytest.raises(ValueError, match="not a value of rate"):
        parse_config(Typed, ["--set", "rate=inf"])
    with pytest.raises(ValueError, match="seed: expected an integer within int64, got 18446744073709551616"):
        parse_config(Typed, ["--seed", "18446744073709551616"])


def test_a_run_folder_recording_a_removed_field_at_its_old_default_continues(tmp_path: Path) -> None:
    """A folder written before a field became a constant resumes as it did; one recording another value is
    refused in one line naming the field and why it went."""
    from sar_zero123.cli import simulate

    out = tmp_path / "data"
    flags = ["--out", str(out), "--classes", "TANK", "--instances", "1", "--azimuth_step_deg", "120",
             "--size", "16"]  # fmt: skip
    assert simulate(flags).is_dir()
    record_path = out / "run.json"
    record = json.loads(record_path.read_text())
    record["config"].update(procedural_sheet=0, real_root=None)  # as the folder was recorded before
    record_path.write_text(json.dumps(record))
    assert simulate([*flags, "--resume"]) == out
    record["config"]["procedural_sheet"] = 3
    record_path.write_text(json.dumps(record))
    refused = r"procedural_sheet=3, but procedural_sheet was removed: that sheet is sar_zero123.sim"
    with pytest.raises(ValueError, match=refused):
        simulate([*flags, "--resume"])
    with pytest.raises(ValueError, match=r"^--procedural_sheet was removed: that sheet is "):
        simulate([*flags, "--procedural_sheet", "0"])


def test_a_checkpoint_recording_a_removed_field_at_its_old_default_resumes(tmp_path: Path) -> None:
    from sar_zero123.config.json_io import config_to_dict
    from sar_zero123.runs.checkpoints import STATE_FILE, check_resume_config
    from sar_zero123.stages.vae import TrainVAEConfig

    config = TrainVAEConfig()
    written = {**config_to_dict(config), "kl_weight": 1e-6, "reconstruction_loss": "l1"}  # before they went
    (tmp_path / STATE_FILE).write_text(json.dumps({"config": written, "config_class": "TrainVAEConfig"}))
    check_resume_config(tmp_path, config)
    written["kl_weight"] = 0.5
    (tmp_path / STATE_FILE).write_text(json.dumps({"config": written, "config_class": "TrainVAEConfig"}))
    with pytest.raises(ValueError, match=r"kl_weight=0.5, but kl_weight was removed: the KL term"):
        check_resume_config(tmp_path, config)
