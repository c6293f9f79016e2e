"""Fitting a run into minutes (workflow.time_budget) on the run's ledger (workflow.ledger): the plans, and the time kept."""

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
from efficienttrack.learn.settings import ModelConfig, PolicyConfig
from efficienttrack.learn.training import read_scalars
from efficienttrack.workflow import ledger as ledger_module
from efficienttrack.workflow import pipeline, stages, time_budget
from efficienttrack.workflow.config import RunConfig, from_dict
from efficienttrack.workflow.ledger import Ledger, read_spent
from efficienttrack.workflow.pipeline import run_pipeline
from efficienttrack.workflow.stages import COLLECT, RunLog, evaluation
from efficienttrack.workflow.time_budget import (
    KEPT_FOR_POLICIES,
    LAST_PLAN_MARGIN,
    MAX_MODEL_SCALE,
    MAX_POLICY_SCALE,
    RESERVE,
    Planner,
    StepTimes,
    fit,
    step_seconds,
)
from toy_system import TOY, TOY_CFG, toy_split

CFG = RunConfig(model=ModelConfig(steps=100), policy=PolicyConfig(steps=50), rounds=3, warm_budget=0.5, time_budget=0.5)
TIMES = StepTimes(model=0.1, policy=0.2, windows=1000)  # round 1: 10 s of model and 10 s of policy steps; later: half


def test_the_factor_fits_every_training_left_and_the_rest_of_the_run_into_what_is_left():
    assert fit(30, 4, [(20, 0), (10, 0), (10, 0)], last=False) == pytest.approx((30 * (1 - RESERVE) - 4) / 40)
    # the held-out evaluations of a training do not scale with its steps
    assert fit(80, 4, [(20, 15), (20, 30)], last=False) == pytest.approx((80 * (1 - RESERVE) - 4 - 45) / 40)
    assert fit(30, 0, [(10, 0)], last=True) == pytest.approx(30 * (1 - RESERVE) / (10 * (1 + LAST_PLAN_MARGIN)))


class Clock:
    """A stand-in for the modules' clock that moves only when told to."""

    def __init__(self):
        self.now = 0.0

    def perf_counter(self):
        return self.now


def _run_clock(monkeypatch):
    """One fake clock for the pipeline and the ledger: a run's wall time moves only when a test says so."""
    clock = Clock()
    fake = SimpleNamespace(perf_counter=clock.perf_counter)
    monkeypatch.setattr(ledger_module, "time", fake)
    monkeypatch.setattr(pipeline, "time", fake)
    return clock


def _planning(tmp_path, monkeypatch, minutes=0.5, rounds=3, times=TIMES):
    """A ledger whose collection and PD evaluation are done (in no time), and a planner for CFG over it."""
    clock = _run_clock(monkeypatch)
    ledger = Ledger(tmp_path, clock.perf_counter())
    ledger.once(COLLECT, lambda: {"interaction_steps": 100, "seconds": 0.0})
    ledger.once(evaluation("pd"), lambda: {"seconds": 0.0})
    log = RunLog(tmp_path, Console(file=io.StringIO()))
    return Planner(replace(CFG, rounds=rounds, time_budget=minutes), ledger, log, lambda: times), ledger, clock


def _train(ledger, clock, k, part, seconds):
    """Round k's training ``part`` as the ledger sees it: it takes ``seconds``."""

    def work():
        clock.now += seconds
        return None, {}

    ledger.run(part, work, lambda: None, k)


