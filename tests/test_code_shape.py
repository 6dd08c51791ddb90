"""The shape the code keeps (docs/design.md, sections 3 and 6): small files and functions, arrows that point
one way, no import circle. Measured from the source with ``ast``; nothing is imported or run."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

LAB = Path(__file__).resolve().parents[1] / "lab"
MAX_FILE_LINES = 1000
MAX_FUNCTION_LINES = 120
#: Layers from the bottom up: a file may import its own layer and the ones below, never one above.
LAYERS = {"core": 0, "geometry": 1, "data": 2, "modules": 3, "viewer": 4, "api": 4, "lessons": 4, "server": 5,
          "cli": 6}
#: Front ends beside each other may use each other only where named here: REST and the viewer serve
#: lessons; a lesson report draws its scenes with the viewer's renderers (scene.as_html).
FRONT_END_USES = {("api", "lessons"), ("viewer", "lessons"), ("lessons", "viewer")}


def sources() -> list[Path]:
    return sorted(p for p in LAB.rglob("*.py") if "__pycache__" not in p.parts)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(LAB.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def imports_of(path: Path) -> set[str]:
    """Every ``lab.*`` module a file imports, at any depth (function-level imports count too)."""
    found: set[str] = set()
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("lab"))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            if base.startswith("lab"):
                found.add(base)
                found.update(f"{base}.{a.name}" for a in node.names)
    known = {module_name(p) for p in sources()}
    return {name for name in found if name in known and name != module_name(path)}


def test_no_file_in_lab_is_longer_than_the_limit():
    long = {str(p.relative_to(LAB.parent)): n for p in sources() if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES}
    assert long == {}, f"files over {MAX_FILE_LINES} lines: {long}"


def test_no_function_in_lab_is_longer_than_the_limit():
    long = {}
    for path in sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long[f"{path.relative_to(LAB.parent)}:{node.name}"] = length
    assert long == {}, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def test_arrows_point_down_the_layers():
    upward = []
    for path in sources():
        here = layer_of(module_name(path))
        if here is None:
            continue
        for target in imports_of(path):
            there = layer_of(target)
            if there is None or there == here:
                continue
            if LAYERS[there] > LAYERS[here] or (LAYERS[there] == LAYERS[here]
                                                 and (here, there) not in FRONT_END_USES):
                upward.append(f"{module_name(path)} -> {target}")
    assert upward == [], "imports that point up (or sideways) a layer:\n" + "\n".join(upward)


def test_modules_reach_each_other_only_through_their_packages():
    """A module package does not import another module's internals (it may use lab.modules.<other>)."""
    reaching = []
    for path in sources():
        name = module_name(path)
        if layer_of(name) != "modules" or name.count(".") < 2:
            continue
        own = name.split(".")[2]
        for target in imports_of(path):
            parts = target.split(".")
            if layer_of(target) == "modules" and len(parts) > 3 and parts[2] != own:
                reaching.append(f"{name} -> {target}")
    assert reaching == [], "\n".join(reaching)


def test_there_is_no_import_circle():
    graph = {module_name(p): {t for t in imports_of(p) if not t.endswith("__init__")} for p in sources()}
    # a package's __init__ re-exporting its files is not a circle with them
    graph = {name: {t for t in targets if not name.startswith(t + ".")} for name, targets in graph.items()}
    circles: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                circles.append([*stack[stack.index(nxt):], nxt])
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    assert circles == [], "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)


@pytest.mark.parametrize("path", [p for p in sources() if p.name != "__init__.py"][:1])
def test_the_checks_read_real_files(path):
    assert imports_of(path) is not None and len(sources()) > 50
