"""The package's import graph (docs/ARCHITECTURE.md, "Allowed imports"): acyclic between modules and
between wings, function-level imports included, and the simulator and the domain conventions at the bottom."""

from __future__ import annotations

import ast
from pathlib import Path

import sar_zero123

PACKAGE = Path(sar_zero123.__file__).resolve().parent


def module_name(path: Path) -> str:
    parts = ("sar_zero123", *path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports anywhere in its source (relative imports resolved)."""
    files = {module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {name: set() for name in files}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*parent, base] if base else parent)
                targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
            else:
                continue
            for target in targets:
                while target and target not in files:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path that ends where it starts, or None (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == 1:
                return path[path.index(target) :] + [target]
            if target not in state and (cycle := visit(target)):
                return cycle
        state[node] = 2
        path.pop()
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def wing(module: str) -> str:
    return ".".join(module.split(".")[:2])


def test_find_cycle_finds_a_deferred_cycle_and_passes_a_chain():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_modules_import_no_cycle():
    assert find_cycle(import_graph()) is None


def test_wings_import_no_cycle():
    wings: dict[str, set[str]] = {}
    for module, targets in import_graph().items():
        if module.endswith(".__main__"):  # a command; nothing imports it
            continue
        wings.setdefault(wing(module), set()).update(wing(t) for t in targets if wing(t) != wing(module))
    assert find_cycle(wings) is None


def test_simulator_and_domain_import_nothing_above_them():
    graph = import_graph()
    assert graph["sar_zero123.domain"] == set()
    for module, targets in graph.items():
        if module.startswith("sar_zero123.sim") and not module.endswith(".__main__"):
            outside = {t for t in targets if not t.startswith("sar_zero123.sim")}
            assert outside <= {"sar_zero123.domain"}, (module, outside)
