"""Command-line configuration for the training scripts.

Each script declares one ``@dataclass`` whose fields carry a default and a trailing comment.
:func:`parse_config` turns it into command-line flags (``--field_name value``; ``--field-name`` is
accepted too), optionally reads ``--config x.yaml`` (or ``.json``) first, and lets flags override
the file. A list field's flag may be repeated; its values add up. The trailing comment becomes the
flag's help text. The dataclass's ``__post_init__`` does the validation, so a bad value fails with a
``ValueError`` naming the field before any work starts.

A command's flags are the settings a user of it chooses; the rest (architecture sizes, optimiser and loss
details, logging, workers, research options: a class's ``ADVANCED_FIELDS``)
are set with ``--set FIELD=VALUE`` (any field, repeatable) or a ``--config`` file, in the spirit of
nanoGPT's configurator, and are listed with their defaults at the end of ``--help``. Their older spelling
``--field VALUE`` still parses (unlisted), so that recorded commands run as they did.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import math
import numbers
import os
import re
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

from sar_zero123.domain import read_number
from sar_zero123.yaml_data import read_yaml

ConfigT = TypeVar("ConfigT")

_COMMENT_RE = re.compile(r"^\s*(\w+)\s*:[^#]*#\s*(.+?)\s*$")
_FIELD_RE = re.compile(r"^\s*(\w+)\s*:")
_BLOCK_RE = re.compile(r"^\s*#\s?(.*?)\s*$")


def field_comments(cls: type) -> dict[str, str]:
    """Help text of each field: the trailing ``# comment`` of its line or, where it has none, the block of
    ``#`` lines right above it (joined), from the source of the class and of the dataclasses it inherits
    fields from (a subclass's line wins; empty where the source is unavailable). Only lines at the class
    body's own indentation count, so annotated names inside methods never lend their comments."""
    comments: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            source = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        body_indent: str | None = None
        block: list[str] = []
        for line in source.splitlines():
            if not line.strip() or (body_indent is None and line.lstrip().startswith(("@", "class "))):
                block = []
                continue
            indent = line[: len(line) - len(line.lstrip())]
            if body_indent is None:
                body_indent = indent
            if indent != body_indent:
                block = []
                continue
            comment = _BLOCK_RE.match(line)
            if comment:
                block.append(comment.group(1))
                continue
            trailing, field_line = _COMMENT_RE.match(line), _FIELD_RE.match(line)
            if trailing:
                comments[trailing.group(1)] = trailing.group(2)
            elif field_line and block:
                comments[field_line.group(1)] = " ".join(block)
            block = []
    return comments


def _unwrap_optional(annotation: Any) -> tuple[Any, bool]:
    """``X | None`` -> (X, True); anything else -> (annotation, False)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(annotation)) == 2:
            return args[0], True
    return annotation, False


def finite_float(text: str) -> float:
    """A float flag's value: any number but NaN and the infinities (``float`` reads ``"1e999"`` as inf),
    written plainly (:func:`~sar_zero123.domain.read_number`: no ``"1_0"``, no non-ASCII digits)."""
    value = read_number(text)
    if not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {text!r}")
    return float(value)


def integer(text: str) -> int:
    """An integer flag's value, written plainly (:func:`~sar_zero123.domain.read_number`: ``int`` reads
    ``"1_0"`` as 10)."""
    return int(read_number(text, integer=True))


def _scalar_parser(annotation: Any, name: str) -> Any:
    if annotation is float:
        return finite_float
    if annotation is int:
        return integer
    if annotation is str:
        return str
    if annotation is Path:
        return str
    if typing.get_origin(annotation) is typing.Literal:
        choices = typing.get_args(annotation)
        return integer if type(choices[0]) is int else type(choices[0])
    raise TypeError(f"config field {name!r}: unsupported type {annotation!r}")


def _add_field(parser: argparse.ArgumentParser, field: dataclasses.Field, annotation: Any, help_text: str):
    name = field.name
    flags = [f"--{name}"] + ([f"--{name.replace('_', '-')}"] if "_" in name else [])
    inner, optional = _unwrap_optional(annotation)
    kwargs: dict[str, Any] = {"dest": name, "default": argparse.SUPPRESS, "help": help_text}
    origin = typing.get_origin(inner)
    if inner is bool:
        parser.add_argument(*flags, action=argparse.BooleanOptionalAction, **kwargs)
        return
    if origin in (list, tuple, Sequence, typing.Sequence):
        args = [a for a in typing.get_args(inner) if a is not Ellipsis]
        element = args[0] if args else str
        element_type = _scalar_parser(element, name)
        # "extend": a repeated flag adds its values (`--pipeline a --pipeline b` -> [a, b])
        parser.add_argument(
            *flags, nargs="*" if optional else "+", action="extend", type=element_type, **kwargs
        )
        return
    scalar = _scalar_parser(inner, name)
    if typing.get_origin(inner) is typing.Literal:
        kwargs["choices"] = typing.get_args(inner)
    if optional:
        # "none" on the command line gives None for optional fields.
        def parse_optional(text: str, _scalar=scalar) -> Any:
            return None if text.lower() in ("none", "null") else _scalar(text)

        parse_optional.__name__ = scalar.__name__  # argparse names it: "invalid finite_float value"
        parser.add_argument(*flags, type=parse_optional, **kwargs)
    else:
        parser.add_argument(*flags, type=scalar, **kwargs)


def _coerce(name: str, value: Any, annotation: Any) -> Any:
    """A flag's, ``--set``'s or ``--config`` file's value as the field's declared type takes it: checked
    (a number finite, a bool a bool, a name one of its choices, a list's items each), a list given to a
    tuple field as a tuple and an int given to a float field as a float.

    Raises:
        ValueError: ``"<name>: expected <type>, got <value>"`` for a value of another type.
    """
    inner, optional = _unwrap_optional(annotation)
    if value is None:
        if optional:
            return None
        raise ValueError(f"{name}: expected {_kind(inner)}, got None")
    origin = typing.get_origin(inner)
    if origin in (list, tuple, Sequence, typing.Sequence):
        args = [a for a in typing.get_args(inner) if a is not Ellipsis]
        if not isinstance(value, (list, tuple)):
            raise ValueError(
                f"{name}: expected a list of {_kind(args[0] if args else str)}, got {_short(value)}"
            )
        items = [_coerce(name, item, args[0]) for item in value] if args else list(value)
        return tuple(items) if origin is tuple else items
    return _coerce_scalar(name, value, inner)


def _coerce_scalar(name: str, value: Any, kind: Any) -> Any:
    if typing.get_origin(kind) is typing.Literal:
        if value not in typing.get_args(kind) or isinstance(value, bool):
            raise ValueError(f"{name}: expected one of {list(typing.get_args(kind))}, got {_short(value)}")
        return value
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:  # within int64: what torch and numpy take as a seed or a size
        ok = isinstance(value, int) and not isinstance(value, bool) and -(2**63) <= value < 2**63
    elif kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        value = float(value) if ok else value
    elif kind in (str, Path):
        ok = isinstance(value, str)
    else:  # a type the flags do not parse (a field set only from code): passed on as given
        ok = True
    if not ok:
        raise ValueError(f"{name}: expected {_kind(kind)}, got {_short(value)}")
    return value


def _kind(kind: Any) -> str:
    names = {
        bool: "true or false",
        int: "an integer within int64",
        float: "a finite number",
        str: "a name",
        Path: "a path",
    }
    return names.get(kind, getattr(kind, "__name__", str(kind)))


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else f"{text[:77]}..."


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """Read a YAML or JSON mapping of config values.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: if the file is not valid JSON/YAML (naming the file) or does not hold a mapping.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"--config: {str(path)!r} is a folder; expected a YAML or JSON file")
    if not path.is_file():
        raise FileNotFoundError(f"--config: no such file {str(path)!r}")
    if path.suffix == ".json":
        values = _read_json_config(path)
    else:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as error:
            raise ValueError(f"--config {str(path)!r}: not valid YAML ({error})") from None
        values = read_yaml(text, f"--config {str(path)!r}")
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ValueError(f"--config {str(path)!r}: expected a mapping of field names to values")
    return values


