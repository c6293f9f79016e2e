"""The study runner: the job list, a tiny study locally, in a process pool and on Ray, reruns, reports, failures, the CLI;
the validation split and the point selected on it."""

import json
import math
import os
import re
import shutil
import signal
import time
from dataclasses import replace

import numpy as np
import pytest
from matplotlib.axes import Axes
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.metrics import TABLE_METRICS
from efficienttrack.data.references import Reference, save_references
from efficienttrack.envs.core import LOOPS
from efficienttrack.study import (
    METHODS,
    Job,
    Study,
    available_methods,
    executors,
    make_jobs,
    make_study,
    methods,
    report,
    run_study,
)
from efficienttrack.study.executors import Outcome, process_pool
from efficienttrack.study.figure import log_mae_axis, plot_study
from efficienttrack.study.jobs import default_validation, split_validation
from efficienttrack.study.methods import Method, job_settings, point
from efficienttrack.study.paper_table import is_paper_system, paper_row
from efficienttrack.study.report import combine
from efficienttrack.study.run import progress_line
from efficienttrack.study.summary import FIELDS, summarize
from efficienttrack.study.tables import markdown_table
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.collect import pass_counts
from efficienttrack.workflow.config import PRESETS

TINY = PRESETS["tiny"]
FAST = replace(TINY, device="cpu", model=replace(TINY.model, steps=30), policy=replace(TINY.policy, steps=30))
"""The quick preset's EfficientTrack settings, with fewer training steps: a run takes a few seconds."""


@pytest.fixture(scope="module")
def refs():
    """Two short training references and one test reference (60 steps of generated loading cycles)."""
    cycles = [Reference(r.name, r.q[:60]) for r in generate_references(3, seed=1)]
    return cycles[:2], cycles[2:]


def tiny_study(refs, budget=None):
    train, test = refs
    return make_study(SystemSpec(), train, test, budget=budget or 2 * 59, preset="tiny", run_config=FAST)


@pytest.fixture(scope="module")
def refs3(refs):
    """``refs`` with a third training reference, ``val_01``: the one a validation split of 1 holds out of the three."""
    extra = Reference("val_01", generate_references(1, seed=7)[0].q[:60])
    return [*refs[0], extra], refs[1]


@pytest.fixture(scope="module")
def validated(tmp_path_factory, refs3):
    """As ``finished``, with ``val_01`` held out for validation: PD, EfficientTrack, PPO and ILC, in the closed loop.

    No open-loop job: a baseline's points are measured on the validation references as on the test references, in its
    loop (``CurveRecorder.measure``), and ``finished`` runs the open loop's on the test references."""
    out = tmp_path_factory.mktemp("validated")
    train, test = refs3
    study = make_study(SystemSpec(), train, test, budget=2 * 59, preset="tiny", run_config=FAST, validation=1)
    jobs = make_jobs(study, ["pd", "efficienttrack", "ilc", "ppo"])
    lines = []
    result = run_study(study, jobs, out, log=lines.append)
    return out, study, result, lines


@pytest.fixture(scope="module")
def finished(tmp_path_factory, refs):
    """PD, EfficientTrack (one collection pass) and PPO (closed and open loop, the quick settings) run in this process."""
    out = tmp_path_factory.mktemp("study")
    study = tiny_study(refs)
    lines = []
    result = run_study(study, make_jobs(study, ["pd", "efficienttrack", "ppo"], ["closed", "open"]), out, log=lines.append)
    return out, study, result, lines


def failing(job, folder):
    raise RuntimeError("the simulator exploded")


def not_finite(job, folder):
    return [point(10, 1.0, {"mae_deg": math.nan})]


def test_pass_counts_follow_1_2_5_within_the_budget():
    assert pass_counts(1000, 100) == [1, 2, 5, 10]
    assert pass_counts(999, 100) == [1, 2, 5]
    assert pass_counts(99, 100) == []
    assert pass_counts(10**9, 1)[-1] == 1000  # collect.MAX_PASSES


def test_job_list(refs, monkeypatch):
    study = tiny_study(refs)
    jobs = make_jobs(study, ["pd", "ilc", "efficienttrack"], ["closed", "open"], [0, 1])
    # PD and the ILC oracle are deterministic: one job stands for every seed; neither has an open loop
    assert [job.name for job in jobs] == [
        "pd-closed-s0", "ilc-closed-s0", *(f"efficienttrack-{loop}-s{s}" for loop in ("closed", "open") for s in (0, 1))
    ]  # fmt: skip
    assert {job.study for job in jobs} == {study}
    assert [job.method for job in make_jobs(study)] == available_methods()
    for args, message in [
        ((["pd", "dreamer"],), "--methods dreamer: unknown"),
        ((["pd", "pd"],), "--methods pd,pd: give each method once"),
        ((["pd"], ["sideways"]), "--loops sideways: unknown"),
        ((["pd"], ["open"]), "none of these methods has these loops"),
        ((["pd"], ["closed"], [0, 0]), "--seeds 0,0: a seed is repeated"),
        ((["pd"], ["closed"], [-1]), "--seeds: a seed must be"),
    ]:
        with pytest.raises(EfficientTrackError, match=message):
            make_jobs(study, *args)
    with pytest.raises(EfficientTrackError, match="--budget 100: less than one collection pass .*118"):
        make_jobs(tiny_study(refs, budget=100), ["efficienttrack"])
    # the open loop needs a PWM-level plant: the built-in xe75 has one, a reference-level system does not
    monkeypatch.setitem(METHODS, "fake", Method("fake", "Fake", failing, LOOPS))
    assert [job.name for job in make_jobs(study, ["fake"], ["closed", "open"])] == ["fake-closed-s0", "fake-open-s0"]
    toy = replace(study, system=SystemSpec(system="toy_system:make"))
    with pytest.raises(EfficientTrackError, match="--loops open: the system toy_system:make has no PWM-level plant"):
        make_jobs(toy, ["fake"], ["open"])
    with pytest.raises(EfficientTrackError, match="--preset 'huge'"):
        make_study(SystemSpec(), *refs, preset="huge")


