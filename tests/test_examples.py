"""The examples outside the package (examples/*.py): they compile, and the package imports none of them nor rclpy."""

import ast
import importlib
import importlib.util
import py_compile
from pathlib import Path

import pytest

from test_layout import PACKAGE

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.py"))


def test_there_are_examples():
    assert "ros2_node.py" in {path.name for path in EXAMPLES}


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda path: path.name)
def test_example_compiles(example, tmp_path):
    compiled = py_compile.compile(str(example), cfile=str(tmp_path / "example.pyc"), doraise=True)
    assert compiled == str(tmp_path / "example.pyc") and Path(compiled).read_bytes()[:4] == importlib.util.MAGIC_NUMBER
    # it is not imported (rclpy is not installed), but every name it takes from the package must still be there
    taken = [
        (node.module, alias.name)
        for node in ast.walk(ast.parse(example.read_text()))
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "efficienttrack"
        for alias in node.names
    ]
    assert taken, f"{example.name} imports nothing from the package"
    for module, name in taken:
        assert hasattr(importlib.import_module(module), name), f"{example.name}: from {module} import {name}"


def test_the_package_needs_no_ros():
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        assert not any(f"{word} {name}" in text for word in ("import", "from") for name in ("rclpy", "examples")), path
