"""The package's import graph (docs/ARCHITECTURE.md, "Allowed imports"): acyclic between modules and
between wings, function-level imports included, and the simulator and the domain conventions at the bottom."""

from __future__ import annotations

import ast
import re
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


def documented_allowed_imports() -> dict[str, set[str]]:
    """The "Allowed imports" table of docs/ARCHITECTURE.md: wing -> the wings it may import."""
    text = (PACKAGE.parent / "docs" / "ARCHITECTURE.md").read_text()
    section = text[text.index("## Allowed imports") :]
    rows = [line for line in section.splitlines()[:40] if line.startswith("| `")]
    names = {f"sar_zero123.{name}" for name in _wings_on_disk()}
    allowed: dict[str, set[str]] = {}
    for row in rows:
        left, right = (cell.strip() for cell in row.strip("|").split("|")[:2])
        wings = [f"sar_zero123.{name}" for name in re.findall(r"`([\w/]+)`", left) if "/" not in name]
        if not wings:  # train/, benchmarks/: outside the package
            continue
        if right.startswith("nothing"):
            targets: set[str] = set()
        elif right.startswith("every wing"):
            targets = set(names)
        elif right.startswith("any wing above"):
            excluded = {f"sar_zero123.{name}" for name in re.findall(r"`(\w+)`", right)}
            targets = set().union(*allowed.values(), *([{w} for w in allowed])) - excluded
        else:
            targets = {f"sar_zero123.{name}" for name in re.findall(r"`([\w.]+)`", right)}
            targets = {".".join(t.split(".")[:2]) for t in targets} & names
        for name in wings:
            allowed[name] = targets
    return allowed


def _wings_on_disk() -> set[str]:
    modules = {path.stem for path in PACKAGE.glob("*.py") if path.stem != "__init__"}
    return modules | {path.parent.name for path in PACKAGE.glob("*/__init__.py")}


def test_every_wing_imports_only_what_the_architecture_table_allows():
    allowed = documented_allowed_imports()
    imported: dict[str, set[str]] = {}
    for module, targets in import_graph().items():
        if module == "sar_zero123":  # the package's own __init__ (lazy re-exports)
            continue
        if module.endswith(".__main__"):  # a command: it may import what its command needs
            imported.setdefault("sar_zero123.cli", set()).update(wing(t) for t in targets)
            continue
        imported.setdefault(wing(module), set()).update(wing(t) for t in targets if wing(t) != wing(module))
    undocumented = sorted(set(imported) - set(allowed))
    assert not undocumented, f"wings missing from the table: {undocumented}"
    breaches = {name: sorted(targets - allowed[name] - {"sar_zero123"}) for name, targets in imported.items()}
    assert {name: bad for name, bad in breaches.items() if bad} == {}


def test_nothing_imports_the_commands_and_benchmarks_never_import_train():
    for module, targets in import_graph().items():
        assert "sar_zero123.cli" not in targets or module == "sar_zero123.cli", module
    for path in (PACKAGE.parent / "benchmarks").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom | ast.Import):
                names = (
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                )
                assert not any(n == "train" or n.startswith("train.") for n in names), path


def test_stage_modules_only_assemble_no_model_loss_or_training_loop():
    """docs/ARCHITECTURE.md: a stage module holds its config, its run function and setup helpers; models,
    losses and training loops live in model/, training/ and evaluation/."""
    for path in sorted((PACKAGE / "stages").glob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                bases = {ast.unparse(base) for base in node.bases}
                assert not bases & {"nn.Module", "torch.nn.Module", "ModelMixin"}, (path.name, node.name)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                assert node.func.attr not in ("backward", "step") or ast.unparse(node.func.value) not in (
                    "accelerator",
                    "loss",
                    "optimizer",
                    "scheduler",
                    "lr_scheduler",
                ), (path.name, ast.unparse(node))
