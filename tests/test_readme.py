"""The README's Python quick start and docs/your-system.md's plug-in example run exactly as written."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PLUG_IN = ROOT / "docs" / "your-system.md"


def plug_in_example() -> tuple[str, list[str]]:
    """The ``mymachines.py`` block and the command lines of the bash block right after it."""
    text = PLUG_IN.read_text()
    module = re.search(r"```python\n(# mymachines\.py\n.*?)```", text, re.S)
    assert module, f"{PLUG_IN.name}: no ```python block starting with '# mymachines.py'"
    commands = re.search(r"```bash\n(.*?)```", text[module.end() :], re.S)
    assert commands, f"{PLUG_IN.name}: no ```bash block after the mymachines.py example"
    lines = [line.strip() for line in commands.group(1).splitlines() if line.strip() and not line.startswith("#")]
    return module.group(1), lines


def test_the_example_uses_the_console_script_and_the_plug_in():
    _, lines = plug_in_example()
    assert lines and all(line.startswith("efficienttrack ") for line in lines)
    assert any("mymachines:make" in line for line in lines)


@pytest.fixture
def user_folder(monkeypatch, tmp_path):
    """``tmp_path`` as the working folder of a user's console script or script, in-process: not on ``sys.path`` (so the
    plug-in is found only because specs look there first), and no user module is left imported afterwards."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", ".")])
    yield tmp_path
    sys.modules.pop("mymachines", None)


@pytest.mark.slow
def test_plug_in_example_runs_as_written(user_folder):
    """The ``efficienttrack`` command lines through the console script's app, in-process (a subprocess each cost
    seconds of imports; test_wheel runs the installed console script)."""
    module, lines = plug_in_example()
    (user_folder / "mymachines.py").write_text(module)
    for line in lines:
        done = CliRunner().invoke(app, shlex.split(line)[1:], env={"COLUMNS": "160"})
        assert done.exit_code == 0, f"{PLUG_IN.name} command failed: {line}\n{done.output}\n{done.exception!r}"
    assert "EfficientTrack" in done.output and (user_folder / "runs" / "mine" / "metrics.json").is_file()


def python_quick_start() -> str:
    """The README's ```python block that begins with ``import efficienttrack as et``."""
    block = re.search(r"```python\n(import efficienttrack as et\n.*?)```", README.read_text(), re.S)
    assert block, "README: no ```python block starting with 'import efficienttrack as et'"
    return block.group(1)


@pytest.mark.slow
def test_the_python_quick_start_runs_as_written_and_beats_pd(user_folder, capsys):
    """Executed in-process in a fresh namespace (a subprocess cost seconds of imports)."""
    exec(python_quick_start(), {"__name__": "__main__"})
    pd_mae, et_mae = (float(x) for x in capsys.readouterr().out.strip().splitlines()[-1].split())
    assert et_mae < pd_mae
    assert (user_folder / "runs" / "python" / "policy.pt").is_file()


def test_the_top_level_api_names_resolve_and_stay_lazy():
    import efficienttrack

    code = "import sys, efficienttrack; print('torch' in sys.modules)"
    done = subprocess.run(
        [sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(ROOT / "src")}, capture_output=True, text=True
    )
    assert done.stdout.strip() == "False", done.stderr  # importing the package imports no torch
    for name in efficienttrack.API:
        assert callable(getattr(efficienttrack, name)), name
    assert efficienttrack.run.__name__ == "run_pipeline" and efficienttrack.round.__name__ == "next_round"
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        efficienttrack.nope  # noqa: B018