def test_each_training_is_planned_for_what_is_left_at_the_step_times_the_finished_ones_took(tmp_path, monkeypatch):
    planner, ledger, clock = _planning(tmp_path, monkeypatch)  # 28.5 s of 30 for 40 s of training
    first = planner.scale(1, "model")
    assert first == pytest.approx(30 * (1 - RESERVE) / 40)
    _train(ledger, clock, 1, "model", 10 * first)  # as predicted
    second = planner.scale(1, "policy")  # round 1's policy (10 s) and two half rounds (20 s) in what is left
    assert second == pytest.approx((30 - 10 * first) * (1 - RESERVE) / 30)
    plan = json.loads((tmp_path / "stages" / "time_budget_policy.json").read_text())
    assert plan["slower_than_probed"] == pytest.approx({"model": 1, "policy": 1}) and plan["scale"] == second
    _train(ledger, clock, 1, "policy", 10 * second)
    for k, part, unscaled in ((2, "model", 20), (2, "policy", 15), (3, "model", 10)):
        left = 30 - clock.now
        assert planner.scale(k, part) == pytest.approx(min(1, left * (1 - RESERVE) / unscaled)), (k, part)
        _train(ledger, clock, k, part, 5 * planner.scale(k, part))
    # the last training, 5 s unscaled, keeps its margin free: nothing plans after it
    last = planner.scale(3, "policy")
    assert last == pytest.approx(min(1, (30 - clock.now) * (1 - RESERVE) / (5 * (1 + LAST_PLAN_MARGIN))))
    assert (tmp_path / "rounds" / "3" / "stages" / "time_budget_policy.json").is_file()
    later = {f"rounds/{k}/{part}" for k in (2, 3) for part in ("model", "policy")}
    assert planner.summary()["scales"].keys() == {"model", "policy", *later}


def test_a_training_slower_than_probed_cuts_the_next_ones(tmp_path, monkeypatch):
    planner, ledger, clock = _planning(tmp_path, monkeypatch)
    first = planner.scale(1, "model")
    _train(ledger, clock, 1, "model", 2 * 10 * first)  # the machine got twice as slow after the probes
    second = planner.scale(1, "policy")
    facts = json.loads((tmp_path / "stages" / "time_budget_policy.json").read_text())
    assert facts["slower_than_probed"] == pytest.approx({"model": 2, "policy": 2})  # the policy has not trained yet
    assert second == pytest.approx((30 - 20 * first) * (1 - RESERVE) / (2 * 30)) and second < first


def test_each_network_is_planned_at_its_own_trainings_slowness_once_it_has_trained(tmp_path, monkeypatch):
    planner, ledger, clock = _planning(tmp_path, monkeypatch, minutes=1)  # 57 s for 40 s of training
    _train(ledger, clock, 1, "model", 10 * planner.scale(1, "model"))  # as probed
    _train(ledger, clock, 1, "policy", 1.5 * 10 * planner.scale(1, "policy"))  # the policy's steps ran 1.5 × the probe
    scale = planner.scale(2, "model")  # two models of 5 s as probed, two policies of 5 s × 1.5
    plan = json.loads((tmp_path / "rounds" / "2" / "stages" / "time_budget_model.json").read_text())
    assert plan["slower_than_probed"] == pytest.approx({"model": 1, "policy": 1.5})
    assert scale == pytest.approx(min(1, (60 - clock.now) * (1 - RESERVE) / (2 * 5 + 2 * 5 * 1.5)))
    assert "the model's trainings took 1.00 ×, the policy's 1.50 × the estimate" in (tmp_path / "run.log").read_text()


def test_a_one_round_run_keeps_the_margin_in_its_policy_plan_the_last_one(tmp_path, monkeypatch):
    planner, ledger, clock = _planning(tmp_path, monkeypatch, minutes=0.25, rounds=1)  # 14.25 s for 20 s of training
    _train(ledger, clock, 1, "model", 10 * planner.scale(1, "model"))
    expected = (15 - clock.now) * (1 - RESERVE) / (10 * (1 + LAST_PLAN_MARGIN))
    assert planner.scale(1, "policy") == pytest.approx(expected)


