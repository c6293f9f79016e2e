"""The core install, for real: the wheel built from this tree, installed alone in a fresh virtual environment.

Without torch and the training and study stacks, ``efficienttrack --help`` and ``efficienttrack deploy`` of an
export on the simulator must run, and a command that needs an extra must name it in one line (docs/deploy.md).
"""

import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EXTRAS
from efficienttrack.data.references import Reference, load_references, save_references
from efficienttrack.learn.policy import AdjustmentPolicy, save_policy
from efficienttrack.learn.settings import POLICY_PRESETS
from test_export import EXTRA_LIBRARIES

ROOT = Path(__file__).resolve().parents[1]

NO_NETWORK = re.compile(
    r"NewConnectionError|Failed to establish a new connection|Temporary failure in name resolution|ConnectTimeoutError|"
    r"ReadTimeoutError|Network is unreachable|ProxyError"
)
"""What pip says when it cannot reach a package index."""

IN_PROCESS = """
import sys
from efficienttrack.__main__ import main

sys.argv[0] = "efficienttrack"
code = 0
try:
    main()
except SystemExit as exc:
    code = exc.code
imported = {name.split(".")[0] for name in sys.modules} & set(LEFT_OUT)
print("imported:", ",".join(sorted(imported)))
sys.exit(code)
"""
"""The command line's main, run in the fresh environment; then which of ``LEFT_OUT`` (defined before it) it imported."""


def test_the_command_line_names_the_extra_that_installs_each_library_the_core_leaves_out():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    libraries = {
        re.match(r"[\w-]+", requirement)[0].replace("-", "_"): extra
        for extra in ("train", "study", "ros")
        for requirement in extras[extra]
        if not requirement.startswith("efficienttrack[")
    }
    assert EXTRAS == libraries


def run(*args, code: int = 0) -> subprocess.CompletedProcess:
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=300)
    assert done.returncode == code, f"{args}: exit code {done.returncode}\n{done.stdout}\n{done.stderr}"
    return done


def core_install(tmp_path: Path) -> Path:
    """A fresh virtual environment with the wheel of this tree and its core dependencies alone: its python."""
    source = tmp_path / "source"  # a copy: the build writes build/ and an egg-info beside the sources, not in the tree
    shutil.copytree(ROOT / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source)
    run(sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", tmp_path / "wheel", source)
    [wheel] = (tmp_path / "wheel").glob("efficienttrack-*.whl")
    venv = tmp_path / "venv"
    run(sys.executable, "-m", "venv", "--without-pip", venv)  # this pip installs into it (--python): faster than its own
    python = venv / "bin" / "python"
    # --no-compile: byte-compiling every installed module (numpy, onnxruntime) took a third of the install
    install = [sys.executable, "-m", "pip", "--python", python, "install", "--quiet", "--no-compile", "--retries", "1",
               "--timeout", "15"]  # fmt: skip
    done = subprocess.run([str(a) for a in (*install, wheel)], capture_output=True, text=True, timeout=300)
    offline = NO_NETWORK.search(done.stdout + done.stderr)
    if done.returncode != 0 and offline:
        pytest.skip(f"pip reaches no package index for the core dependencies, and its cache lacks them ({offline[0]})")
    assert done.returncode == 0, done.stdout + done.stderr
    return python


@pytest.mark.slow
@pytest.mark.early
def test_the_core_install_deploys_an_export_without_torch(tmp_path):
    python = core_install(tmp_path)
    found = run(python, "-c", f"import importlib.util as u; print([m for m in {EXTRA_LIBRARIES} if u.find_spec(m)])")
    assert found.stdout.strip() == "[]", f"the core install brought in {found.stdout}"

    # the export and the references, made with this environment's full install
    invoke = CliRunner().invoke
    assert invoke(app, ["refs", "generate", "--n", "2", "--out", str(tmp_path / "gen")]).exit_code == 0
    save_references([Reference(r.name, r.q[:40]) for r in load_references(tmp_path / "gen")], tmp_path / "refs")
    policy = AdjustmentPolicy(POLICY_PRESETS["tiny"])
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.5)  # an untrained policy that adjusts
    save_policy(policy, tmp_path / "policy.pt")
    result = invoke(app, ["export", "--policy", str(tmp_path / "policy.pt"), "--out", str(tmp_path / "export")])
    assert result.exit_code == 0, result.output

    efficienttrack = python.parent / "efficienttrack"  # the console script
    assert "deploy" in run(efficienttrack, "--help").stdout
    out = tmp_path / "deployed"
    args = ("deploy", "--system", "xe75", "--policy", tmp_path / "export", "--refs", tmp_path / "refs", "--out", out)
    done = run(python, "-c", f"LEFT_OUT = {EXTRA_LIBRARIES!r}\n{IN_PROCESS}", *args, "--fast", "--arm", "--shadow")
    assert "2 run(s) done (shadow)" in done.stdout and done.stdout.splitlines()[-1] == "imported: ", done.stdout
    report = json.loads((out / "deploy.json").read_text())
    assert [r["reason"] for r in report["runs"]] == ["done", "done"] and report["shadow"]
    ticks = [json.loads(line) for line in (out / "ref_01.jsonl").read_text().splitlines()[1:-1]]
    assert max(max(map(abs, tick["a"])) for tick in ticks) > 0  # the graph ran: it adjusted, in shadow mode only logged

    # round 1's collection on the machine's computer: through the loop, on the core install alone
    args = (
        "collect",
        "--refs",
        tmp_path / "refs",
        "--out",
        tmp_path / "collected",
        "--loop",
        "--fast",
        "--arm",
        "--passes",
        "1",
    )
    done = run(python, "-c", f"LEFT_OUT = {EXTRA_LIBRARIES!r}\n{IN_PROCESS}", *args)
    assert "collected 2 episodes" in done.stdout and done.stdout.splitlines()[-1] == "imported: ", done.stdout

    # the settings are read without torch
    assert "imagined_share" in run(efficienttrack, "config", "show", "tiny").stdout

    # a command that needs the train extra says so in one line
    done = run(efficienttrack, "export", "--policy", tmp_path / "policy.pt", "--out", tmp_path / "again", code=2)
    assert done.stderr.count("\n") == 1, done.stderr
    assert "needs torch, which is not installed: pip install 'efficienttrack[train]'" in done.stderr
