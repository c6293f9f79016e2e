"""Fitting a run into minutes (workflow.time_budget): the factor's arithmetic, and a run that trains fewer steps."""

import io
import json
import time
from dataclasses import replace
from types import SimpleNamespace

import pytest
from rich.console import Console
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.dynamics import ModelConfig
from efficienttrack.learn.policy import PolicyConfig
from efficienttrack.learn.training import read_scalars
from efficienttrack.workflow import pipeline, time_budget
from efficienttrack.workflow.config import RunConfig, from_dict
from efficienttrack.workflow.pipeline import run_pipeline
from efficienttrack.workflow.stages import RunLog, Stages
from efficienttrack.workflow.time_budget import (
    LAST_PLAN_MARGIN,
    RESERVE,
    StepTimes,
    TimeBudget,
    budget_scale,
    read_spent,
    step_seconds,
)
from toy_system import TOY, TOY_CFG, toy_split

CFG = RunConfig(model=ModelConfig(steps=100), policy=PolicyConfig(steps=50), rounds=3, warm_budget=0.5, time_budget=10)
TIMES = StepTimes(model=0.1, policy=0.2, windows=1000)


def test_the_factor_fits_every_rounds_training_into_what_is_left():
    # round 1: 100 × 0.1 + 50 × 0.2 = 20 s; rounds 2 and 3 half of it each: 40 s in all
    scale, training = budget_scale(CFG, TIMES, seconds_left=30, other_seconds=4)
    assert training == pytest.approx(40) and scale == pytest.approx((30 * (1 - RESERVE) - 4) / 40)
    assert budget_scale(CFG, TIMES, seconds_left=3600, other_seconds=4)[0] == 1.0  # never more steps than configured
    epochs = replace(CFG, model=ModelConfig(steps=None, epochs=2, batch_size=100))  # 2 passes over 1000 windows: 20 steps
    assert budget_scale(epochs, TIMES, seconds_left=3600, other_seconds=0)[1] == pytest.approx((20 * 0.1 + 50 * 0.2) * 2)


def test_a_budget_too_small_to_train_is_refused():
    with pytest.raises(EfficientTrackError, match=r"--time-budget 10 min: 0.0 min would be left for training"):
        budget_scale(CFG, TIMES, seconds_left=5, other_seconds=4)