def test_sb3_methods_are_registered_with_both_loops():
    for name in ("sac", "ppo"):
        assert METHODS[name].loops == LOOPS
        assert "efficienttrack.baselines.sb3" in METHODS[name].requires
    for name in ("efficienttrack", "supertrack", "tdmpc"):
        assert METHODS[name].loops == LOOPS
    assert METHODS["ilc"].loops == ("closed",) and not METHODS["ilc"].seeded


@pytest.mark.slow
def test_study_writes_table_json_and_figure(finished):
    out, study, result, lines = finished
    names = ("pd-closed-s0", "efficienttrack-closed-s0", "efficienttrack-open-s0", "ppo-closed-s0", "ppo-open-s0")
    assert result.ran == names and not result.failed and not result.skipped
    assert lines[0].endswith("5 jobs, 0 finished earlier (skipped), 5 to run (local)")
    assert lines[2].startswith("[2/5] efficienttrack-closed-s0 done in") and lines[2].endswith("at 118 interaction steps")
    entries = json.loads((out / "study.json").read_text())
    assert [(e["method"], e["loop"], e["seeds"]) for e in entries] == [
        ("pd", "closed", [0]), ("efficienttrack", "closed", [0]), ("efficienttrack", "open", [0]), ("ppo", "closed", [0]),
        ("ppo", "open", [0]),
    ]  # fmt: skip
    pd, et, et_open, ppo, _ = entries
    assert et_open["interaction_steps"] == 118
    open_job = json.loads((out / "jobs" / "efficienttrack-open-s0" / "result.json").read_text())
    assert [p["passes"] for p in open_job["curve"]] == [1]
    assert pd["interaction_steps"] == 0 and pd["interaction_hours"] == 0
    assert et["interaction_steps"] == 118 and et["interaction_hours"] == pytest.approx(118 / 20 / 3600)
    for entry in entries:
        for field in FIELDS:
            if (entry["method"], field) == ("pd", "samples_per_step"):  # no interaction step to share compute over
                assert entry[field] is None
                continue
            assert math.isfinite(entry[field]) and entry[f"{field}_std"] is None  # one seed: no spread
        assert entry["episodes"] == 1 and len(entry["per_joint_mae_deg"]) == 4
        points = entry["curves"][0]["points"]
        assert entry["mae_deg"] == max(points, key=lambda p: p["interaction_steps"])["mae_deg"]  # the final point
        assert entry["best_mae_deg"] == min(p["mae_deg"] for p in points)
    assert et["mae_deg"] != pd["mae_deg"]
    assert et["samples_per_step"] == pytest.approx((30 * 64 + 30 * 64) / 118)  # both trainings' windows (FAST)
    assert ppo["samples_per_step"] == 0  # its first update comes after a rollout of 4 × 32 steps, past the budget
    # PPO (4 environments, the quick preset) is evaluated at 1, 2, 5, 10, 20, 50, 100 steps, as multiples of 4, and at 118
    assert [p["interaction_steps"] for p in ppo["curve"]] == [4, 8, 12, 20, 52, 100, 120]
    # the job's own record of its curve, and the run folder of its one pass count
    job = json.loads((out / "jobs" / "efficienttrack-closed-s0" / "result.json").read_text())
    assert [p["passes"] for p in job["curve"]] == [1] and job["seed"] == 0
    assert job["curve"][0]["metrics"]["mae_deg"] == pytest.approx(et["mae_deg"])
    assert (out / "jobs" / "efficienttrack-closed-s0" / "passes_1" / "policy.pt").is_file()
    config = json.loads((out / "study_config.json").read_text())
    assert config["budget"] == 118 and config["preset"] == "tiny" and config["system"]["system"] == "xe75"
    table = (out / "study.md").read_text()
    assert (
        "| PD | closed | 1 | 0 |" in table and "| EfficientTrack | closed | 1 | 118 |" in table and "| PPO | open |" in table
    )
    assert "| wall (s) | grad. samples / I.S. |" in table
    header = (out / "study.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["method", "loop", "seeds", "interaction_steps"]
    assert {f"{m}_std" for m in TABLE_METRICS} <= set(header)
    assert (out / "study.png").is_file()


@pytest.mark.slow
def test_rerun_skips_finished_jobs_and_refuses_another_study(finished, refs):
    out, study, _, _ = finished
    results = sorted((out / "jobs").glob("*/result.json"))
    before = [path.stat().st_mtime_ns for path in results]
    rerun = run_study(study, make_jobs(study, ["pd", "efficienttrack"]), out, log=lambda line: None)
    assert rerun.skipped == ("pd-closed-s0", "efficienttrack-closed-s0") and rerun.ran == ()
    assert [path.stat().st_mtime_ns for path in results] == before
    other = tiny_study(refs, budget=1000)
    with pytest.raises(EfficientTrackError, match="study_config.json: this folder holds a study of another"):
        run_study(other, make_jobs(other, ["pd"]), out)


@pytest.mark.slow
@pytest.mark.figures
def test_report_is_rebuilt_from_the_folders(finished, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(finished[0], out)
    for name in ("study.json", "study.md", "study.csv", "study.png"):
        (out / name).unlink()
    # a second seed, found only as a folder: its MAE 1° higher at the same interaction steps
    seed0 = json.loads((out / "jobs" / "efficienttrack-closed-s0" / "result.json").read_text())
    seed1 = {**seed0, "seed": 1, "curve": [{**p, "metrics": {**p["metrics"], "mae_deg": p["metrics"]["mae_deg"] + 1}}
                                           for p in seed0["curve"]]}  # fmt: skip
    (out / "jobs" / "efficienttrack-closed-s1").mkdir()
    (out / "jobs" / "efficienttrack-closed-s1" / "result.json").write_text(json.dumps(seed1))
    (out / "jobs" / "broken-closed-s0").mkdir()
    (out / "jobs" / "broken-closed-s0" / "error.json").write_text(json.dumps({"error": "ValueError: bad"}))
    (out / "jobs" / "pd-closed-s1").mkdir()
    (out / "jobs" / "pd-closed-s1" / "result.json").write_text('{"method": "pd", "lo')  # truncated by a crash
    rebuilt = report(out)
    assert all(path.is_file() for path in rebuilt.paths)
    assert (out / "study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    et = rebuilt.entries[1]
    mae0 = seed0["curve"][0]["metrics"]["mae_deg"]
    assert et["seeds"] == [0, 1] and et["mae_deg"] == pytest.approx(mae0 + 0.5)
    assert et["mae_deg_std"] == pytest.approx(np.std([mae0, mae0 + 1], ddof=1))
    assert et["curve"][0]["seeds"] == 2 and et["curve"][0]["mae_deg"] == pytest.approx(mae0 + 0.5)
    assert rebuilt.failed["broken-closed-s0"] == "ValueError: bad"
    assert rebuilt.failed["pd-closed-s1"].startswith("unreadable result.json (damaged or truncated)")
    assert "`pd-closed-s1`: unreadable result.json" in (out / "study.md").read_text()
    assert "`broken-closed-s0`: ValueError: bad" in (out / "study.md").read_text()
    assert json.loads((out / "study.json").read_text()) == json.loads(json.dumps(rebuilt.entries))
    with pytest.raises(EfficientTrackError, match="no study here"):
        report(tmp_path / "nothing")


def test_the_table_gives_the_final_point_and_the_best_on_test_apart_with_the_papers_rows():
    def result(seed, maes):
        points = [{"interaction_steps": 10 * i, "wall_seconds": i, "metrics": {**dict.fromkeys(TABLE_METRICS, 1.0),
                   "mae_deg": m, "per_joint_mae_deg": [m] * 4}} for i, m in enumerate(maes)]  # fmt: skip
        return {"method": "efficienttrack", "loop": "closed", "seed": seed, "curve": points}

    (entry,) = summarize([result(0, [3.0, 1.0, 2.0]), result(1, [3.0, 2.0, 4.0])])
    assert entry["mae_deg"] == 3.0 and entry["interaction_steps"] == 20  # the last points: 2 and 4
    assert entry["mae_deg_std"] == pytest.approx(np.std([2.0, 4.0], ddof=1))
    assert entry["best_mae_deg"] == 1.5 and entry["best_interaction_steps"] == 10  # the lowest test MAEs: 1 and 2
    assert [f["seed"] for f in entry["final"]] == [0, 1] and entry["per_joint_mae_deg"] == [3.0] * 4
    plain = markdown_table([entry], {})
    assert "final point" in plain and "| EfficientTrack | closed | 2 | 20 ± 0 |" in plain and "Table I" not in plain
    assert "| 3.00 ± 1.41 |" in plain and plain.count("| 1.50 ± 0.71 | 10 ± 0 |") == 1
    paper = markdown_table([entry], {}, paper=True)
    published = "| *paper, Table I* | closed |  | *176,720* | *2.454* | *–* | *–* | *0.32* | *0.46* | *0.23* | *0.670* | "
    published += "*0.590* |"
    assert published in paper
    variant = {**entry, "settings_changes": ["efficienttrack.policy.k_smooth=2"]}
    both = markdown_table([entry, variant], {}, paper=True).split("\n\n")[1].splitlines()  # the first table's rows
    assert [line.split(" | ")[0] for line in both[2:]] == [
        "| EfficientTrack",
        "| EfficientTrack (policy.k_smooth=2)",
        "| *paper, Table I*",
    ]  # once, under the method's last variant
    assert paper_row("pd", "open")["mae_deg"] == 2.73 and paper_row("ilc", "closed") is None
    assert is_paper_system({"system": "paper", "plant": None, "pd": None, "options": {}})
    assert is_paper_system({"system": None, "plant": "paper", "pd": "paper", "options": {}})
    assert not is_paper_system({"system": "xe75", "plant": None, "pd": None, "options": {}})
    assert not is_paper_system({"system": "paper", "plant": None, "pd": None, "options": {"seed": 1}})


def test_the_figure_draws_mae_on_a_log_axis_only_when_the_curves_span_a_decade():
    def entries(*maes):
        return [{"curve": [{"interaction_steps": 0, "mae_deg": maes[0]}]},
                {"curve": [{"interaction_steps": n, "mae_deg": m} for n, m in enumerate(maes[1:], 1)]}]  # fmt: skip

    assert not log_mae_axis(entries(4.9, 1.5, 0.7))  # the closed-loop curves: 7× apart, a linear axis from 0
    assert log_mae_axis(entries(4.9, 38.9, 0.69))  # an open-loop start at 39° beside 0.69°
    assert not log_mae_axis(entries(0.0, 5.0, 0.6))  # an MAE of 0 has no logarithm and is left out
    assert not log_mae_axis([])


def test_a_failing_job_is_reported_and_the_others_finish(refs, tmp_path, monkeypatch):
    monkeypatch.setitem(METHODS, "boom", Method("boom", "Boom", failing, ("closed",)))
    monkeypatch.setitem(METHODS, "nan", Method("nan", "NaN", not_finite, ("closed",)))
    study = tiny_study(refs)
    lines = []
    result = run_study(study, make_jobs(study, ["boom", "pd", "nan"]), tmp_path, log=lines.append)
    assert result.ran == ("pd-closed-s0",)
    assert result.failed == {
        "boom-closed-s0": "RuntimeError: the simulator exploded",
        "nan-closed-s0": "point 0 of the curve: 'metrics' must hold a finite 'mae_deg', got nan",
    }
    assert "[1/3] boom-closed-s0 FAILED: RuntimeError: the simulator exploded" in lines
    assert (
        "the simulator exploded" in json.loads((tmp_path / "jobs" / "boom-closed-s0" / "error.json").read_text())["traceback"]
    )
    assert not (tmp_path / "jobs" / "boom-closed-s0" / "result.json").exists()
    assert [e["method"] for e in result.report.entries] == ["pd"] and set(result.report.failed) == set(result.failed)
    # a rerun runs the failed jobs again, and only them
    rerun = run_study(study, make_jobs(study, ["boom", "pd"]), tmp_path, log=lambda line: None)
    assert rerun.skipped == ("pd-closed-s0",) and list(rerun.failed) == ["boom-closed-s0"]


@pytest.mark.slow
def test_process_pool_runs_jobs_in_spawned_workers(refs, tmp_path):
    study = tiny_study(refs)
    jobs = [Job("pd", "closed", seed, study) for seed in (0, 1)]
    result = run_study(study, jobs, tmp_path, workers=2, log=lambda line: None)
    assert sorted(result.ran) == ["pd-closed-s0", "pd-closed-s1"] and not result.failed
    maes = [json.loads((tmp_path / "jobs" / name / "result.json").read_text())["curve"][0]["metrics"]["mae_deg"]
            for name in result.ran]  # fmt: skip
    assert maes[0] == maes[1]


@pytest.mark.slow
def test_a_worker_that_dies_fails_no_job_and_its_jobs_run_once_more_alone(refs, tmp_path, monkeypatch):
    from toy_system import DIE_ONCE

    marker = tmp_path / "die"
    marker.touch()
    monkeypatch.setenv(DIE_ONCE, str(marker))
    train, test = refs
    study = make_study(SystemSpec(system="toy_system:make_dying"), train, test, budget=2 * 59, preset="tiny", run_config=FAST)
    jobs = [Job("pd", "closed", seed, study) for seed in (0, 1)]
    result = run_study(study, jobs, tmp_path / "out", workers=2, log=lambda line: None)
    assert not marker.exists()  # a worker took it and died, breaking the pool
    assert sorted(result.ran) == ["pd-closed-s0", "pd-closed-s1"] and not result.failed


def test_a_stop_signal_to_a_local_study_stops_its_workers_instead_of_waiting_for_them(default_stop_signals):
    with pytest.raises(KeyboardInterrupt), process_pool(2) as pool:
        assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # else the kill below ends the test run
        futures = [pool.submit(time.sleep, 60) for _ in range(3)]  # two running jobs and one queued
        while len(pool._processes) < 2 or not (futures[0].running() and futures[1].running()):
            time.sleep(0.05)
        workers = list(pool._processes.values())
        started = time.monotonic()
        os.kill(os.getpid(), signal.SIGTERM)
        futures[0].result()
    assert time.monotonic() - started < 20  # not the 60 s of the jobs
    deadline = time.monotonic() + 10  # a worker whose exit is not reaped yet still counts as alive for a moment
    while (any(worker.is_alive() for worker in workers) or not futures[2].done()) and time.monotonic() < deadline:
        time.sleep(0.05)  # and the pool's shutdown settles the queued job's future a moment later, under load
    assert not any(worker.is_alive() for worker in workers)
    assert futures[2].cancelled() or futures[2].exception(timeout=0) is not None  # the queued job never ran


def test_cli_study(refs, tmp_path, monkeypatch):
    monkeypatch.setitem(METHODS, "boom", Method("boom", "Boom", failing, ("closed",)))
    save_references(refs[0], tmp_path / "train")
    save_references(refs[1], tmp_path / "test")
    out = tmp_path / "study"
    common = ["study", "--train-refs", tmp_path / "train", "--test-refs", tmp_path / "test", "--out", out, "--preset", "tiny"]
    result = CliRunner().invoke(app, [str(a) for a in [*common, "--methods", "pd,boom"]], env={"COLUMNS": "200"})
    assert result.exit_code == 1, result.output  # a job failed; the other finished and the report is written
    assert "pd-closed-s0 done in" in result.output and "boom-closed-s0 FAILED: RuntimeError" in result.output
    assert [e["method"] for e in json.loads((out / "study.json").read_text())] == ["pd"]
    again = CliRunner().invoke(app, ["study", "--out", str(out), "--report-only"])
    assert again.exit_code == 0 and "| PD | closed |" in again.output
    for extra, message in [
        (["--methods", "pd", "--executor", "slurm"], "--executor slurm: unknown"),
        (["--methods", "pd", "--address", "10.0.0.1:6379"], "--address 10.0.0.1:6379: only with --executor ray"),
        (["--methods", "pd", "--jobs", "0"], "--jobs 0"),
        (["--methods", "pd", "--seeds", "a"], "--seeds 'a'"),
        (["--methods", "pd", "--method-budget", "sac"], "--method-budget 'sac': expected METHOD=STEPS"),
        (["--methods", "pd", "--budget", "5000"], "holds a study of another system, references, budget"),
        (["--methods", "pd", "--validation", "1"], "--validation 1: would hold out 1 of the 2 training references"),
        (["--methods", "pd", "--method-set", "ilc.trials"], "--method-set 'ilc.trials': expected METHOD.field=value"),
        (["--methods", "pd", "--method-set", "ilc.trials=1"], "holds a study of another system, references, budget"),
    ]:
        refused = CliRunner().invoke(app, [str(a) for a in [*common, *extra]])
        assert isinstance(refused.exception, EfficientTrackError) and message in str(refused.exception), refused.output
    forced = CliRunner().invoke(app, [str(a) for a in [*common, "--methods", "pd", "--budget", "5000", "--force"]])
    assert forced.exit_code == 0 and json.loads((out / "study_config.json").read_text())["budget"] == 5000
    assert not (out / "jobs" / "boom-closed-s0").exists()
    assert "validation" not in json.loads((out / "study_config.json").read_text())  # two references: none held out


def test_a_method_budget_replaces_the_study_budget_for_that_method(refs):
    train, test = refs
    study = make_study(SystemSpec(), train, test, budget=2 * 59, preset="tiny", run_config=FAST, method_budgets={"ppo": 64})
    jobs = {job.method: job for job in make_jobs(study, ["efficienttrack", "ppo"])}
    assert jobs["ppo"].budget == 64 and jobs["efficienttrack"].budget == 2 * 59
    assert study.identity()["method_budgets"] == {"ppo": 64, "tdmpc": 2_000}  # the quick preset's own for TD-MPC
    with pytest.raises(EfficientTrackError, match="--method-budget efficienttrack=50: less than one collection pass"):
        make_jobs(make_study(SystemSpec(), train, test, 2 * 59, "tiny", FAST, {"efficienttrack": 50}), ["efficienttrack"])
    with pytest.raises(EfficientTrackError, match="--method-budget nope=…: unknown method"):
        make_jobs(make_study(SystemSpec(), train, test, 2 * 59, "tiny", FAST, {"nope": 50}), ["pd"])


def test_the_ilc_oracle_runs_as_a_study_method_below_pd(refs, tmp_path):
    study = tiny_study(refs)
    result = run_study(study, make_jobs(study, ["pd", "ilc"]), tmp_path, log=lambda line: None)
    best = {entry["method"]: entry["mae_deg"] for entry in result.report.entries}
    assert best["ilc"] < 0.7 * best["pd"]  # after the few trials of the tiny budget, at the gain of 0.35
    assert "ILC (oracle" in result.report.markdown
    with pytest.raises(EfficientTrackError, match="--method-budget ilc=10: less than one ILC trial .*59 steps"):
        make_jobs(make_study(SystemSpec(), *refs, 2 * 59, "tiny", FAST, {"ilc": 10}), ["ilc"])


def test_the_quick_preset_gives_td_mpc_a_smaller_budget_that_the_user_may_override(refs):
    train, test = refs
    assert make_study(SystemSpec(), train, test, preset="tiny").budget_of("tdmpc") == 2_000
    assert make_study(SystemSpec(), train, test, preset="tiny", method_budgets={"tdmpc": 500}).budget_of("tdmpc") == 500
    assert make_study(SystemSpec(), train, test, preset="cpu").budget_of("tdmpc") == 200_000


def test_a_study_refuses_an_unknown_preset(refs):
    with pytest.raises(EfficientTrackError, match="--preset 'huge': unknown"):
        Study(SystemSpec(), tuple(refs[0]), tuple(refs[1]), 118, "huge", FAST)


def test_the_validation_split_is_fixed_disjoint_and_leaves_most_references_for_training(refs3):
    refs = [Reference(f"ref_{i:02d}", np.full((5, 4), 0.01 * i)) for i in range(10)]
    kept, held = split_validation(refs, 3)
    assert [r.name for r in held] == ["ref_02", "ref_04", "ref_06"]  # the first 3 of a fixed permutation, in order
    assert [r.name for r in kept] == [r.name for r in refs if r not in held]
    assert split_validation(refs[::-1], 3) == (kept[::-1], held[::-1])  # the same ones, whatever the order given
    assert split_validation(refs, 0) == (tuple(refs), ())
    assert [default_validation(n) for n in (40, 10, 9, 2)] == [4, 1, 0, 0]  # a tenth, rounded down
    assert split_validation(refs, 4)[1][:3] == held  # one more held out keeps the first ones
    for count, message in [
        (5, "--validation 5: would hold out 5 of the 10 training references; hold out fewer than half (at most 4 here)"),
        (-1, "--validation -1: expected a number of training references ≥ 0"),
        (1.5, "--validation 1.5: expected"),
    ]:
        with pytest.raises(EfficientTrackError, match=re.escape(message)):
            split_validation(refs, count)
    train, test = refs3
    study = make_study(SystemSpec(), train, test, budget=2 * 59, preset="tiny", run_config=FAST, validation=1)
    assert [r.name for r in study.validation] == ["val_01"] and [r.name for r in study.train] == ["ref_01", "ref_02"]
    validation, others = ({r.q.tobytes() for r in part} for part in (study.validation, (*study.train, *study.test)))
    assert validation and not validation & others  # disjoint from the training and the test references
    assert study.steps_per_pass == 2 * 59  # the held-out reference is not collected on
    identity = study.identity()
    assert identity["validation"] == 1 and identity["validation_references"] == {"val_01": 60}
    assert list(identity["train_references"]) == ["ref_01", "ref_02", "val_01"]  # every training reference given
    plain = make_study(SystemSpec(), train, test, budget=3 * 59, preset="tiny", run_config=FAST).identity()  # 3: none
    assert "validation" not in plain and "validation_references" not in plain  # as before the setting
    with pytest.raises(EfficientTrackError, match="--validation 1: would hold out 1 of the 2 training references"):
        make_study(SystemSpec(), train[:2], test, preset="tiny", validation=1)


def test_a_study_folder_with_another_validation_split_is_refused_naming_it(refs3, tmp_path):
    train, test = refs3
    studies = {n: make_study(SystemSpec(), train, test, 2 * 59, "tiny", FAST, validation=n) for n in (0, 1)}
    for made, rerun, difference in [(0, 1, "validation: absent here, 1 now"), (1, 0, "validation: 1 here, absent now")]:
        out = tmp_path / f"made-with-{made}"
        run_study(studies[made], make_jobs(studies[made], ["pd"]), out, log=lambda line: None)
        with pytest.raises(EfficientTrackError, match=f"study_config.json: this folder holds a study of .*{difference}"):
            run_study(studies[rerun], make_jobs(studies[rerun], ["pd"]), out)
        again = run_study(studies[made], make_jobs(studies[made], ["pd"]), out, log=lambda line: None)
        assert again.skipped == ("pd-closed-s0",)  # the same setting resumes


def test_the_report_selects_each_seeds_point_on_validation_and_gives_its_test_mae():
    def result(seed, maes, validation, method="efficienttrack"):
        points = [{"interaction_steps": 10 * i, "wall_seconds": i, "metrics": {**dict.fromkeys(TABLE_METRICS, 1.0),
                   "mae_deg": m, "per_joint_mae_deg": [m] * 4}} for i, m in enumerate(maes)]  # fmt: skip
        for p, v in zip(points, validation or [], strict=False):
            p["validation"] = {**p["metrics"], "mae_deg": v}
        return {"method": method, "loop": "closed", "seed": seed, "curve": points, "wall_seconds": 1.0}

    seed0 = result(0, [3.0, 1.0, 2.0], [2.5, 1.8, 1.2])  # validation chooses the last point; test's best is the middle
    seed1 = result(1, [3.0, 2.0, 4.0], [3.0, 1.0, 1.0])  # a tie on validation: the earlier point
    partial = result(1, [3.0, 2.0], [3.0])  # a point without validation: no choice for the seed
    et, ppo = summarize([seed0, seed1, result(0, [5.0, 4.0], None, "ppo"), {**partial, "method": "ppo"}])
    assert [p["interaction_steps"] for p in et["selected"]] == [20, 10] and [p["seed"] for p in et["selected"]] == [0, 1]
    assert [p["mae_deg"] for p in et["selected"]] == [2.0, 2.0] and et["selected"][0]["validation_mae_deg"] == 1.2
    assert et["selected_mae_deg"] == 2.0 and et["selected_mae_deg_std"] == 0.0
    assert et["selected_interaction_steps"] == 15
    assert et["selected_interaction_steps_std"] == pytest.approx(np.std([20, 10], ddof=1))
    assert et["mae_deg"] == 3.0 and et["best_mae_deg"] == 1.5  # the final and the optimistic points, unchanged
    assert et["curves"][0]["points"][2]["validation_mae_deg"] == 1.2
    assert ppo["selected"] is None and ppo["selected_mae_deg"] is None and ppo["selected_mae_deg_std"] is None
    table = markdown_table([et, ppo], {})
    assert "selected on validation" in table.splitlines()[0] and "mean ± sample std over seeds" in table.splitlines()[0]
    assert (
        "| MAE 95 % CI (°) | selected MAE (°) | selected 95 % CI (°) | I.S. selected | best MAE (°) | I.S. at best |" in table
    )
    assert "| [2.000, 4.000] | 2.00 ± 0.00 | [2.000, 2.000] | 15 ± 7 | 1.50 ± 0.71 | 10 ± 0 |" in table  # EfficientTrack
    assert "| [2.000, 4.000] | – | – | – | 3.00 ± 1.41 | 10 ± 0 |" in table  # PPO: a seed without validation, no selection
    assert et["selection_steps"] == 0 + 10 + 20 and ppo["selection_steps"] is None  # EfficientTrack's points: runs
    assert "chosen among runs that took 30 interaction steps in all" in table
    [supertrack] = summarize([{**seed0, "method": "supertrack"}])
    assert supertrack["selection_steps"] is None  # its points are one run's checkpoints
    line = progress_line(Outcome("efficienttrack-closed-s0", seed0, None), 1, 2)
    assert line.endswith("final MAE 2.00° at 20 interaction steps; selected on validation: 2.00° at 20")
    assert progress_line(Outcome("ppo-closed-s1", partial, None), 2, 2).endswith("final MAE 2.00° at 10 interaction steps")


@pytest.mark.slow
def test_a_study_with_validation_measures_every_point_on_it_and_reports_the_selected_point(validated, finished):
    out, study, result, lines = validated
    assert not result.failed and len(result.ran) == 4
    config = json.loads((out / "study_config.json").read_text())
    assert config["validation"] == 1 and config["validation_references"] == {"val_01": 60}
    for name in result.ran:
        job = json.loads((out / "jobs" / name / "result.json").read_text())
        if job["method"] == "ilc":  # the oracle learns on the test references: nothing to validate
            assert all("validation" not in p for p in job["curve"])
            continue
        assert all(p["validation"]["episodes"] == 1 and p["validation"]["mae_deg"] > 0 for p in job["curve"]), name
    # EfficientTrack trained on the two references left, and its policy was scored on the held-out one
    run = json.loads((out / "jobs" / "efficienttrack-closed-s0" / "passes_1" / "run.json").read_text())
    assert list(run["train_references"]) == ["ref_01", "ref_02"]
    assert (out / "jobs" / "efficienttrack-closed-s0" / "validation" / "passes_1" / "metrics.json").is_file()
    entries = {(e["method"], e["loop"]): e for e in result.report.entries}
    for key, entry in entries.items():
        curve = json.loads((out / "jobs" / f"{key[0]}-{key[1]}-s0" / "result.json").read_text())["curve"]
        if key[0] == "ilc":
            assert entry["selected"] is None
            continue
        chosen = min(curve, key=lambda p: p["validation"]["mae_deg"])
        assert entry["selected_mae_deg"] == chosen["metrics"]["mae_deg"], key
        assert entry["selected_interaction_steps"] == chosen["interaction_steps"], key
    assert "; selected on validation: " in lines[2]
    assert "| EfficientTrack | closed | 1 | 118 |" in result.report.markdown
    # the same training references and seeds as the study without validation: the same test figures, point by point
    plain = {(e["method"], e["loop"]): e["curves"] for e in finished[2].report.entries}
    for key in [("pd", "closed"), ("efficienttrack", "closed"), ("ppo", "closed")]:
        ours = [p["mae_deg"] for p in entries[key]["curves"][0]["points"]]
        assert ours == pytest.approx([p["mae_deg"] for p in plain[key][0]["points"]]), key


@pytest.mark.slow
def test_the_studys_efficienttrack_job_on_ray_gives_exactly_what_run_gives_with_the_same_settings_and_seed(refs, tmp_path):
    """The study's closed-loop EfficientTrack job (no validation references) at p passes is ``run`` with the same preset,
    seed, passes, references and system: the same settings, episodes and test metrics to the last bit (issue #26).

    The study runs its jobs (EfficientTrack's and PD's) with the Ray executor: with no ``ray.init`` here, it starts a
    local instance (1 CPU, a 200 MB object store, no dashboard) and stops it. What a Ray worker gives is what ``run``
    gives in this process."""
    import ray  # the study extra's, as the SB3 baselines'

    save_references(refs[0], tmp_path / "train")
    save_references(refs[1], tmp_path / "test")
    folders = ["--train-refs", tmp_path / "train", "--test-refs", tmp_path / "test"]
    sizes = ["--preset", "tiny", "--set", "model.steps=10", "--set", "policy.steps=10"]  # seconds: only equality counts
    seed, passes = 3, 2  # not the default seed; the study runs 1 and 2 passes (budget 2 × 118), the last is compared
    study = [*folders, "--out", tmp_path / "study", *sizes, "--set", "device=cpu", "--methods", "pd,efficienttrack",
             "--seeds", seed, "--budget", passes * 118, "--validation", 0, "--executor", "ray"]  # fmt: skip
    run = [*folders, "--out", tmp_path / "run", *sizes, "--set", f"collect.passes={passes}", "--seed", seed,
           "--device", "cpu", "--plots", 0]  # fmt: skip
    for command, args in (("study", study), ("run", run)):
        result = CliRunner().invoke(app, [command, *map(str, args)])
        assert result.exit_code == 0, result.output
    assert not ray.is_initialized()
    jobs = tmp_path / "study" / "jobs"
    job = jobs / f"efficienttrack-closed-s{seed}"
    ours = json.loads((job / "result.json").read_text())["curve"][-1]
    theirs = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert ours["passes"] == passes and ours["interaction_steps"] == theirs["interaction_steps"] == passes * 118
    assert ours["metrics"] == theirs["efficienttrack"]  # equal, not approximately
    [pd] = jobs.glob("pd-closed-*/result.json")
    assert json.loads(pd.read_text())["curve"][0]["metrics"] == theirs["pd"]
    assert (tmp_path / "study" / "study.png").is_file() and (job / "job.log").is_file()
    folders = (job / f"passes_{passes}", tmp_path / "run")
    same_run = [{k: v for k, v in json.loads((f / "run.json").read_text()).items() if k != "provenance"} for f in folders]
    assert same_run[0] == same_run[1]  # settings (seed, collect.seed, passes), system, references and their order
    assert same_run[1]["config"]["collect"] == {**same_run[1]["config"]["collect"], "seed": seed, "passes": passes}
    for method in ("pd", "efficienttrack"):
        for ref in refs[1]:
            a, b = (np.load(f / "records" / method / f"{ref.name}.npz") for f in folders)
            assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files), (method, ref.name)


def test_method_set_changes_a_methods_settings_and_the_table_names_the_change(refs, tmp_path):
    plain = tiny_study(refs)
    changes = ["ilc.trials=1", "ilc.gain=[0.5, 0.5, 0.5, 0.5]"]
    changed = make_study(SystemSpec(), *refs, 2 * 59, "tiny", FAST, method_settings=changes)
    (job,) = make_jobs(changed, ["ilc"])
    assert job.settings_changes == tuple(changes)
    assert (job_settings(job).trials, job_settings(job).gain) == (1, (0.5,) * 4)
    assert job_settings(make_jobs(plain, ["ilc"])[0]) == "tiny"  # no change: the preset's name, as before
    assert changed.identity()["method_settings"] == {"ilc": changes}
    assert "method_settings" not in plain.identity()
    run_study(plain, make_jobs(plain, ["ilc"]), tmp_path / "plain", log=lambda line: None)
    run_study(changed, [job], tmp_path / "changed", log=lambda line: None)
    result = json.loads((tmp_path / "changed" / "jobs" / "ilc-closed-s0" / "result.json").read_text())
    assert result["settings_changes"] == changes
    both = combine([tmp_path / "plain", tmp_path / "changed"], tmp_path / "both.png")  # not one job twice: two entries
    assert [entry.get("settings_changes") for entry in both.entries] == [None, changes]
    assert [len(entry["curve"]) for entry in both.entries] == [3, 2]  # trials 0, 1, 2 within the budget; 0, 1
    assert "| ILC (oracle: sees the test references) (trials=1, gain=[0.5, 0.5, 0.5, 0.5]) | closed |" in both.markdown


@pytest.mark.parametrize(
    ("changes", "methods", "message"),
    [
        (["nope.x=1"], ["pd"], "--method-set nope.x=1: unknown method, choose from efficienttrack, sac"),
        (["pd.kp=1"], ["pd"], "--method-set pd.kp=1: pd has no settings to change"),
        (["efficienttrack-rounds.rounds=2"], ["pd"], "has no settings to change \\(it runs the closed loop's settings: --set"),
        (["ilc.trails=1"], ["ilc"], r"--method-set ilc.trails=1: unknown ILCSettings field\(s\) trails"),
        (["ilc.trials=0"], ["ilc"], "--method-set ilc.trials=0: trials must be an integer ≥ 1, got 0"),
        (["ilc.trials=2", "ilc.gain=0.5"], ["ilc"], "--method-set ilc.gain=0.5: gain must be a list of 4 finite numbers > 0"),
        (["supertrack.policy.lr=fast"], ["pd"], "--method-set supertrack.policy.lr=fast: policy.lr must be a finite"),
        (["efficienttrack.k_smooth=1"], ["efficienttrack"], "changes open-loop EfficientTrack, and no job runs it.*--set"),
    ],
)
def test_method_set_refuses_a_change_no_job_can_make_before_any_job_runs(refs, changes, methods, message):
    study = make_study(SystemSpec(), *refs, 2 * 59, "tiny", FAST, method_settings=changes)
    with pytest.raises(EfficientTrackError, match=message):
        make_jobs(study, methods)


def test_method_set_must_name_a_method_and_a_field():
    with pytest.raises(EfficientTrackError, match="--method-set 'trials=1': expected METHOD.field=value"):
        make_study(SystemSpec(), [], [], method_settings=["trials=1"])


def test_the_figure_draws_each_settings_variant_of_a_method_with_its_own_line(tmp_path, monkeypatch):
    points = [{"interaction_steps": s, "interaction_hours": s / 72_000, "mae_deg": m} for s, m in ((100, 2.0), (200, 1.0))]
    entries = [{"method": "supertrack", "loop": "open", "curve": points, "selected": None}] + [
        {"method": "supertrack", "loop": "open", "settings_changes": [f"supertrack.noise_open={v}"], "curve": points,
         "selected": None}
        for v in (0.1, 0.5)
    ]  # fmt: skip
    drawn = []
    plot = Axes.plot

    def spy(self, *args, **kwargs):
        lines = plot(self, *args, **kwargs)
        drawn.extend((line.get_label(), line.get_linestyle()) for line in lines)
        return lines

    monkeypatch.setattr(Axes, "plot", spy)
    plot_study(entries, tmp_path / "variants.png")
    assert drawn[:3] == [
        ("SuperTrack (reduced) (open loop)", "-"),
        ("SuperTrack (reduced) (noise_open=0.1) (open loop)", "--"),
        ("SuperTrack (reduced) (noise_open=0.5) (open loop)", ":"),
    ]


def test_a_jobs_provenance_names_the_commit_it_started_from(refs, tmp_path, monkeypatch):
    commits = iter(["a" * 40, "b" * 40])  # a commit made while the job ran
    real = executors.provenance
    monkeypatch.setattr(executors, "provenance", lambda **kw: {**real(**kw), "git_commit": next(commits)})
    [job] = make_jobs(tiny_study(refs), ["pd"])
    facts = executors.execute(job, tmp_path).result["provenance"]
    assert facts["git_commit"] == "a" * 40 and facts["git_commit_at_end"] == "b" * 40 and facts["wall_seconds"] >= 0
    monkeypatch.setattr(executors, "provenance", real)
    assert "git_commit_at_end" not in executors.execute(job, tmp_path / "again").result["provenance"]


def test_efficienttrack_in_rounds_is_one_run_with_a_point_per_round_each_validated(refs3, tmp_path, monkeypatch):
    train, test = refs3  # two training references after val_01 is held out: a pass is 118 steps
    study = make_study(SystemSpec(), train, test, budget=2 * 59, preset="tiny", run_config=FAST, validation=1,
                       method_budgets={"efficienttrack-rounds": 5 * 59})  # fmt: skip
    [job] = make_jobs(study, ["efficienttrack-rounds"])
    result = run_study(study, [job], tmp_path, log=lambda line: None)
    folder = tmp_path / "jobs" / "efficienttrack-rounds-closed-s0"
    curve = json.loads((folder / "result.json").read_text())["curve"]
    assert [(p["round"], p["interaction_steps"]) for p in curve] == [(1, 118), (2, 236)]  # 295 steps hold two rounds
    rounds = json.loads((folder / "run" / "metrics.json").read_text())["rounds"]
    assert [p["metrics"]["mae_deg"] for p in curve] == [r["efficienttrack"]["mae_deg"] for r in rounds]
    assert all(p["validation"]["episodes"] == 1 for p in curve) and curve[1]["wall_seconds"] > curve[0]["wall_seconds"]
    assert 0 < curve[0]["gradient_samples"] < curve[1]["gradient_samples"]
    [entry] = result.report.entries
    chosen = min(curve, key=lambda p: p["validation"]["mae_deg"])
    assert entry["selected_interaction_steps"] == chosen["interaction_steps"] and entry["selection_steps"] is None
    assert "| EfficientTrack (rounds) | closed |" in result.report.markdown
    monkeypatch.setattr(methods, "run_pipeline", lambda *args, **kwargs: pytest.fail("a finished round ran again"))
    assert methods.run_efficienttrack_rounds(job, folder) == curve  # each round's point is read back
