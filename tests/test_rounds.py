import csv
import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.training import read_scalars
from efficienttrack.study.methods import rounds_within
from efficienttrack.workflow.config import RunConfig, from_dict, preset
from efficienttrack.workflow.evaluation import evaluate
from efficienttrack.workflow.pipeline import run_pipeline
from efficienttrack.workflow.rounds import round_references, rounds_rows, write_rounds
from toy_system import TOY, TOY_CFG


@pytest.fixture(scope="module")
def refs(toy_refs):
    return toy_refs


@pytest.fixture(scope="module")
def two_rounds(tmp_path_factory, refs, toy_run):
    """A two-round toy run: a copy of the session's one-round run (conftest.py) extended by a second round.

    Seeded, it is what a fresh two-round run gives, wall times aside: round 1 is not trained again (fresh runs of more
    rounds are the ``small_rounds`` fixture's). Tests that run in it copy it.
    """
    out = tmp_path_factory.mktemp("rounds") / "run"
    shutil.copytree(toy_run[0], out)
    return out, run_pipeline(TOY, *refs, out, replace(TOY_CFG, rounds=2), max_plots=0)  # tracking plots: test_pipeline's


@pytest.fixture(scope="module")
def small_rounds(tmp_path_factory, refs):
    """A fresh three-round run, small, with every round setting changed: ``(folder, RunResult, trained_on)``.

    One collection pass and short trainings (nothing here depends on how well it tracks); later rounds train on their
    deployment alone (``round_data: new``), deploy on half the training references each (``round_share``) and ramp their
    learning rates (``round_warmup``; round 1's model ramps over its own ``warmup``). ``trained_on``: the episodes each
    training (model, then policy; round 1, 2, 3) is given.
    """
    trained_on = []

    def counting(train, records_at):
        def wrapper(*args, **kwargs):
            trained_on.append(len(args[records_at]))
            return train(*args, **kwargs)

        return wrapper

    small = replace(TOY_CFG, collect=replace(TOY_CFG.collect, passes=1),
                    model=replace(TOY_CFG.model, steps=40, warmup=0.1), policy=replace(TOY_CFG.policy, steps=40),
                    rounds=3, round_data="new", round_share=0.5, round_warmup=0.25)  # fmt: skip
    out = tmp_path_factory.mktemp("small_rounds")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(dynamics, "train_model", counting(dynamics.train_model, 1))  # (cfg, records, …)
        patch.setattr(policy, "train_policy", counting(policy.train_policy, 2))  # (cfg, g_theta, records, …)
        result = run_pipeline(TOY, *refs, out, small, max_plots=0)
    return out, result, trained_on


def check_round_outputs(out, result, deployments):
    """Assert what a finished run of several rounds reports and writes.

    Args:
        out: the run folder.
        result: its ``RunResult``.
        deployments: the training references that rounds 2, 3, … deployed on, one list a round.
    """
    rounds = result.metrics["rounds"]
    last = len(deployments) + 1
    assert [entry["round"] for entry in rounds] == list(range(1, last + 1))
    for k, deployed in enumerate(deployments, start=2):  # one pass over the round's references, no noise
        assert rounds[k - 1]["interaction_steps"] == rounds[k - 2]["interaction_steps"] + sum(len(r.q) - 1 for r in deployed)
        recorded = sorted(p.stem for p in (out / "rounds" / str(k) / "records" / "deploy").glob("*.npz"))
        assert recorded == sorted(ref.name for ref in deployed), k
    assert result.metrics["interaction_steps"] == rounds[-1]["interaction_steps"]
    assert result.metrics["efficienttrack"] == rounds[-1]["efficienttrack"]
    assert result.metrics["policy"] == str(out / "rounds" / str(last) / "policy.pt")
    assert json.loads((out / "metrics.json").read_text())["rounds"] == rounds
    assert (out / "plots" / "rounds.png").is_file()
    table = list(csv.DictReader((out / "rounds.csv").open()))
    assert [row["method"] for row in table] == ["PD", *(f"Round {k}" for k in range(1, last + 1))]
    assert table[0]["interaction_steps"] == "" and f"| Round {last} |" in (out / "rounds.md").read_text()