def test_minutes_to_spare_go_to_the_models_first_as_long_as_the_policies_keep_room_for_theirs(tmp_path, monkeypatch):
    planner, ledger, clock = _planning(tmp_path, monkeypatch, minutes=0.8)  # 45.6 s for 40 s of training
    assert planner.scale(1, "model") == 1.0  # more would leave the three policies (20 s) less than 1.5 × their time
    _train(ledger, clock, 1, "model", 10)
    spare = planner.scale(1, "policy")  # the two models left keep their 10 s; the three policies share the rest
    assert spare == pytest.approx((38 * (1 - RESERVE) - 10) / 20) and 1 < spare < MAX_POLICY_SCALE
    _train(ledger, clock, 1, "policy", 10 * spare)
    assert planner.scale(2, "model") == 1.0
    one, ledger, clock = _planning(tmp_path / "one", monkeypatch, minutes=0.6, rounds=1)  # 34.2 s for 20 s of training
    model = one.scale(1, "model")  # what is left after 1.5 × the policy's 10 s
    assert model == pytest.approx((36 * (1 - RESERVE) - KEPT_FOR_POLICIES * 10) / 10) and 1 < model < MAX_MODEL_SCALE
    _train(ledger, clock, 1, "model", 10 * model)
    policy = one.scale(1, "policy")  # the policy takes the rest, its last plan's margin kept
    assert policy == pytest.approx((36 - 10 * model) * (1 - RESERVE) / (10 * (1 + LAST_PLAN_MARGIN))) and policy > 1
    roomy, ledger, clock = _planning(tmp_path / "roomy", monkeypatch, minutes=60)
    assert roomy.scale(1, "model") == MAX_MODEL_SCALE
    _train(ledger, clock, 1, "model", 10 * MAX_MODEL_SCALE)
    assert roomy.scale(1, "policy") == MAX_POLICY_SCALE
    log = (tmp_path / "roomy" / "run.log").read_text()
    assert "round 1's model trains 3.00 × its steps" in log and "round 1's policy trains 1.50 × its steps" in log


def test_a_budget_too_small_to_train_is_refused_and_none_plans_nothing(tmp_path, monkeypatch):
    planner, *_ = _planning(tmp_path, monkeypatch, minutes=0.02)  # 1.2 s for 40 s of training
    with pytest.raises(EfficientTrackError, match=r"--time-budget 0.02 min: less than 5% of the 0.7 min the configured"):
        planner.scale(1, "model")
    unbudgeted = Planner(replace(CFG, time_budget=None), Ledger(tmp_path / "other", 0.0), None, lambda: 1 / 0)
    assert unbudgeted.scale(1, "model") == 1.0 and unbudgeted.summary() is None


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


@pytest.mark.slow
def test_a_run_with_a_budget_trains_the_scaled_steps_plans_each_training_and_keeps_the_factors(tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "measure_step_times", lambda cfg, records, held_out, device: StepTimes(0.3, 1.2, 500))
    # 40 s; round 1's training "takes" 50 × 0.3 + 25 × 1.2 = 45 s, round 2 half of it. The toy's steps are far faster
    # than that, so later trainings are given the minutes to spare (models up to 3 ×, policies 1.5 ×): few steps keep
    # the run short.
    cfg = replace(TOY_CFG, time_budget=40 / 60, rounds=2, collect=replace(TOY_CFG.collect, passes=1),
                  model=replace(TOY_CFG.model, steps=50), policy=replace(TOY_CFG.policy, steps=25))  # fmt: skip
    result = run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)  # no tracking plots: none is checked here
    scales = result.metrics["time_budget"]["scales"]
    assert 0.05 < scales["model"] < 1 and set(scales) == {"model", "policy", "rounds/2/model", "rounds/2/policy"}
    assert len(read_scalars(tmp_path / "logs" / "model")["train/loss"][0]) == round(50 * scales["model"])
    # round 1's policy is planned with how long its model's training took against the 15 s × scale predicted
    model_seconds = json.loads((tmp_path / "stages" / "model.json").read_text())["seconds"]
    policy_plan = json.loads((tmp_path / "stages" / "time_budget_policy.json").read_text())
    ratio = model_seconds / (15 * scales["model"])
    assert policy_plan["slower_than_probed"] == pytest.approx({"model": ratio, "policy": ratio}, rel=1e-3)
    warm = round(25 * scales["rounds/2/policy"] * TOY_CFG.warm_budget)
    assert len(read_scalars(tmp_path / "rounds" / "2" / "logs" / "policy")["train/loss"][0]) == warm
    assert result.metrics["config"]["time_budget"] == cfg.time_budget and result.metrics["config"]["model"]["steps"] == 50

    def measured_again(*args):
        raise AssertionError("a rerun measured the step times again")

    monkeypatch.setattr(pipeline, "measure_step_times", measured_again)
    again = run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    assert {"time_budget", "time_budget_policy", "rounds/2/time_budget_model"} <= set(again.skipped)
    assert again.metrics["time_budget"]["scales"] == scales


