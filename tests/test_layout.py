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
