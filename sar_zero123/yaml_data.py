"""YAML read as plain data, bounded: the one reader of recipes and ``--config`` files.

``yaml.safe_load`` never builds objects, but it still expands anchors and aliases (a few hundred bytes of
nested aliases grow to gigabytes), recurses once per nesting level (a deep file ends in ``RecursionError``)
and keeps the last of two equal keys without a word (a repeated field or section silently loses the
first). :func:`read_yaml` walks the file's parse events first, which costs memory and time linear in its
size, and refuses any anchor or alias and nesting deeper than :data:`MAX_YAML_DEPTH`; the mapping
constructor then refuses a key given twice. No library loader offers these three checks together.
"""

from __future__ import annotations

from typing import Any

import yaml

__all__ = ["MAX_YAML_DEPTH", "read_yaml"]

#: Deepest nesting of mappings and lists a recipe or config file may use (they need three).
MAX_YAML_DEPTH = 16


class _RepeatedKey(ValueError):
    """A mapping key given twice (raised by the loader, prefixed by :func:`read_yaml`)."""


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
                raise _RepeatedKey(f"{key!r} is given twice (line {line}); give each field and section once")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(text: str, where: str) -> Any:
    """The data of a YAML document: scalars, lists and mappings only.

    Args:
        text: The document.
        where: What it is, for messages (e.g. ``"recipe 'mine.yaml'"``).

    Raises:
        ValueError: Naming ``where``, for text that is not YAML, an anchor or alias (``&``/``*``), nesting
            deeper than :data:`MAX_YAML_DEPTH`, or a key given twice in one mapping.
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
    except _RepeatedKey as error:
        raise ValueError(f"{where}: {error}") from None
    except yaml.YAMLError as error:
        raise ValueError(f"{where}: not valid YAML ({_one_line(error)})") from None


def _one_line(error: yaml.YAMLError) -> str:
    """The parser's problem and its line, without the quoted source lines PyYAML adds."""
    problem = getattr(error, "problem", None) or getattr(error, "context", None) or str(error).splitlines()[0]
    mark = getattr(error, "problem_mark", None) or getattr(error, "context_mark", None)
    return f"{problem}, line {mark.line + 1}" if mark is not None else str(problem)