def _read_json_config(path: Path) -> Any:
    """A JSON ``--config`` file read as :func:`~sar_zero123.yaml_data.read_yaml` reads YAML: a key given twice
    refused (``json`` keeps the last), as is nesting too deep to parse."""

    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [key for key, _ in pairs]
        repeated = sorted({key for key in keys if keys.count(key) > 1})
        if repeated:
            raise ValueError(f"--config {str(path)!r}: {repeated} given twice; give each field once")
        return dict(pairs)

    try:
        return json.loads(path.read_text(encoding="utf-8"), object_pairs_hook=unique)
    except RecursionError:
        raise ValueError(f"--config {str(path)!r}: nested too deep to read") from None
    except json.JSONDecodeError as error:  # worded as read_json words it
        raise ValueError(
            f"{path}: invalid JSON at line {error.lineno} column {error.colno} ({error.msg}); expected a "
            "JSON mapping of config values"
        ) from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file; expected a JSON mapping of config values") from None


@dataclasses.dataclass(frozen=True)
class RemovedField:
    """A config field that was removed: the value it held by default, and why it went (what was measured, and
    what replaces it). A config class lists them in ``REMOVED_FIELDS``; a flag, a ``--config`` file or a run
    folder's record that sets one to another value than ``default`` is refused, naming it and ``reason``."""

    default: Any
    reason: str