def test_step_seconds_and_evaluation_seconds_come_from_short_trainings_after_a_warm_up():
    class Result:
        def __init__(self, seconds):
            self.seconds = seconds

    calls = []

    def train(cfg):
        calls.append((cfg.steps, cfg.eval_every))
        evaluations = cfg.steps // cfg.eval_every
        return Result(3.0 + 0.25 * cfg.steps + 0.5 * evaluations + (5.0 if len(calls) == 1 else 0.0))  # a slow first call

    per_step, per_evaluation, longest = step_seconds(train, ModelConfig(steps=None, epochs=5))
    assert per_step == pytest.approx(0.25) and per_evaluation == pytest.approx(0.5)
    warm_up, short, long = time_budget.PROBE_STEPS
    assert calls == [(warm_up, warm_up), (short, short), (long, long), (short, short // 2)] and longest.seconds == 9.5


def test_the_evaluations_count_once_per_training_whatever_its_steps():
    times = TIMES._replace(model_evaluation=0.5, policy_evaluation=1.0)  # 10 of each per training: 15 s a round
    scale, training = budget_scale(CFG, times, seconds_left=80, other_seconds=4)
    assert training == pytest.approx(40 + 3 * 15) and scale == pytest.approx((80 * (1 - RESERVE) - 4 - 45) / 40)


class Clock:
    """A stand-in for the module's clock that moves only when told to."""

    def __init__(self):
        self.now = 0.0

    def perf_counter(self):
        return self.now


def _planned(tmp_path, monkeypatch, minutes, rounds=3):
    """A budget for CFG with TIMES as the probes' step times on a clock of its own, its round 1 planned."""
    clock = Clock()
    monkeypatch.setattr(time_budget, "time", SimpleNamespace(perf_counter=clock.perf_counter))
    monkeypatch.setattr(time_budget, "measure_step_times", lambda cfg, records, held_out, device: TIMES)
    log = RunLog(tmp_path, Console(file=io.StringIO()))
    budget = TimeBudget(replace(CFG, rounds=rounds, time_budget=minutes), Stages(tmp_path), log, clock.perf_counter())
    budget.first_round([], [], None, pass_seconds=0.0, evaluation_seconds=0.0)
    return budget, clock


def test_trainings_that_take_what_the_probes_said_are_planned_again_at_the_probes_step_times(tmp_path, monkeypatch):
    budget, clock = _planned(tmp_path, monkeypatch, minutes=0.5)  # 28.5 s of 30 for 40 s of training
    first = budget.scales[0]
    assert first == pytest.approx(30 * (1 - RESERVE) / 40)
    model_seconds = 100 * 0.1 * first  # as predicted; the clock moves on by that much
    clock.now += model_seconds
    assert budget.first_policy(model_seconds).policy.steps == round(50 * budget.policy_scale)
    plan = json.loads((tmp_path / "stages" / "time_budget_policy.json").read_text())
    # what is left, less its reserve, over round 1's policy (10 s) and two half rounds (20 s), unscaled
    assert plan["slower_than_probed"] == pytest.approx(1)
    assert budget.policy_scale == pytest.approx((30 - model_seconds) * (1 - RESERVE) / 30)
    policy_seconds = 50 * 0.2 * budget.policy_scale
    clock.now += policy_seconds
    budget.later_round(2, model_seconds + policy_seconds)
    second = json.loads((tmp_path / "stages" / "time_budget_round_2.json").read_text())
    assert second["slower_than_probed"] == pytest.approx(1)
    assert budget.scales[1] == pytest.approx((30 - model_seconds - policy_seconds) * (1 - RESERVE) / 20)
    second_seconds = 0.5 * 20 * budget.scales[1]
    clock.now += second_seconds
    budget.later_round(3, model_seconds + policy_seconds + second_seconds)
    # the last round, 10 s unscaled, keeps its margin free: nothing plans after it
    left = 30 - model_seconds - policy_seconds - second_seconds
    assert budget.scales[2] == pytest.approx(left * (1 - RESERVE) / (10 * (1 + LAST_PLAN_MARGIN)))


def test_a_one_round_run_keeps_the_margin_in_its_policy_plan_the_last_one(tmp_path, monkeypatch):
    budget, clock = _planned(tmp_path, monkeypatch, minutes=0.25, rounds=1)  # 14.25 s for 20 s of training
    model_seconds = 100 * 0.1 * budget.scales[0]
    clock.now += model_seconds
    budget.first_policy(model_seconds)
    assert budget.policy_scale == pytest.approx((15 - model_seconds) * (1 - RESERVE) / (10 * (1 + LAST_PLAN_MARGIN)))


def test_a_model_training_slower_than_probed_cuts_round_one_policy_and_counts_in_the_next_plan(tmp_path, monkeypatch):
    budget, clock = _planned(tmp_path, monkeypatch, minutes=0.5)
    first = budget.scales[0]
    model_seconds = 2 * 100 * 0.1 * first  # the machine got twice as slow after the probes
    clock.now += model_seconds
    cfg = budget.first_policy(model_seconds)
    facts = json.loads((tmp_path / "stages" / "time_budget_policy.json").read_text())
    assert facts["slower_than_probed"] == pytest.approx(2)
    # what is left, less its reserve, over round 1's policy and two half rounds, all at twice the probes' step times
    assert facts["seconds_for_training"] == pytest.approx((30 - model_seconds) * (1 - RESERVE))
    assert budget.policy_scale == pytest.approx(facts["seconds_for_training"] / (2 * (50 * 0.2 + 2 * 0.5 * 20)))
    assert budget.policy_scale < first and cfg.policy.steps == round(50 * budget.policy_scale)
    policy_seconds = 2 * 50 * 0.2 * budget.policy_scale
    clock.now += policy_seconds
    budget.later_round(2, model_seconds + policy_seconds)
    second = json.loads((tmp_path / "stages" / "time_budget_round_2.json").read_text())
    assert second["slower_than_probed"] == pytest.approx(2)
    assert budget.summary()["round_1_policy_scale"] == budget.policy_scale


@pytest.mark.slow
def test_a_run_with_a_budget_trains_the_scaled_steps_plans_each_round_and_keeps_the_factors(tmp_path, monkeypatch):
    monkeypatch.setattr(time_budget, "measure_step_times", lambda cfg, records, held_out, device: StepTimes(0.05, 0.1, 500))
    # 40 s; round 1's training "takes" 300 × 0.05 + 300 × 0.1 = 45 s, round 2 half of it
    cfg = replace(TOY_CFG, time_budget=40 / 60, rounds=2)
    result = run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)  # no tracking plots: none is checked here
    first = json.loads((tmp_path / "stages" / "time_budget.json").read_text())
    policy_plan = json.loads((tmp_path / "stages" / "time_budget_policy.json").read_text())
    second = json.loads((tmp_path / "stages" / "time_budget_round_2.json").read_text())
    assert 0.05 < first["scale"] < 1 and first["unscaled_training_seconds"] == pytest.approx(45 * 1.5)
    steps = round(TOY_CFG.model.steps * first["scale"])
    assert len(read_scalars(tmp_path / "logs" / "model")["train/loss"][0]) == steps
    # round 1's policy is planned with how long its model's training really took against the 15 s × scale predicted
    model_seconds = json.loads((tmp_path / "stages" / "model.json").read_text())["seconds"]
    assert policy_plan["slower_than_probed"] == pytest.approx(model_seconds / (15 * first["scale"]), rel=1e-3)
    policy_steps = round(TOY_CFG.policy.steps * policy_plan["scale"]) if policy_plan["scale"] < 1 else 300
    assert len(read_scalars(tmp_path / "logs" / "policy")["train/loss"][0]) == policy_steps
    # round 2 is planned with how long round 1's trainings really took against what the probes predicted for them
    trained = result.metrics["rounds"][0]["train_seconds"]
    predicted = 15 * first["scale"] + 30 * policy_plan["scale"]
    assert second["slower_than_probed"] == pytest.approx(trained / predicted, rel=1e-3)
    assert 0.05 <= second["scale"] <= 1
    warm = round(round(TOY_CFG.policy.steps * second["scale"]) * TOY_CFG.warm_budget) if second["scale"] < 1 else 150
    assert len(read_scalars(tmp_path / "rounds" / "2" / "logs" / "policy")["train/loss"][0]) == warm
    assert result.metrics["time_budget"]["scales"] == [first["scale"], second["scale"]]
    assert result.metrics["time_budget"]["round_1_policy_scale"] == policy_plan["scale"]
    assert result.metrics["config"]["time_budget"] == cfg.time_budget and result.metrics["config"]["model"]["steps"] == 300

    def measured_again(*args):
        raise AssertionError("a rerun measured the step times again")

    monkeypatch.setattr(time_budget, "measure_step_times", measured_again)
    again = run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    assert {"time_budget", "time_budget_policy", "time_budget_round_2"} <= set(again.skipped)
    assert again.metrics["time_budget"]["scales"] == result.metrics["time_budget"]["scales"]


def test_the_cli_option_sets_the_budget_and_refuses_a_bad_one(tmp_path):
    for value in ("0", "nan", "-3"):
        result = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--time-budget", value])
        assert isinstance(result.exception, EfficientTrackError), value
        assert "--time-budget" in str(result.exception) and "a finite number > 0" in str(result.exception)


def test_a_config_without_a_budget_serializes_as_before_the_field_existed():
    assert "time_budget" not in TOY_CFG.to_dict()  # folders made before it still match their settings and resume
    assert from_dict(CFG.to_dict()) == CFG and from_dict(TOY_CFG.to_dict()) == TOY_CFG


def _run_clock(monkeypatch):
    """One fake clock for the pipeline and the budget: a run's wall time moves only when a test says so."""
    clock = Clock()
    fake = SimpleNamespace(perf_counter=clock.perf_counter)
    monkeypatch.setattr(time_budget, "time", fake)
    monkeypatch.setattr(pipeline, "time", fake)
    return clock


def _stage(folder, name):
    return json.loads((folder / "stages" / f"{name}.json").read_text())


def test_a_run_killed_in_its_model_training_and_rerun_ends_within_its_minutes(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    monkeypatch.setattr(time_budget, "measure_step_times", lambda *args: StepTimes(1.0, 2.0, 500))  # 300 + 600 s a round
    cfg = replace(TOY_CFG, time_budget=2, rounds=1)  # 120 s; collection and PD take no time on this clock
    train_model = dynamics.train_model

    def killed(*args, **kwargs):
        clock.now += 30  # 30 s into the model's training, the run is killed
        raise KeyboardInterrupt

    monkeypatch.setattr(dynamics, "train_model", killed)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    first = _stage(tmp_path, "time_budget")
    assert first["scale"] == pytest.approx(120 * (1 - RESERVE) / 900)  # the model's training: 38 s of steps
    assert read_spent(tmp_path / "stages" / "time_budget_spent.json")[0] == pytest.approx(30)

    def resumed(*args, **kwargs):  # the rerun trains the rest: 8 s, so the training took the 38 s planned
        clock.now += 8
        return train_model(*args, **kwargs)

    def policy_training(policy_cfg, *args, **kwargs):  # takes its steps at the probes' step time, then the test ends
        clock.now += policy_cfg.steps * 2.0
        raise KeyboardInterrupt

    def measured_again(*args):
        raise AssertionError("the rerun measured the step times again")

    monkeypatch.setattr(dynamics, "train_model", resumed)
    monkeypatch.setattr(policy, "train_policy", policy_training)
    monkeypatch.setattr(time_budget, "measure_step_times", measured_again)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    assert _stage(tmp_path, "time_budget") == first  # round 1's plan is kept: its model trained those steps
    plan = _stage(tmp_path, "time_budget_policy")
    # the model's training took 30 s before the kill and 8 s after it, as planned; 120 − 38 s are left, not 120 − 8
    assert plan["slower_than_probed"] == pytest.approx(1)
    assert plan["seconds_for_training"] == pytest.approx((120 - 38) * (1 - RESERVE))
    assert plan["scale"] == pytest.approx(plan["seconds_for_training"] / (600 * (1 + LAST_PLAN_MARGIN)))
    assert clock.now <= 120  # both invocations together: the run ends within its 2 minutes


def test_a_rerun_plans_with_what_the_collection_and_the_evaluation_took_before_the_kill(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    monkeypatch.setattr(time_budget, "measure_step_times", lambda *args: StepTimes(1.0, 2.0, 500))
    cfg = replace(TOY_CFG, time_budget=3, rounds=2)  # 180 s
    collect, evaluate_stage, kills = pipeline.collect, pipeline.evaluate_stage, [KeyboardInterrupt]

    def collecting(*args, **kwargs):  # 6 passes of 5 s; the rerun finds them recorded
        if not (tmp_path / "stages" / "collect.json").exists():
            clock.now += 30
        return collect(*args, **kwargs)

    def evaluating(stages, name, *args, **kwargs):  # 4 s into the PD evaluation the run is killed; the rerun takes 4 s more
        clock.now += 4
        if kills:
            raise kills.pop()
        return evaluate_stage(stages, name, *args, **kwargs)

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "collect", collecting)
    monkeypatch.setattr(pipeline, "evaluate_stage", evaluating)
    monkeypatch.setattr(dynamics, "train_model", stop)  # the test ends after round 1's plan
    for _ in range(2):
        with pytest.raises(KeyboardInterrupt):
            run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    plan = _stage(tmp_path, "time_budget")
    # planned at 38 s: two evaluations of 8 s (4 s before the kill, 4 s after) and a deployment pass of 5 s to come
    assert plan["other_seconds"] == pytest.approx(2 * 8 + 5)
    assert plan["scale"] == pytest.approx(((180 - 38) * (1 - RESERVE) - 21) / plan["unscaled_training_seconds"])


def _budget(folder, clock, cfg=CFG):
    return TimeBudget(cfg, Stages(folder), RunLog(folder, Console(file=io.StringIO())), clock.perf_counter())


def test_a_killed_run_loses_at_most_a_heartbeat_of_its_time(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    monkeypatch.setattr(time_budget, "HEARTBEAT", 0.005)
    path = tmp_path / "stages" / "time_budget_spent.json"
    with _budget(tmp_path, clock).counting():
        assert read_spent(path) == (0.0, 1, False, {})  # written as it starts
        clock.now = 42.0
        deadline = time.monotonic() + 5
        while read_spent(path)[0] != 42.0:  # the heartbeat writes it, with nothing else happening in the run
            assert time.monotonic() < deadline, "no heartbeat"
            time.sleep(0.002)
        rerun = _budget(tmp_path, clock)  # as after a SIGKILL here: nothing more is written before the rerun
        assert rerun.seconds_spent() == 42.0 and rerun.invocation == 2
        clock.now = 50.0
        assert rerun.seconds_spent() == 50.0


def test_work_that_a_kill_split_took_the_runs_time_from_its_start_else_what_was_measured(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    first = _budget(tmp_path, clock)
    with pytest.raises(KeyboardInterrupt), first.counting():
        first.begin("collect")
        clock.now = 10.0
        assert first.took("collect", 9.5) == 9.5  # within one invocation: what the caller measured
        first.begin("round_1_model")
        clock.now = 40.0  # killed 30 s into the training (Ctrl-C: the time is written on the way out)
        raise KeyboardInterrupt
    second = _budget(tmp_path, clock)
    with second.counting():
        clock.now = 41.0  # the restart
        second.begin("collect")  # found done: kept as it was
        second.begin("round_1_model")
        assert second.took("collect", 0.0) == 9.5
        clock.now = 61.0  # the resumed training reports its own 20 s
        assert second.took("round_1_model", 20.0) == pytest.approx(40 + 1 + 20 - 10)
        assert second.took("round_1_policy", 3.0) == 3.0  # never begun (a folder older than the record): as measured
    assert read_spent(tmp_path / "stages" / "time_budget_spent.json")[:3] == (61.0, 2, False)
    assert _budget(tmp_path, clock).took("round_1_model", 1.0) == pytest.approx(51)  # kept for a later rerun


def test_a_rerun_that_adds_rounds_to_a_finished_run_counts_its_own_minutes(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    budget = _budget(tmp_path, clock)
    with budget.counting():
        clock.now = 500.0
        budget.finish()
    assert budget.summary()["seconds_spent"] == 500.0
    assert _budget(tmp_path, clock).seconds_spent() == 0.0


def test_an_unreadable_record_of_the_time_spent_is_refused_naming_it(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    path = tmp_path / "stages" / "time_budget_spent.json"
    path.parent.mkdir()
    for text in ("{", '{"spent_seconds": -1, "invocations": 1, "finished": false, "work": {}}', "[]"):
        path.write_text(text)
        with pytest.raises(EfficientTrackError, match=r"time_budget_spent.json: the time budget's record .* --force$"):
            _budget(tmp_path, clock)
