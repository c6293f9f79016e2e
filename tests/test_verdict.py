"""A policy worse than PD alone is called so: in metrics.json, in the run's log, and again when it is deployed."""

import json

import pytest

from efficienttrack.deploy.deployment import recorded_verdict
from efficienttrack.workflow.evaluation import worse_than_pd
from test_loop import deploy_inputs, invoke  # noqa: F401  (the fixture)


def test_worse_than_pd_compares_the_test_mae():
    assert worse_than_pd({"mae_deg": 4.83}, None) is None
    assert worse_than_pd({"mae_deg": 4.83}, {"mae_deg": 4.83}) is None
    assert worse_than_pd({"mae_deg": 4.83}, {"mae_deg": 1.2}) is None
    warning = worse_than_pd({"mae_deg": 4.83}, {"mae_deg": 5.77})
    assert warning is not None and "(5.77° against 4.83° MAE on the test references): do not deploy it" in warning


@pytest.mark.parametrize("inside", ["policy.pt", "rounds/2/policy.pt"])
def test_the_run_that_tested_a_policy_gives_its_verdict(inside, tmp_path, monkeypatch):
    run = tmp_path / "runs" / "tiny"
    (run / inside).parent.mkdir(parents=True, exist_ok=True)
    (run / inside).write_bytes(b"")
    monkeypatch.chdir(tmp_path)  # the run wrote the policy's path as given, relative to where it ran
    (run / "metrics.json").write_text(json.dumps({"policy": f"runs/tiny/{inside}", "worse_than_pd": "worse"}))
    assert recorded_verdict(run / inside) == "worse"
    (run / "metrics.json").write_text(json.dumps({"policy": f"runs/tiny/{inside}", "worse_than_pd": None}))
    assert recorded_verdict(run / inside) is None
    (run / "metrics.json").write_text(json.dumps({"policy": "runs/other/policy.pt", "worse_than_pd": "worse"}))
    assert recorded_verdict(run / inside) is None  # another policy's verdict
    (run / "metrics.json").write_text("{broken")
    assert recorded_verdict(run / inside) is None and recorded_verdict(None) is None


def test_deploy_arms_a_policy_worse_than_pd_only_when_told_and_warns_in_shadow(deploy_inputs, tmp_path):  # noqa: F811
    refs, policy = deploy_inputs
    (policy.parent / "metrics.json").write_text(json.dumps({"policy": str(policy), "worse_than_pd": "it tracks worse"}))
    args = ("deploy", "--refs", refs, "--policy", policy, "--fast", "--arm")
    refused = invoke(*args, "--out", tmp_path / "armed")
    assert "it tracks worse; its recorded evaluation tracked worse than PD" in str(refused.exception)
    assert not (tmp_path / "armed").exists()
    for extra in ("--shadow", "--accept-worse"):
        result = invoke(*args, "--out", tmp_path / extra, extra)
        assert result.exit_code == 0, result.output
        assert f"warning: {policy}: it tracks worse" in result.stderr


def test_the_verdict_travels_with_the_policy_into_copies_and_exports(deploy_inputs, tmp_path):  # noqa: F811
    refs, policy = deploy_inputs
    evaluated = invoke("evaluate", "--refs", refs, "--policy", policy, "--out", tmp_path / "eval", "--plots", "0")
    assert evaluated.exit_code == 0, evaluated.output
    evaluation = json.loads(policy.with_suffix(".json").read_text())["evaluation"]
    assert evaluation["mae_deg"] > evaluation["pd_mae_deg"] and "do not deploy it" in evaluation["worse_than_pd"]
    assert evaluation["references"] == ["ref_01", "ref_02"]
    (tmp_path / "eval" / "metrics.json").unlink()  # the run folder that measured it is gone
    copy = tmp_path / "elsewhere" / "mine.pt"
    copy.parent.mkdir()
    copy.write_bytes(policy.read_bytes())
    copy.with_suffix(".json").write_text(policy.with_suffix(".json").read_text())
    assert invoke("export", "--policy", copy, "--out", tmp_path / "export").exit_code == 0
    for deployed in (policy, copy, tmp_path / "export"):
        assert recorded_verdict(deployed) == evaluation["worse_than_pd"]
        refused = invoke("deploy", "--refs", refs, "--policy", deployed, "--fast", "--arm", "--out", tmp_path / "armed")
        assert "its recorded evaluation tracked worse than PD" in str(refused.exception), refused.output
    assert not (tmp_path / "armed").exists()


def test_a_policy_config_that_cannot_be_written_is_a_warning_after_the_evaluation(deploy_inputs, tmp_path, monkeypatch):  # noqa: F811
    from efficienttrack.core.errors import EfficientTrackError
    from efficienttrack.workflow import evaluation as evaluation_module

    def refuse(path, evaluation):
        raise EfficientTrackError(f"{path}: read-only")

    monkeypatch.setattr(evaluation_module, "record_evaluation", refuse)
    refs, policy = deploy_inputs
    result = invoke("evaluate", "--refs", refs, "--policy", policy, "--out", tmp_path / "eval", "--plots", "0")
    assert result.exit_code == 0, result.output
    assert "warning: the verdict is not kept with the policy" in result.output
    assert json.loads((tmp_path / "eval" / "metrics.json").read_text())["worse_than_pd"] is not None


def test_an_unproven_policy_is_armed_only_after_a_passing_shadow_run_or_with_accept_worse(deploy_inputs, tmp_path):  # noqa: F811
    refs, policy = deploy_inputs  # a policy as train-policy writes it: never evaluated
    armed = ("deploy", "--refs", refs, "--policy", policy, "--fast", "--arm")
    refused = invoke(*armed, "--out", tmp_path / "armed")
    assert "unproven: no evaluation and no shadow deployment of it is recorded" in str(refused.exception)
    assert not (tmp_path / "armed").exists()
    accepted = invoke(*armed, "--out", tmp_path / "accepted", "--accept-worse")
    assert accepted.exit_code == 0 and "unproven (never evaluated" in accepted.output
    shadow = invoke(*armed, "--out", tmp_path / "shadow", "--shadow")
    assert shadow.exit_code == 0, shadow.output
    record = json.loads(policy.with_suffix(".json").read_text())["shadow"]
    assert record["runs"] == 2 and record["deployment"] == str((tmp_path / "shadow").resolve())
    assert invoke(*armed, "--out", tmp_path / "armed").exit_code == 0  # a passing shadow run proves it enough to arm