def removed_fields(config: Any) -> Mapping[str, RemovedField]:
    """The removed fields of a config class or instance (its ``REMOVED_FIELDS``; ``{}`` where it has none)."""
    return getattr(config, "REMOVED_FIELDS", {})


def drop_removed_fields(config: Any, values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``values`` without the removed fields that hold their old default (a config or record written before
    they went reads as it did).

    Raises:
        ValueError: Naming ``where``, the field and why it went, for one set to another value.
    """
    removed = removed_fields(config)

    def plain(value: Any) -> Any:  # a tuple default as JSON and YAML hold it
        return [plain(item) for item in value] if isinstance(value, (list, tuple)) else value

    for name, item in removed.items():
        if name in values and plain(values[name]) != plain(item.default):
            raise ValueError(f"{where}: {name}={values[name]!r}, but {name} was removed: {item.reason}")
    return {name: value for name, value in values.items() if name not in removed}


def advanced_fields(cls: Any) -> set[str]:
    """A config class's settings that are not flags: its ``ADVANCED_FIELDS`` and those of the classes it
    inherits fields from."""
    names: set[str] = set()
    for klass in getattr(cls, "__mro__", type(cls).__mro__):
        names.update(klass.__dict__.get("ADVANCED_FIELDS", ()))
    return names


def _set_value(text: str, annotation: Any, name: str) -> Any:
    """The value of ``--set NAME=TEXT`` for a field of this type: a number, a name, ``true``/``false``,
    ``none`` (optional fields), a list as ``[8, 16]`` or ``8,16``.

    Raises:
        ValueError: Naming the field, for text that is not a value of its type.
    """
    inner, optional = _unwrap_optional(annotation)
    if optional and text.strip().lower() in ("none", "null", "~"):
        return None
    try:
        if inner is bool:
            value = yaml.safe_load(text)
            if not isinstance(value, bool):
                raise ValueError(f"expected true or false, got {text!r}")
            return value
        if typing.get_origin(inner) in (list, tuple, Sequence, typing.Sequence):
            args = [a for a in typing.get_args(inner) if a is not Ellipsis]
            element = _scalar_parser(args[0] if args else str, name)
            stripped = text.strip()
            items = stripped[1:-1] if stripped.startswith("[") and stripped.endswith("]") else stripped
            return [element(item.strip().strip("'\"")) for item in re.split(r"[,\s]+", items) if item.strip()]
        value = _scalar_parser(inner, name)(text)
        if typing.get_origin(inner) is typing.Literal and value not in typing.get_args(inner):
            raise ValueError(f"expected one of {list(typing.get_args(inner))}")
        return value
    except (TypeError, ValueError) as error:
        raise ValueError(f"--set {name}={text}: not a value of {name} ({error})") from None


def _set_values(pairs: Sequence[str], cls: type, hints: Mapping[str, Any], names: set[str]) -> dict[str, Any]:
    """``--set FIELD=VALUE`` pairs as field values (a later pair wins).

    Raises:
        ValueError: For a pair without ``=`` or a field the command does not have (listing them).
    """
    values: dict[str, Any] = {}
    for pair in pairs:
        name, equals, text = pair.partition("=")
        name = name.strip().replace("-", "_")
        if not equals or not name:
            raise ValueError(f"--set {pair!r}: expected FIELD=VALUE")
        if name in removed_fields(cls):
            raise ValueError(f"--set {name}: {name} was removed: {removed_fields(cls)[name].reason}")
        if name not in names:
            raise ValueError(f"--set {pair!r}: no field {name!r}; expected one of {sorted(names)}")
        values[name] = _set_value(text, hints[name], name)
    return values


def _advanced_epilog(
    fields: Sequence[dataclasses.Field], advanced: set[str], comments: Mapping[str, str]
) -> str:
    """The end of ``--help``: each setting that is not a flag, its default and its comment."""
    import textwrap

    lines = ["settings without a flag (--set FIELD=VALUE, repeatable, or a --config file):"]
    for field in fields:
        if field.name not in advanced:
            continue
        default = field.default if field.default is not dataclasses.MISSING else field.default_factory()  # type: ignore[misc]
        text = comments.get(field.name, "")
        lines += textwrap.wrap(f"{field.name} (default: {default!r}): {text}", width=100,
                               initial_indent="  ", subsequent_indent="      ")  # fmt: skip
    return "\n".join(lines)


def parse_config(
    cls: type[ConfigT],
    argv: Sequence[str] | None = None,
    *,
    prog: str | None = None,
) -> ConfigT:
    """Build a config dataclass from ``--config FILE`` and command-line flags.

    Precedence: dataclass defaults < values in ``--config`` < flags. Every field is ``--field_name``
    (``--field-name`` too). A config with ``resume_from_checkpoint`` and no ``resume`` field also takes
    ``--resume``, the same as ``--resume_from_checkpoint latest``, so that every stage continues a run
    with ``--resume``.

    Args:
        cls: a dataclass whose fields all have defaults.
        argv: the arguments (without the program name); ``None`` reads ``sys.argv``.
        prog: the command's name in usage lines (``None``: the script's file name).

    Returns:
        An instance of ``cls`` (its ``__post_init__`` has validated it).

    Raises:
        ValueError: for keys in the config file that are not fields of ``cls``, or bad values.
        FileNotFoundError: if ``--config`` names a missing file.
        NotADirectoryError: if an ``output_dir`` or ``work_dir`` field names a file (checked
            here, before the script loads anything).
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    summary = (cls.__doc__ or "").strip().splitlines()
    # the command's own fields first, then those it inherits (FinetuneConfig's loss fields)
    own = cls.__dict__.get("__annotations__", {})
    fields = sorted((f for f in dataclasses.fields(cls) if f.init), key=lambda f: f.name not in own)
    names = {field.name for field in fields}
    # settings that are not flags: --set FIELD=VALUE or --config (ADVANCED_FIELDS)
    advanced = advanced_fields(cls) & names
    takes_set = "set" not in names  # the quickstart's own --set names a stage too
    parser = argparse.ArgumentParser(
        prog=prog, description=summary[0] if summary else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_advanced_epilog(fields, advanced, comments) if advanced and takes_set else None,
    )  # fmt: skip
    parser.add_argument(
        "--config", default=None, help="YAML or JSON file with field values (flags override it)"
    )
    if takes_set:
        parser.add_argument(
            "--set", dest="_set", action="append", default=[], metavar="FIELD=VALUE",
            help="set any field, those listed at the end included; repeatable (lists as 8,16 or [8, 16]; "
                 "none for an optional field)",
        )  # fmt: skip
    for field in fields:
        default = field.default if field.default is not dataclasses.MISSING else field.default_factory()  # type: ignore[misc]
        help_text = f"{comments.get(field.name, '')} (default: {default!r})".strip()
        # a setting without a flag still parses as --name VALUE (the commands recorded in the results pages
        # and older scripts run as they did), but is listed as a setting, not a flag
        hidden = field.name in advanced and takes_set
        _add_field(parser, field, hints[field.name], argparse.SUPPRESS if hidden else help_text)
    if "resume_from_checkpoint" in names and "resume" not in names:
        parser.add_argument(
            "--resume", dest="resume_from_checkpoint", action="store_const", const="latest",
            default=argparse.SUPPRESS,
            help="continue the run in the output folder from its newest intact checkpoint (the same as "
            "--set resume_from_checkpoint=latest)",
        )  # fmt: skip
    removed = removed_fields(cls)
    for token in sys.argv[1:] if argv is None else argv:
        flag = token.partition("=")[0].lstrip("-").replace("-", "_")
        if token.startswith("--") and flag in removed:
            raise ValueError(f"--{flag} was removed: {removed[flag].reason}")
    namespace = vars(parser.parse_args(argv))
    config_path = namespace.pop("config")
    set_pairs = namespace.pop("_set", [])
    values: dict[str, Any] = {}
    if config_path is not None:
        file_values = drop_removed_fields(cls, read_config_file(config_path), f"--config {config_path!r}")
        known = {f.name for f in fields}
        unknown = sorted(set(file_values) - known)
        if unknown:
            raise ValueError(
                f"--config {config_path!r}: unknown field(s) {unknown}; expected a subset of {sorted(known)}"
            )
        values.update(file_values)
    values.update(namespace)
    values.update(_set_values(set_pairs, cls, hints, names))
    values = {name: _coerce(name, value, hints[name]) for name, value in values.items()}
    config = cls(**values)
    for name in OUTPUT_DIR_FIELDS:
        if hasattr(config, name) and getattr(config, name) is not None:
            check_output_dir(getattr(config, name), name)
    return config


