"""The contract between the modules and the viewer's interactions: names, not guesses.

An interaction reads session values only through ``ctx.value(name)`` / ``ctx.values(names)``, which refuse a
name the pipeline does not list in ``views``. Statically, from the source of every interaction file: (a) each
name passed to that accessor (a literal, or a module-level constant built from literals) is one of its
pipeline's views; and (b) every view of every registered pipeline is a value the pipeline provides: written
by a step or read by one (a dataset value). So renaming a state value in a module fails here, not in a
browser. At run time the accessor refuses undeclared names with a clear error.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from lab.core.errors import UnknownName
from lab.modules import MODULES, get_pipeline
from lab.viewer.interactions import InteractionContext, StateView
from toy_pipeline import TOY

INTERACTIONS = Path(__file__).resolve().parents[2] / "lab" / "viewer" / "interactions"
ACCESSORS = ("value", "values")


def interaction_modules() -> dict[str, list[Path]]:
    """The source files of each module's interactions: ``interactions/<module>.py``, or every file of the
    package ``interactions/<module>/``."""
    found: dict[str, list[Path]] = {}
    for path in sorted(INTERACTIONS.iterdir()):
        if path.suffix == ".py" and path.stem != "__init__":
            found[path.stem] = [path]
        elif path.is_dir() and (path / "__init__.py").exists():
            found[path.name] = sorted(path.glob("*.py"))
    return found


def _dotted(path: Path) -> str:
    parts = path.relative_to(INTERACTIONS).with_suffix("").parts
    parts = parts[:-1] if parts[-1] == "__init__" else parts
    return ".".join(("lab", "viewer", "interactions", *parts))


def _is_ctx(node: ast.expr) -> bool:
    if isinstance(node, ast.Name):
        return node.id == "ctx"
    return isinstance(node, ast.Attribute) and node.attr == "ctx"


def accessor_reads(path: Path) -> list[tuple[int, tuple[str, ...]]]:
    """``(line, names)`` of every ``ctx.value(...)`` / ``ctx.values(...)`` call in an interaction file; the
    first argument is evaluated in the module's namespace (a literal or a module constant). A name made at run
    time (a loop variable) cannot be checked: it fails the test."""
    module = importlib.import_module(_dotted(path))
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in ACCESSORS and _is_ctx(node.func.value) and node.args):
            continue
        try:
            value = eval(compile(ast.Expression(node.args[0]), str(path), "eval"), dict(vars(module)))
        except NameError as exc:
            pytest.fail(f"{path.name}:{node.lineno}: ctx.{node.func.attr} is given a name made at run time "
                        f"({exc}); pass a literal or a module-level constant so the contract can be checked")
        names = (value,) if isinstance(value, str) else tuple(value)
        assert all(isinstance(n, str) for n in names), f"{path.name}:{node.lineno}: {names!r}"
        found.append((node.lineno, names))
    return found


@pytest.mark.parametrize("module", sorted(interaction_modules()))
def test_every_name_an_interaction_reads_is_one_of_its_pipelines_views(module):
    assert module in MODULES, f"interactions of {module!r}, which is no registered module"
    pipeline = get_pipeline(module)
    reads = [(path.name, line, names) for path in interaction_modules()[module] for line,
             names in accessor_reads(path)]
    assert reads, f"the {module} interactions read no session value through ctx.value / ctx.values"
    missing = {(name, f"{file}:{line}") for file, line,
               names in reads for name in names if name not in pipeline.views}
    assert not missing, (f"the {module} interactions read names that pipeline {module!r} does not list in "
                         "its "
                         f"views {sorted(pipeline.views)}: {sorted(missing)}")


def test_the_interaction_files_of_every_module_with_interactions_are_checked():
    assert {"epipolar", "stereo", "texture", "diffusion", "sfm"} <= set(interaction_modules())


@pytest.mark.parametrize("module", MODULES)
def test_every_view_is_a_value_the_pipeline_provides(module):
    pipeline = get_pipeline(module)
    provided = {name for spec in pipeline.steps for name in (*spec.writes, *spec.reads)}
    assert pipeline.views <= provided, (f"views of {module!r} that no step writes or reads: "
                                        f"{sorted(pipeline.views - provided)}")


def context(pipeline=TOY) -> InteractionContext:
    from lab.core import open_session

    session = open_session(pipeline)
    return InteractionContext(scene=None, gui=None, folder=None, images=None, plots=None, session=session,
                              is_client=False, show_error=lambda exc: None, run=lambda step, params: None,
                              restart=lambda *a, **k: False, extent=lambda: 1.0)


def test_the_accessor_refuses_a_name_that_is_not_a_view():
    ctx = context()  # the toy pipeline lists no views
    with pytest.raises(UnknownName, match="does not list in its views"):
        ctx.value("images")
    with pytest.raises(UnknownName, match="'images'"):
        ctx.values(("images",))


def test_the_accessor_reads_views_and_refuses_undeclared_reads():
    stereo = get_pipeline("stereo")
    ctx = context(stereo)
    assert ctx.value("left_raw") is ctx.session.state["left_raw"]
    assert ctx.value("disparity") is None  # a view no step has made yet
    values = ctx.values(("left_raw", "disparity"), {"left_raw": 1, "right_raw": 2})
    assert isinstance(values, StateView) and dict(values) == {"left_raw": 1}
    assert values.get("disparity") is None and "left_raw" in values
    with pytest.raises(UnknownName, match="without declaring it"):
        values.get("right_raw")  # in the state, but not declared: refused, not silently None
