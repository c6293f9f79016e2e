"""The package reads in data-flow order: no module imports one from a layer above its own."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "efficienttrack"

LAYERS = (
    ("core", {"core"}),
    ("data", {"data"}),
    ("systems", {"systems"}),
    ("learning", {"learn"}),
    ("deployment", {"deploy"}),
    ("workflow", {"workflow"}),
    ("environments", {"envs"}),
    ("baselines", {"baselines"}),
    ("study", {"study"}),
    ("command line", {"cli", "__main__"}),
)
"""Layers from the bottom up: a module may import its own layer and the ones below."""


def layer_of(module: str) -> int:
    top = module.split(".")[1] if module.startswith("efficienttrack.") else module
    for rank, (_, names) in enumerate(LAYERS):
        if top in names:
            return rank
    raise AssertionError(f"module efficienttrack.{top} is in no layer of tests/test_layout.py: place it there")


def package_modules() -> list[str]:
    modules = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        if parts[-1] != "__init__" or len(parts) > 2:
            modules.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return [m for m in modules if m != "efficienttrack"]


def imported(module: str) -> set[str]:
    parts = module.split(".")
    path = PACKAGE.parent.joinpath(*parts)
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "efficienttrack":
                names |= {f"efficienttrack.{alias.name}" for alias in node.names}
            else:
                names.add(node.module)
    return {name for name in names if name.startswith("efficienttrack.")}


@pytest.mark.parametrize("module", package_modules())
def test_no_module_imports_upward(module):
    own = layer_of(module)
    upward = sorted(name for name in imported(module) if layer_of(name) > own)
    assert not upward, f"{module} ({LAYERS[own][0]}) imports from layers above it: {upward}"


def test_the_package_init_imports_only_the_core():
    assert {layer_of(name) for name in imported("efficienttrack")} <= {0}, imported("efficienttrack")


def test_systems_import_nothing_from_learning():
    learning = {name for _, names in LAYERS[3:] for name in names}
    for module in package_modules():
        if module.startswith("efficienttrack.systems"):
            assert not {m.split(".")[1] for m in imported(module)} & learning, module


def test_layer_check_catches_an_upward_import():
    assert layer_of("efficienttrack.systems.pd") < layer_of("efficienttrack.learn.dynamics")
    assert layer_of("efficienttrack.deploy.runtime") < layer_of("efficienttrack.workflow.collect")


def test_the_top_level_holds_only_packages_and_no_folder_more_than_15_modules():
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert top == ["__init__.py", "__main__.py"], top
    for folder in [p for p in PACKAGE.rglob("*") if p.is_dir() and p.name != "__pycache__"]:
        modules = [p for p in folder.glob("*.py") if p.name != "__init__.py"]
        assert len(modules) <= 15, f"{folder.relative_to(PACKAGE)} holds {len(modules)} modules"


def import_time_edges(module: str) -> set[str]:
    """Modules that ``module`` imports when it is imported (its top-level statements, type-only ones included)."""
    parts = module.split(".")
    path = PACKAGE.parent.joinpath(*parts)
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    statements, names = list(ast.parse(path.read_text()).body), set()
    while statements:
        node = statements.pop()
        if isinstance(node, (ast.If, ast.Try)):
            statements += [*node.body, *getattr(node, "orelse", []), *getattr(node, "finalbody", [])]
            statements += [s for handler in getattr(node, "handlers", []) for s in handler.body]
        elif isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("efficienttrack"):
            sub = {f"{node.module}.{alias.name}" for alias in node.names}
            modules = {name for name in sub if name in ALL_MODULES}
            names |= modules or {node.module}
            names |= {node.module} if sub - modules else set()
    return {name for name in names if name in ALL_MODULES and name != module}


ALL_MODULES = {*package_modules(), "efficienttrack"}


def import_cycle() -> list[str] | None:
    """One circle of import-time imports between the package's modules, or None."""
    edges = {module: import_time_edges(module) for module in ALL_MODULES}
    done: set[str] = set()

    def visit(module: str, path: list[str]) -> list[str] | None:
        if module in path:
            return path[path.index(module) :] + [module]
        if module in done:
            return None
        for name in sorted(edges[module]):
            cycle = visit(name, [*path, module])
            if cycle:
                return cycle
        done.add(module)
        return None

    return next((cycle for module in sorted(ALL_MODULES) if (cycle := visit(module, []))), None)


def test_no_import_circle_between_modules_the_package_init_included():
    assert import_cycle() is None, " → ".join(import_cycle() or [])
