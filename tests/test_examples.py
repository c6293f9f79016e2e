"""The examples outside the package (examples/*.py): they compile, and the package imports none of them nor rclpy."""

import py_compile
from pathlib import Path

import pytest

from test_layout import PACKAGE

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.py"))


def test_there_are_examples():
    assert "ros2_node.py" in {path.name for path in EXAMPLES}


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda path: path.name)
def test_example_compiles(example, tmp_path):
    py_compile.compile(str(example), cfile=str(tmp_path / "example.pyc"), doraise=True)


def test_the_package_needs_no_ros():
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        assert not any(f"{word} {name}" in text for word in ("import", "from") for name in ("rclpy", "examples")), path
