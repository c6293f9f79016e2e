"""The benchmark scripts (benchmarks/*.py) run: the cheap ones at their smallest size, the long ones as far as --help.

They are measured by hand, not by tests, so a change that breaks one would otherwise go unnoticed until a measurement.
"""

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

SMALL_RUNS = {
    "train_throughput.py": (["--sizes", "tiny", "--steps", "3", "--devices", "cpu"], "window-steps/s"),
    "policy_latency.py": (["--calls", "5", "--sizes", "tiny"], "p99"),
    "onnx_latency.py": (["--calls", "5", "--sizes", "tiny"], "guarded step"),
    "sim_throughput.py": (["--seconds", "0.05"], "closed loop steps/s"),
    "loop_jitter.py": (["--minutes", "0.01", "--size", "tiny"], "missed ticks"),
}
"""Benchmarks cheap enough to run here: their smallest arguments and a phrase of the report they must print."""
HELP_ONLY = ["baseline_inputs.py", "baseline_throughput.py", "precision.py", "rounds.py", "tdmpc_throughput.py", "tracking.py"]
"""Benchmarks that take minutes even at their smallest size: their imports and argument parsing are checked."""


def run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *args], capture_output=True, text=True, timeout=120, check=False
    )


def test_every_benchmark_is_covered():
    assert {path.name for path in BENCHMARKS.glob("*.py")} == set(SMALL_RUNS) | set(HELP_ONLY)


@pytest.mark.parametrize("script", sorted(SMALL_RUNS))
def test_benchmark_runs_small(script, tmp_path):
    args, phrase = SMALL_RUNS[script]
    if script == "loop_jitter.py":
        args = [*args, "--out", str(tmp_path)]
    result = run(script, *args)
    assert result.returncode == 0, result.stderr[-2000:]
    assert phrase in result.stdout


@pytest.mark.parametrize("script", HELP_ONLY)
def test_benchmark_parses_its_arguments(script):
    result = run(script, "--help")
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.startswith("usage:")


def test_baseline_throughput_refuses_steps_within_the_warm_up():
    result = run("baseline_throughput.py", "--steps", "50")
    assert result.returncode == 2
    assert "--steps must exceed SAC's 100 warm-up steps" in result.stderr
