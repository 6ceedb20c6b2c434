"""YAML read as plain data, bounded: the one reader of recipes and ``--config`` files.

``yaml.safe_load`` still expands aliases (a few hundred bytes grow to gigabytes), recurses per nesting
level, keeps the last of two equal keys silently and reads YAML 1.1's loose numbers (``1:30`` is 90).
:func:`read_yaml` walks the parse events first (linear cost), refusing anchors, aliases and nesting deeper
than :data:`MAX_YAML_DEPTH`; the constructors refuse a repeated key and a number not written as a plain
decimal.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

__all__ = ["MAX_YAML_DEPTH", "read_yaml"]

#: Deepest nesting of mappings and lists a recipe or config file may use (they need three).
MAX_YAML_DEPTH = 16


#: How a recipe writes a number: decimal digits, a sign, a point, an exponent; YAML's infinities and NaN
#: (``.inf``, ``.nan``: refused by the number fields themselves).
_PLAIN_INT = re.compile(r"[-+]?(?:0|[1-9][0-9]*)")
_PLAIN_FLOAT = re.compile(
    r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)"
)
#: A float YAML 1.1 reads as text (``1e-4``: an exponent without a point), read as the number it writes.
_EXPONENT_FLOAT = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+\Z")


class _Refused(ValueError):
    """A mapping key given twice, or a loosely written number."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """The safe loader, refusing a mapping that gives one scalar key twice."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                continue
            key = self.construct_object(key_node)
            if key in seen:
                line = key_node.start_mark.line + 1
                raise _Refused(f"{key!r} is given twice (line {line}); give each field and section once")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        return self._plain(node, _PLAIN_INT, super().construct_yaml_int(node))

    def construct_yaml_float(self, node: yaml.ScalarNode) -> float:
        return self._plain(node, _PLAIN_FLOAT, super().construct_yaml_float(node))

    @staticmethod
    def _plain(node: yaml.ScalarNode, pattern: re.Pattern[str], value: Any) -> Any:
        if not pattern.fullmatch(node.value):
            line = node.start_mark.line + 1
            raise _Refused(
                f"{node.value!r} (line {line}) is a number only in YAML 1.1's loose forms (read as "
                f"{value!r}); write it as a plain decimal number, or quote it for text"
            )
        return value


_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:int", _UniqueKeyLoader.construct_yaml_int)
_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:float", _UniqueKeyLoader.construct_yaml_float)
_UniqueKeyLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789."))


def read_yaml(text: str, where: str) -> Any:
    """The data of a YAML document: scalars, lists and mappings only.

    Raises:
        ValueError: Naming ``where``, for text that is not YAML, an anchor or alias, a tag no safe constructor
            reads, nesting deeper than :data:`MAX_YAML_DEPTH`, a repeated key, or a loose YAML 1.1 number.
    """
    depth = 0
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
                raise ValueError(
                    f"{where}: YAML anchors and aliases (& and *) are not read; write each value out"
                )
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_YAML_DEPTH:
                    raise ValueError(
                        f"{where}: nested deeper than {MAX_YAML_DEPTH} levels of mappings and lists"
                    )
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except _Refused as error:
        raise ValueError(f"{where}: {error}") from None
    except yaml.YAMLError as error:
        raise ValueError(f"{where}: not valid YAML ({_one_line(error)})") from None


def _one_line(error: yaml.YAMLError) -> str:
    """The parser's problem and its line, without the quoted source lines PyYAML adds."""
    problem = getattr(error, "problem", None) or getattr(error, "context", None) or str(error).splitlines()[0]
    mark = getattr(error, "problem_mark", None) or getattr(error, "context_mark", None)
    return f"{problem}, line {mark.line + 1}" if mark is not None else str(problem)
