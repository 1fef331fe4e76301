"""The package's layout keeps its rules: imports go one way (a stage never reaches into another's private names,
nor up into the pipeline, evaluation or the command line), no two packages import each other, no module or
function grows past a screenful or two."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "svs_torch"

#: The stages, in the order data flows through them.
STAGES = ("segmentation", "features", "geometry", "depth")
#: What each top-level package may import besides itself (``core`` everywhere). A stage may use other stages'
#: public names (the nearness segmenter measures with the dense matcher), never the layers above it.
ALLOWED = {
    "core": set(),
    "segmentation": {"features", "geometry", "depth"},
    "features": set(),
    "geometry": set(),
    "depth": {"geometry"},
    "data": set(),
    "capture": set(),
    "pipeline": {*STAGES},
    "evaluation": {*STAGES, "pipeline", "data"},
    "plotting": {*STAGES, "pipeline"},
    "cli": {*STAGES, "pipeline", "data", "evaluation", "plotting", "capture"},
    "__init__": {"pipeline", "segmentation", "features"},  # the lazy public names
    "moved": set(),
}
#: Longest module (lines) and function (lines from ``def`` to its last line).
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60
#: Functions allowed past MAX_FUNCTION_LINES, each with why it stays whole (and a ceiling of 80 lines).
LONG_FUNCTIONS: dict[str, str] = {}


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append((".".join(parts), path))
    return out


def _imports(module: str, path: Path) -> list[tuple[str, list[str], int]]:
    """(absolute module imported from, names, line) of every import of ``svs_torch`` in the file."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] in ("svs_torch", "hw", "experiments"):
                found.append((target, [alias.name for alias in node.names], node.lineno))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in ("svs_torch", "hw", "experiments"):
                    found.append((alias.name, [], node.lineno))
    return found


def _top(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _edges():
    for module, path in _modules():
        for target, names, line in _imports(module, path):
            targets = [target] + [f"{target}.{name}" for name in names]
            yield module, path, line, target, names, targets


def test_the_library_never_imports_hw_experiments_or_the_command_line():
    """Only the command line may start the device emulator of ``hw/`` (``svs-depth capture --emulator``);
    nothing imports ``experiments/``, and only the command line imports itself."""
    bad = [f"{path.relative_to(PACKAGE.parent)}:{line} imports {target}"
           for module, path, line, target, names, targets in _edges()
           if target.split(".")[0] == "experiments"
           or (_top(module) != "cli" and (target.split(".")[0] == "hw" or any(
               t == "svs_torch.cli" or t.startswith("svs_torch.cli.") for t in targets)))]
    assert not bad, "\n".join(bad)


@pytest.mark.xfail(reason="holds once the modules are grouped by stage, in the next step", strict=False)
def test_every_package_has_its_place_in_the_rules():
    tops = {_top(module) for module, _ in _modules()}
    assert tops == set(ALLOWED), tops ^ set(ALLOWED)


@pytest.mark.xfail(reason="holds once the modules are grouped by stage, in the next step", strict=False)
def test_each_package_imports_only_core_and_what_sits_below_it():
    bad = []
    for module, path, line, target, names, targets in _edges():
        source = _top(module)
        used = {_top(t) for t in targets if t.startswith("svs_torch.") and _top(t) in ALLOWED}
        if target == "svs_torch":  # ``from svs_torch import X``: X is a package or a public name
            used = {name for name in names if name in ALLOWED}
        for other in used - {source, "core", "moved"} - ALLOWED[source]:
            bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {source} imports {other} ({target})")
    assert not bad, "\n".join(bad)


@pytest.mark.xfail(reason="holds once the modules are grouped by stage, in the next step", strict=False)
def test_no_package_reaches_into_another_packages_private_names():
    bad = []
    for module, path, line, target, names, _ in _edges():
        if _top(target) != _top(module) and target.startswith("svs_torch."):
            hidden = [name for name in names if name.startswith("_") and name != "__version__"]
            if hidden or any(part.startswith("_") and part != "__init__" for part in target.split(".")):
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {target} {hidden}")
    assert not bad, "\n".join(bad)


def test_no_import_cycles_between_packages():
    graph: dict[str, set[str]] = {}
    for module, _, _, target, names, targets in _edges():
        source = _top(module)
        for t in targets:
            if t.startswith("svs_torch.") and _top(t) in ALLOWED and _top(t) != source:
                graph.setdefault(source, set()).add(_top(t))
    seen, stack = set(), []

    def visit(node):
        if node in stack:
            raise AssertionError(f"import cycle: {' -> '.join(stack[stack.index(node):] + [node])}")
        if node in seen:
            return
        stack.append(node)
        for other in sorted(graph.get(node, ())):
            visit(other)
        stack.pop()
        seen.add(node)

    for node in sorted(graph):
        visit(node)


def _function_lengths():
    for module, path in _modules():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield f"{module}.{node.name}", node.end_lineno - node.lineno + 1


@pytest.mark.xfail(reason="the long modules and functions are split in a later step", strict=False)
def test_no_module_is_longer_than_400_lines():
    long = [f"{path.relative_to(PACKAGE.parent)}: {n} lines" for _, path in _modules()
            if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES]
    assert not long, "\n".join(long)


@pytest.mark.xfail(reason="the long modules and functions are split in a later step", strict=False)
def test_no_function_is_longer_than_60_lines():
    long = [f"{name}: {n} lines" for name, n in _function_lengths()
            if n > MAX_FUNCTION_LINES and not (name in LONG_FUNCTIONS and n <= 80)]
    assert not long, "\n".join(long)
    assert len(LONG_FUNCTIONS) <= 5
