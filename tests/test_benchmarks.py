"""The benchmark scripts (benchmarks/*.py) run: the cheap ones at their smallest size, the long ones as far as --help.

They are measured by hand, not by tests, so a change that breaks one would otherwise go unnoticed until a measurement.
Each script runs in this process as ``python benchmarks/<script> …`` would run it (``runpy`` as ``__main__``), without
the second or two a fresh interpreter spends importing torch.
"""

import json
import os
import re
import runpy
import shlex
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

SMALL_RUNS = {
    "train_throughput.py": (
        ["--sizes", "tiny", "--steps", "3", "--devices", "cpu"],
        "window-steps/s",
        r"tiny .* on cpu: ([\d,.]+) window-steps/s",
    ),
    "policy_latency.py": (["--calls", "5", "--sizes", "tiny"], "p99", r"tiny .*: wall p50 [\d.]+ ms, p99 ([\d.]+) ms"),
    "onnx_latency.py": (
        ["--calls", "5", "--sizes", "tiny"],
        "guarded step",
        r"guarded step *: wall p50 [\d.]+ ms, p99 ([\d.]+) ms",
    ),
    "sim_throughput.py": (["--seconds", "0.05"], "closed loop steps/s", r"\n *4096 \| *[\d,]+ \| *([\d,]+)\n"),
    "loop_jitter.py": (["--minutes", "0.01", "--size", "tiny"], "missed ticks", r"(\d+) ticks at 20 Hz"),
    "fuzz_loaders.py": (["--mutants", "5"], "escaped in all: 0", r"episode \.npz +\d+ +(\d+) +0 "),
}
"""Benchmarks cheap enough to run here: their smallest arguments, a phrase of the report they must print, and a pattern
of the report whose group is a figure that must be > 0 (a rate, a p99 latency, the ticks run)."""
HELP_ONLY = {
    "baseline_inputs.py": "--method",
    "baseline_probe.py": "--variant",
    "baseline_throughput.py": "--steps",
    "model_vs_simulator.py": "--policy",
    "openloop_smoothness.py": "--k",
    "policy_gradients.py": "--set",
    "oracle_floor.py": "--system",
    "precision.py": "--held-speed",
    "rounds.py": "--presets",
    "rounds_curve.py": "--study-metric",
    "supertrack_ablation.py": "--variant",
    "tdmpc_plan_eval.py": "--train-refs",
    "tdmpc_throughput.py": "--steps",
    "tracking.py": "--seeds",
}
"""Benchmarks that take minutes even at their smallest size: their imports and argument parsing are checked, and their
--help must list this option."""


@pytest.fixture
def run(monkeypatch, capsys):
    """``run(script, *args)`` runs ``benchmarks/<script>`` with ``args`` as its command line, in this process.

    Returns (exit code, stdout, stderr). What a script changes in the process (environment variables such as
    ``OMP_NUM_THREADS``, torch's threads, the global random generators) is restored after the test.
    """
    environ, threads = dict(os.environ), torch.get_num_threads()
    torch_state, numpy_state = torch.get_rng_state(), np.random.get_state()
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # as for `python benchmarks/<script>`: its folder first on sys.path

    def run_script(script: str, *args: str) -> tuple[int, str, str]:
        monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / script), *args])
        code = 0
        try:
            runpy.run_path(str(BENCHMARKS / script), run_name="__main__")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
        out, err = capsys.readouterr()
        return code, out, err

    yield run_script
    os.environ.clear()
    os.environ.update(environ)
    torch.set_num_threads(threads)
    torch.set_rng_state(torch_state)
    np.random.set_state(numpy_state)


def test_every_benchmark_is_covered():
    assert {path.name for path in BENCHMARKS.glob("*.py")} == set(SMALL_RUNS) | set(HELP_ONLY)


@pytest.mark.parametrize("script", sorted(SMALL_RUNS))
def test_benchmark_runs_small(script, tmp_path, run):
    args, phrase, pattern = SMALL_RUNS[script]
    if script == "loop_jitter.py":
        args = [*args, "--out", str(tmp_path)]
    code, out, err = run(script, *args)
    assert code == 0, err[-2000:]
    assert phrase in out
    figure = re.search(pattern, out)
    assert figure, f"no match for {pattern!r} in:\n{out}"
    assert float(figure.group(1).replace(",", "")) > 0, figure.group(0)
    assert f"{script} {shlex.join(args)}" in out  # the command line it was run with, for the record
    if script == "loop_jitter.py":  # the per-tick logs: one record per reference deployed
        references = int(re.search(r"min, (\d+) references", out).group(1))
        assert len(list((tmp_path / "records").glob("*.npz"))) == references >= 1