def test_the_cli_option_sets_the_budget_and_refuses_a_bad_one(tmp_path):
    for value in ("0", "nan", "-3"):
        result = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--time-budget", value])
        assert isinstance(result.exception, EfficientTrackError), value
        assert "--time-budget" in str(result.exception) and "a finite number > 0" in str(result.exception)


def test_a_config_without_a_budget_serializes_as_before_the_field_existed():
    assert "time_budget" not in TOY_CFG.to_dict()  # folders made before it still match their settings and resume
    assert from_dict(CFG.to_dict(), stored=True) == CFG and from_dict(TOY_CFG.to_dict(), stored=True) == TOY_CFG


TOY_TIMES = StepTimes(300 / TOY_CFG.model.steps, 600 / TOY_CFG.policy.steps, 500)
"""Step times at which TOY_CFG's round 1 trains its model in 300 s and its policy in 600 s."""


def _stage(folder, name):
    return json.loads((folder / "stages" / f"{name}.json").read_text())


def test_a_run_killed_in_its_model_training_and_rerun_ends_within_its_minutes(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    monkeypatch.setattr(pipeline, "measure_step_times", lambda *args: TOY_TIMES)  # 300 + 600 s a round
    cfg = replace(TOY_CFG, time_budget=2, rounds=1)  # 120 s; collection and PD take no time on this clock
    train_model = dynamics.train_model

    def killed(*args, **kwargs):
        clock.now += 30  # 30 s into the model's training, the run is killed
        raise KeyboardInterrupt

    monkeypatch.setattr(dynamics, "train_model", killed)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    first = _stage(tmp_path, "time_budget_model")
    assert first["scale"] == pytest.approx(120 * (1 - RESERVE) / 900)  # the model's training: 38 s of steps
    assert read_spent(tmp_path / "stages" / "time_spent.json")[0] == pytest.approx(30)

    def resumed(*args, **kwargs):  # the rerun trains the rest: 8 s, so the training took the 38 s planned
        clock.now += 8
        return train_model(*args, **kwargs)

    def policy_training(policy_cfg, *args, **kwargs):  # takes its steps at the probes' step time, then the test ends
        clock.now += policy_cfg.steps * TOY_TIMES.policy
        raise KeyboardInterrupt

    def measured_again(*args):
        raise AssertionError("the rerun measured the step times again")

    monkeypatch.setattr(dynamics, "train_model", resumed)
    monkeypatch.setattr(policy, "train_policy", policy_training)
    monkeypatch.setattr(pipeline, "measure_step_times", measured_again)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    assert _stage(tmp_path, "time_budget_model") == first  # the model's plan is kept: it trained those steps
    assert _stage(tmp_path, "model")["seconds"] == pytest.approx(38)  # 30 s before the kill and 8 s after it
    plan = _stage(tmp_path, "time_budget_policy")
    assert plan["slower_than_probed"] == pytest.approx({"model": 1, "policy": 1})
    assert plan["seconds_left"] == pytest.approx(120 - 38)
    assert plan["scale"] == pytest.approx((120 - 38) * (1 - RESERVE) / (600 * (1 + LAST_PLAN_MARGIN)))
    assert clock.now <= 120  # both invocations together: the run ends within its 2 minutes


def test_a_rerun_plans_with_what_the_collection_and_the_evaluation_took_before_the_kill(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    monkeypatch.setattr(pipeline, "measure_step_times", lambda *args: TOY_TIMES)
    cfg = replace(TOY_CFG, time_budget=3, rounds=2)  # 180 s
    collect, track_and_save, kills = pipeline.collect, stages.track_and_save, [KeyboardInterrupt]

    def collecting(*args, **kwargs):  # 6 passes of 5 s; the rerun finds them recorded
        if not (tmp_path / "stages" / "collect.json").exists():
            clock.now += 30
        return collect(*args, **kwargs)

    def evaluating(*args, **kwargs):  # 4 s into the PD evaluation the run is killed; the rerun takes 4 s more
        clock.now += 4
        if kills:
            raise kills.pop()
        return track_and_save(*args, **kwargs)

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "collect", collecting)
    monkeypatch.setattr(stages, "track_and_save", evaluating)
    monkeypatch.setattr(dynamics, "train_model", stop)  # the test ends after the model's plan
    for _ in range(2):
        with pytest.raises(KeyboardInterrupt):
            run_pipeline(TOY, *toy_split(), tmp_path, cfg, max_plots=0)
    assert _stage(tmp_path, "evaluate_pd")["seconds"] == pytest.approx(8)
    plan = _stage(tmp_path, "time_budget_model")
    # planned at 38 s: two evaluations of 8 s and a deployment pass of 5 s to come; 900 + 450 s of training
    assert plan["other_seconds"] == pytest.approx(2 * 8 + 5)
    assert plan["scale"] == pytest.approx(((180 - 38) * (1 - RESERVE) - 21) / 1350)


def test_a_killed_run_loses_at_most_a_heartbeat_of_its_time(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    monkeypatch.setattr(ledger_module, "HEARTBEAT", 0.005)
    path = tmp_path / "stages" / "time_spent.json"
    with Ledger(tmp_path, clock.perf_counter()).counting():
        assert read_spent(path) == (0.0, 1, False, {})  # written as it starts
        clock.now = 42.0
        deadline = time.monotonic() + 5
        while read_spent(path)[0] != 42.0:  # the heartbeat writes it, with nothing else happening in the run
            assert time.monotonic() < deadline, "no heartbeat"
            time.sleep(0.002)
        rerun = Ledger(tmp_path, clock.perf_counter())  # as after a SIGKILL here: nothing more is written before the rerun
        assert rerun.seconds_spent() == 42.0 and rerun.invocation == 2
        clock.now = 50.0
        assert rerun.seconds_spent() == 50.0


def test_a_stage_that_a_kill_split_took_the_runs_time_from_its_start_else_what_it_measured(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    first = Ledger(tmp_path, clock.perf_counter())
    with pytest.raises(KeyboardInterrupt), first.counting():
        _train(first, clock, 1, "collect", 9.5)
        assert first.facts["collect"]["seconds"] == 9.5  # within one invocation: what it measured
        clock.now = 10.0

        def killed():
            clock.now = 40.0  # killed 30 s into the training (Ctrl-C: the time is written on the way out)
            raise KeyboardInterrupt

        first.run("model", killed, lambda: None)
    second = Ledger(tmp_path, clock.perf_counter())
    with second.counting():
        clock.now = 41.0  # the restart
        _train(second, clock, 1, "collect", 100.0)  # found done: kept as it was, not done again
        assert second.facts["collect"]["seconds"] == 9.5 and second.skipped == ["collect"]
        _train(second, clock, 1, "model", 20.0)  # the resumed training takes 20 s more
        assert second.facts["model"]["seconds"] == pytest.approx(40 + 1 + 20 - 10)
    assert read_spent(tmp_path / "stages" / "time_spent.json") == (61.0, 2, True, {})


def test_a_rerun_that_adds_rounds_to_a_finished_run_counts_its_own_minutes(tmp_path, monkeypatch):
    clock = _run_clock(monkeypatch)
    with Ledger(tmp_path, clock.perf_counter()).counting():
        clock.now = 500.0
    assert Ledger(tmp_path, clock.perf_counter()).seconds_spent() == 0.0


def test_an_unreadable_record_of_the_time_spent_is_refused_naming_it(tmp_path, monkeypatch):
    path = tmp_path / "stages" / "time_spent.json"
    path.parent.mkdir()
    for text in ("{", '{"spent_seconds": -1, "invocations": 1, "finished": false, "work": {}}', "[]"):
        path.write_text(text)
        with pytest.raises(EfficientTrackError, match=r"time_spent.json: the ledger's record .* --force$"):
            Ledger(tmp_path, 0.0)