def check_minimum(
    config: Any,
    *names: str,
    minimum: float,
    strict: bool = False,
    optional: bool = False,
    maximum: float | None = None,
) -> None:
    """Refuse the first field of ``names`` below ``minimum`` (or above ``maximum``): the range checks of
    ``__post_init__``. A maximum bounds what a setting makes the run allocate, checked before any work.

    Args:
        config: The config dataclass (``self`` in ``__post_init__``).
        names: Fields to check, in order.
        minimum: The smallest allowed value.
        strict: Require ``value > minimum`` instead of ``>=``.
        optional: Accept ``None``.
        maximum: The largest allowed value; ``None``: no upper bound.

    Raises:
        ValueError: ``"<name> must be >= <minimum>[ or None], got <value>"`` (``>`` with ``strict``; "a
            finite number >= ..." for an infinity); NaN, infinities, booleans and non-numbers fail every
            check, ``None`` every check without ``optional``; ``"<name> must be <= <maximum>, got <value>"``
            above ``maximum``.
    """
    for name in names:
        value = getattr(config, name)
        if value is None and optional:
            continue
        bound = f"{'>' if strict else '>='} {minimum}{' or None' if optional else ''}"
        number = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if number and math.isinf(value):
            raise ValueError(f"{name} must be a finite number {bound}, got {value}")
        if not number or not (value > minimum if strict else value >= minimum):
            raise ValueError(f"{name} must be {bound}, got {value}")
        if maximum is not None and value > maximum:
            raise ValueError(f"{name} must be <= {maximum}, got {value}")