@pytest.mark.slow
def test_rounds_add_a_deployment_pass_and_report_every_round(two_rounds, refs, toy_run):
    out, result = two_rounds
    check_round_outputs(out, result, [refs[0]])
    assert result.metrics["rounds"][0]["efficienttrack"] == toy_run[1].metrics["efficienttrack"]  # round 1 as it was


@pytest.mark.slow
def test_evaluate_reads_the_training_interactions_of_a_later_round(two_rounds, refs, tmp_path):
    out, result = two_rounds
    metrics = evaluate(TOY, refs[1], tmp_path / "eval", out / "rounds" / "2" / "policy.pt", device="cpu", max_plots=0)
    assert metrics["interaction_steps"] == result.metrics["rounds"][1]["interaction_steps"]


@pytest.mark.slow
def test_a_later_round_starts_from_the_previous_weights_and_trains_the_warm_budget(two_rounds):
    out, _ = two_rounds
    first = read_scalars(out / "logs" / "model")["train/loss"]
    warm = read_scalars(out / "rounds" / "2" / "logs" / "model")["train/loss"]
    assert warm[1][0] < 0.2 * first[1][0]  # a fresh model starts far off; a warm one near where round 1 ended
    assert len(first[0]) == TOY_CFG.model.steps and len(warm[0]) == round(TOY_CFG.warm_budget * TOY_CFG.model.steps)
    warm_policy = read_scalars(out / "rounds" / "2" / "logs" / "policy")["train/loss"]
    assert len(warm_policy[0]) == round(TOY_CFG.warm_budget * TOY_CFG.policy.steps)


@pytest.mark.slow
def test_rerun_resumes_every_round(two_rounds, refs, tmp_path):
    out, result = tmp_path / "run", two_rounds[1]
    shutil.copytree(two_rounds[0], out)
    again = run_pipeline(TOY, *refs, out, replace(TOY_CFG, rounds=2), max_plots=0)  # plots: the first test's
    assert again.metrics["rounds"] == result.metrics["rounds"]
    assert set(again.skipped) >= {"collect", "model", "policy", "evaluate_efficienttrack"}


@pytest.mark.slow
def test_more_rounds_extend_a_finished_run(two_rounds, toy_run):
    # two_rounds extended the finished one-round toy_run by a round; small_rounds trains a third round on a second
    result = two_rounds[1]
    assert result.metrics["rounds"][:1] == toy_run[1].metrics["rounds"] and result.metrics["rounds"][1]["round"] == 2
    assert set(result.skipped) >= {"collect", "model", "policy", "evaluate_pd", "evaluate_efficienttrack"}


def test_round_data_new_trains_on_the_deployment_pass_only(small_rounds, refs):
    _, result, trained_on = small_rounds
    assert result.metrics["config"]["round_data"] == "new"
    # round 1: the one collection pass; rounds 2 and 3: their deployment on two references, not what came before
    assert trained_on == [len(refs[0])] * 2 + [2] * 4


def test_smaller_rounds_deploy_on_the_next_references_in_turn_and_a_warmup_ramps_their_learning_rates(small_rounds, refs):
    out, result, _ = small_rounds
    train = refs[0]  # four references: a share of a half deploys on two a round, the first two, then the last two
    check_round_outputs(out, result, [train[:2], train[2:]])
    assert "deploying the round-1 policy on 2 of the 4 training references" in (out / "run.log").read_text()
    for part, ramp in (("model", 4), ("policy", 1)):  # round 1 over its section's warmup: the model's 4 steps of 40
        _, first = read_scalars(out / "logs" / part)["train/lr"]
        _, later = read_scalars(out / "rounds" / "2" / "logs" / part)["train/lr"]  # round 2: 20 steps, a ramp of 5
        lr = getattr(TOY_CFG, part).lr
        ramped = lr * 0.5 * (1 + np.cos(np.pi * np.arange(20) / 20)) * np.minimum(1, np.arange(1, 21) / 5)
        assert first[0] == pytest.approx(lr / ramp) and later == pytest.approx(ramped, rel=1e-5)


