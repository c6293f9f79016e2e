"""Every ``efficienttrack`` command the docs show parses as written: its subcommand, options and values exist.

The commands are read from the docs' ``bash`` blocks (continuation lines joined, comments cut, a block's own
``NAME="…"`` variables expanded, ``.venv/bin/`` dropped; a command with an elision ``...`` or an unset variable left
out) and parsed by the command line itself, without running: a renamed or removed option in a documented command fails
here. What they do is tested elsewhere (the rehearsal of docs/your-machine.md runs whole in ``test_machine_workflow``).
"""

import re
import shlex
from pathlib import Path

import pytest

from test_cli import click_command

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
BLOCK = re.compile(r"^```bash\n(.*?)^```", re.M | re.S)
ASSIGNMENT = re.compile(r'^([A-Z_][A-Z0-9_]*)="([^"]*)"$')


def documented_commands(path: Path) -> list[str]:
    """The ``efficienttrack …`` commands of a doc's bash blocks, one string each (variables of the block expanded)."""
    commands = []
    for block in BLOCK.findall(path.read_text()):
        variables: dict[str, str] = {}
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if match := ASSIGNMENT.match(line):
                variables[match[1]] = match[2]
                continue
            for name, value in variables.items():
                line = line.replace(f"${name}", value).replace(f"${{{name}}}", value)
            words = re.split(r"\s*(?:&&|;|\|)\s*", line.replace(".venv/bin/efficienttrack ", "efficienttrack "))
            commands += [w for w in words if w.startswith("efficienttrack ") and not re.search(r"\$|<|\.\.\.(\s|$)", w)]
    return commands


CASES = [(path, command) for path in DOCS for command in documented_commands(path)]


def test_the_docs_show_commands_to_check():
    assert len(CASES) > 50 and {path.name for path, _ in CASES} >= {"your-machine.md", "your-logs.md", "deploy.md"}


@pytest.mark.parametrize(("path", "command"), CASES, ids=[f"{p.name}:{i}" for i, (p, _) in enumerate(CASES)])
def test_a_documented_command_parses(path, command):
    group = click_command()
    args = shlex.split(command)[1:]
    context = group.make_context("efficienttrack", list(args), resilient_parsing=True)
    name, sub, rest = group.resolve_command(context, args)
    while hasattr(sub, "resolve_command") and rest and not rest[0].startswith("-"):  # a group: refs generate, sim fit
        name, sub, rest = sub.resolve_command(context, rest)
    assert sub is not None, f"{path.name}: unknown command in `{command}`"
    try:
        sub.make_context(name, list(rest))
    except Exception as exc:  # click's usage errors: an unknown option, a missing value, a value of the wrong type
        message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
        pytest.fail(f"{path.name}: `{command}` does not parse: {message}")