@pytest.mark.parametrize("script", sorted(HELP_ONLY))
def test_benchmark_parses_its_arguments(script, run):
    code, out, err = run(script, "--help")
    assert code == 0, err[-2000:]
    assert out.startswith(f"usage: {script}")
    description = (BENCHMARKS / script).read_text().split('"""')[1].splitlines()[0]  # argparse's description
    assert " ".join(description.split()) in " ".join(out.split())
    assert "-h, --help" in out and HELP_ONLY[script] in out


def test_rounds_curve_draws_rounds_beside_a_committed_study(tmp_path, run):
    def rounds_run(name, maes, scored=None):  # a run folder's metrics.json with its rounds, and their evaluations
        folder = tmp_path / name
        folder.mkdir()
        rounds = [
            {"round": k, "interaction_steps": 15738 * k, "efficienttrack": {"mae_deg": m}} for k, m in enumerate(maes, 1)
        ]
        (folder / "metrics.json").write_text(json.dumps({"rounds": rounds}))
        for k, m in enumerate(scored or [], 1):
            (folder / "test_eval" / f"round_{k}").mkdir(parents=True)
            (folder / "test_eval" / f"round_{k}" / "metrics.json").write_text(json.dumps({"efficienttrack": {"mae_deg": m}}))
        return str(folder)

    runs = ",".join([rounds_run("s0", [0.5, 0.4, 0.3], [0.9, 0.8]), rounds_run("s1", [0.7, 0.4])])
    study = Path(__file__).resolve().parents[1] / "docs" / "results" / "table1-xe75-closed.json"
    kept, figure = str(tmp_path / "points.json"), str(tmp_path / "f.png")
    code, out, err = run(
        "rounds_curve.py", "--group", f"rounds={runs}", "--study", str(study), "--export", kept, "--out", figure
    )
    assert code == 0, err[-2000:]
    assert "| rounds | 2 | 15,738 → 0.600 ± 0.141, 31,476 → 0.400 ± 0.000 |" in out  # the rounds both seeds have
    assert "| SuperTrack (reduced) (study) | 5 |" in out and (tmp_path / "f.png").stat().st_size > 0
    for name in ("s0", "s1"):
        shutil.rmtree(tmp_path / name)  # the exported points redraw the same without the run folders
    code, again, err = run("rounds_curve.py", "--from", kept, "--study", str(study), "--floor", "xe75=0.337", "--out", figure)
    assert code == 0 and again.split("\nfigure:")[0] == out.split("\nfigure:")[0], err[-2000:]
    assert json.loads(Path(kept).read_text())["command"].startswith("python benchmarks/rounds_curve.py --group")
    runs = ",".join([rounds_run("s0", [0.5, 0.4, 0.3], [0.9, 0.8]), rounds_run("s1", [0.7, 0.4])])
    code, out, err = run("rounds_curve.py", "--group", f"s0={runs.split(',')[0]}", "--scored", "test_eval", "--out",
                         str(tmp_path / "g.png"))  # fmt: skip
    assert "| s0 | 1 | 15,738 → 0.900, 31,476 → 0.800 |" in out  # the evaluated rounds only
    for bad, says in [(["--group", "s0"], "expected NAME=RUN"), (["--group", f"x={tmp_path}"], "no metrics.json"),
                      (["--from", str(tmp_path / "f.png")], "not an --export file"),
                      (["--from", kept, "--floor", "xe75=low"], "expected [PLANT=]MAE")]:  # fmt: skip
        code, out, err = run("rounds_curve.py", *bad, "--out", str(tmp_path / "h.png"))
        assert code == 2 and says in err and "Traceback" not in err


def test_baseline_throughput_refuses_steps_within_the_warm_up(run):
    code, out, err = run("baseline_throughput.py", "--steps", "50")
    assert code == 2
    assert "--steps must exceed SAC's 100 warm-up steps" in err
    assert out == ""  # refused before any measurement
