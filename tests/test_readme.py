"""The README's plug-in example runs exactly as written, from a folder holding mymachines.py, with the console script."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
CONSOLE_SCRIPT = Path(sys.executable).parent / "efficienttrack"


def plug_in_example() -> tuple[str, list[str]]:
    """The ``mymachines.py`` block and the command lines of the bash block right after it."""
    text = README.read_text()
    module = re.search(r"```python\n(# mymachines\.py\n.*?)```", text, re.S)
    assert module, "README: no ```python block starting with '# mymachines.py'"
    commands = re.search(r"```bash\n(.*?)```", text[module.end() :], re.S)
    assert commands, "README: no ```bash block after the mymachines.py example"
    lines = [line.strip() for line in commands.group(1).splitlines() if line.strip() and not line.startswith("#")]
    return module.group(1), lines


def test_the_example_uses_the_console_script_and_the_plug_in():
    _, lines = plug_in_example()
    assert lines and all(line.startswith("efficienttrack ") for line in lines)
    assert any("mymachines:make" in line for line in lines)


@pytest.mark.skipif(not CONSOLE_SCRIPT.exists(), reason=f"console script not installed at {CONSOLE_SCRIPT}")
def test_plug_in_example_runs_as_written(tmp_path):
    module, lines = plug_in_example()
    (tmp_path / "mymachines.py").write_text(module)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "COLUMNS": "160"}
    for line in lines:
        argv = shlex.split(line)
        done = subprocess.run([str(CONSOLE_SCRIPT), *argv[1:]], cwd=tmp_path, env=env, capture_output=True, text=True)
        assert done.returncode == 0, f"README command failed: {line}\n{done.stdout}\n{done.stderr}"
    assert "EfficientTrack" in done.stdout and (tmp_path / "runs" / "mine" / "metrics.json").is_file()