#: Config fields that name a folder a script writes into; :func:`parse_config` checks them first.
OUTPUT_DIR_FIELDS = ("output_dir", "work_dir", "out")


def check_output_dir(path: str | os.PathLike, field: str = "output_dir") -> Path:
    """Check, before any work, that ``path`` is or can become a folder (it and its parents are no files) and
    lies outside the installed ``sar_zero123`` package (its bundled pipelines; a reinstall would lose it).

    Raises:
        NotADirectoryError: naming ``field``, the path and the file (or dangling link) in the way.
        PermissionError: naming ``field``, for a folder (or the nearest existing parent) not writable.
        ValueError: naming ``field``, for a folder inside the package.
    """
    path = Path(path)
    package = Path(__file__).resolve().parent.parent
    if path.resolve().is_relative_to(package):
        raise ValueError(
            f"{field}: {str(path)!r} lies inside the installed sar_zero123 package ({str(package)!r}), "
            "beside its bundled pipelines; name a folder outside it"
        )
    for candidate in (path, *path.parents):
        if candidate.is_symlink() and not candidate.exists():
            where = "is" if candidate == path else f"is inside {str(candidate)!r}, which is"
            raise NotADirectoryError(
                f"{field}: {str(path)!r} {where} a link to {os.readlink(candidate)!r}, which does not exist; "
                "expected a folder to write into"
            )
        if candidate.exists():
            if not candidate.is_dir():
                where = "is a file" if candidate == path else f"is inside {str(candidate)!r}, which is a file"
                raise NotADirectoryError(f"{field}: {str(path)!r} {where}; expected a folder to write into")
            if not os.access(candidate, os.W_OK | os.X_OK):
                where = "" if candidate == path else f" (in {str(candidate)!r})"
                raise PermissionError(
                    f"{field}: {str(path)!r} cannot be written{where}; name a writable folder"
                )
            break
    return path