def test_round_references_move_on_by_a_window_and_the_study_counts_the_rounds_a_budget_holds(refs):
    train = refs[0]
    names = [[ref.name for ref in round_references(train, k, 0.3)] for k in (2, 3, 4)]
    assert names == [[r.name for r in train[:2]], [r.name for r in train[2:]], [r.name for r in train[:2]]]
    assert round_references(train, 5, 1.0) == train and len(round_references(train, 2, 0.01)) == 1
    one_pass = sum(len(ref.q) - 1 for ref in train)
    assert rounds_within(train, 1.0, one_pass - 1) == 0 and rounds_within(train, 1.0, 3 * one_pass) == 3
    first_two = sum(len(ref.q) - 1 for ref in train[:2])
    assert rounds_within(train, 0.5, one_pass + first_two) == 2


def test_round_settings_are_validated():
    with pytest.raises(EfficientTrackError, match=r"rounds must be an integer in \[1, 100\]"):
        RunConfig(rounds=0)
    with pytest.raises(EfficientTrackError, match="cfg.yaml: round_data must be one of all, new"):
        from_dict({"round_data": "old"}, "cfg.yaml")
    with pytest.raises(EfficientTrackError, match=r"round_share must be a finite number in \(0, 1\]"):
        RunConfig(round_share=1.5)
    for budget in (0, -0.5, float("nan"), "half", True):
        with pytest.raises(EfficientTrackError, match="cfg.yaml: warm_budget must be a finite number > 0"):
            from_dict({"warm_budget": budget}, "cfg.yaml")


def test_fastset_is_one_collection_pass_then_three_rounds():
    fastset = preset("fastset")
    assert fastset.collect.passes == 1 and fastset.rounds == 3
    assert fastset.model == preset("cpu").model and fastset.policy == preset("cpu").policy
    assert int(fastset.collect.noisy_episodes(0, 40).sum()) == 33  # the paper's 40 references: 33 noisy and 7 clean at 9:2


def test_rounds_table_rows_and_files(tmp_path):
    pd = {
        "mae_deg": 4.0,
        "rmse_deg": 5.0,
        "fmae_deg": 3.0,
        "smt1_deg": 0.5,
        "smt2_deg": 0.1,
        "etd_mae_cm": 70.0,
        "etd_fmae_cm": 30.0,
    }
    entry = {
        "round": 1,
        "interaction_steps": 72000,
        "interaction_hours": 1.0,
        "efficienttrack": {**pd, "mae_deg": 1.0},
        "model": {"tr_mpe_deg": 0.2, "te_mpe_deg": 0.4},
    }
    rows = rounds_rows(pd, [entry])
    assert rows[0]["interaction_steps"] is None and rows[1]["mae_deg"] == 1.0 and rows[1]["te_mpe_deg"] == 0.4
    csv_path, md_path = write_rounds(rows, tmp_path)
    lines = md_path.read_text().splitlines()
    assert lines[2].startswith("| PD | – | – |") and lines[3].startswith("| Round 1 | 72000 | 1.00 |")
    assert next(csv.DictReader(csv_path.open()))["method"] == "PD"


def test_cli_round_options_name_themselves_in_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["demo", "--out", str(tmp_path / "d"), "--round-data", "old"])
    assert result.exit_code != 0 and "--round-data old: round_data must be one of all, new" in str(result.exception)
    result = runner.invoke(app, ["demo", "--out", str(tmp_path / "d"), "--rounds", "0"])
    assert result.exit_code == 2 and "--rounds" in result.output
    assert not (tmp_path / "d").exists()
