import json
import shutil
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from efficienttrack import __version__, cli
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.provenance import PROVENANCE_KEYS
from efficienttrack.data.metrics import METRIC_KEYS
from efficienttrack.data.references import Reference, save_references
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.training import read_scalars
from efficienttrack.workflow.config import PRESETS, RunConfig, from_dict, load_config
from efficienttrack.workflow.evaluation import evaluate
from efficienttrack.workflow.pipeline import run_pipeline
from toy_system import TOY, TOY_CFG


@pytest.fixture(scope="module")
def refs(toy_refs):
    return toy_refs


@pytest.fixture(scope="module")
def finished_run(toy_run):
    """The session's finished toy run (conftest.py): ``(folder, result)``; a test that runs in the folder copies it."""
    return toy_run


def cli_main(monkeypatch, capsys, *args):
    """Run the ``efficienttrack`` entry point in-process; returns (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["efficienttrack", *map(str, args)])
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = exc.code or 0
    out, err = capsys.readouterr()
    return code, out, err


RESULT_KEYS = {
    "gradient_samples",
    "pd",
    "efficienttrack",
    "interaction_steps",
    "interaction_hours",
    "train_seconds",
    "model",
    "fallbacks",
    "fallback_share",
    "worse_than_pd",
    "warning",
    "references",
    "policy",
    "system",
    "config",
    "rounds",
    "time_budget",
    "provenance",
}
"""Top-level keys of metrics.json, the same for run and evaluate."""


@pytest.mark.slow
def test_run_writes_everything_and_beats_pd(finished_run):
    out, result = finished_run
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == json.loads(json.dumps(result.metrics))
    assert set(metrics) == RESULT_KEYS
    assert set(metrics["pd"]) == set(METRIC_KEYS) and set(metrics["efficienttrack"]) == set(METRIC_KEYS)
    assert set(metrics["model"]) == {"tr_mpe_deg", "te_mpe_deg"}
    assert metrics["interaction_steps"] == 6 * (79 + 69 + 89 + 74)
    assert metrics["interaction_hours"] == pytest.approx(metrics["interaction_steps"] / 20 / 3600, abs=1e-4)
    model, policy_cfg = TOY_CFG.model, TOY_CFG.policy
    assert metrics["gradient_samples"] == model.steps * model.batch_size + policy_cfg.steps * policy_cfg.batch_size
    assert metrics["rounds"][0]["gradient_samples"] == metrics["gradient_samples"]
    assert metrics["references"] == ["ref_04", "ref_05"]
    assert metrics["config"] == TOY_CFG.to_dict()
    assert metrics["provenance"]["device"] == "cpu" and metrics["provenance"]["wall_seconds"] > 0
    for name in ("metrics.json", "config.json", "run.json", "model.json", "policy.json"):
        facts = json.loads((out / name).read_text())["provenance"]
        assert tuple(facts) == PROVENANCE_KEYS, name
        assert facts["version"] == __version__ and facts["torch"] == torch.__version__
    assert load_config(out / "config.json") == TOY_CFG  # the provenance is a record, not a setting
    log = (out / "run.log").read_text()
    assert log.startswith("=== ") and " run (commit " in log.splitlines()[0]
    assert "collected 24 episodes" in log and "EfficientTrack" in log and "1866" in log
    # the toy lag closes 40 % of the error per step; the learned adjustment (exact answer known) must remove most of it
    assert metrics["pd"]["mae_deg"] == pytest.approx(1.69, abs=0.01)
    assert metrics["efficienttrack"]["mae_deg"] < 0.5 * metrics["pd"]["mae_deg"]
    for path in ("model.pt", "model.json", "policy.pt", "policy.json", "config.json", "run.json"):
        assert (out / path).is_file(), path
    prints = [json.loads((out / name).read_text())["training_fingerprint"] for name in ("model.json", "policy.json")]
    assert all(len(p) == 64 for p in prints) and prints[0] != prints[1]
    assert len(list((out / "records" / "pd").glob("*.npz"))) == 2
    # training logs: loss and learning rate every step, the held-out figure (PD on the test references) every tenth
    for name, tag, steps in (("model", dynamics.HELD_OUT_TAG, model.steps), ("policy", policy.HELD_OUT_TAG, policy_cfg.steps)):
        facts = json.loads((out / "stages" / f"{name}.json").read_text())
        assert facts["log"] == f"logs/{name}" and facts["steps"] == steps
        scalars = read_scalars(out / "logs" / name)
        assert scalars["train/loss"][0].tolist() == list(range(1, steps + 1)) and len(scalars["train/lr"][0]) == steps
        assert scalars[tag][0].tolist() == list(range(steps // 10, steps + 1, steps // 10))
        assert list((out / "logs" / name).glob("events.out.tfevents.*"))
    assert len(list((out / "records" / "efficienttrack").glob("*.npz"))) == 2
    assert {p.name for p in (out / "plots").iterdir()} == {
        "tracking_ref_04.png",
        "tracking_ref_05.png",
        "tracking_error.png",
        "training_curves.png",
    }


@pytest.mark.slow
def test_rerun_skips_finished_stages(finished_run, refs, tmp_path):
    out, first = tmp_path / "run", finished_run[1]
    shutil.copytree(finished_run[0], out)
    stamp = {p: p.stat().st_mtime_ns for p in (out / "records").rglob("*.npz")}
    log = (out / "run.log").read_text()
    run_json = (out / "run.json").read_text()
    again = run_pipeline(TOY, *refs, out, TOY_CFG, max_plots=0)  # other plots than the first time: not another run
    assert set(again.skipped) == {"collect", "model", "policy", "evaluate_pd", "evaluate_efficienttrack"}
    assert again.metrics["efficienttrack"] == first.metrics["efficienttrack"]
    assert {p: p.stat().st_mtime_ns for p in (out / "records").rglob("*.npz")} == stamp
    assert (out / "run.json").read_text() == run_json  # provenance of the run's first invocation, kept
    appended = (out / "run.log").read_text()
    assert appended.startswith(log) and appended.count("\n=== ") == log.count("\n=== ") + 1
    assert "model trained (" in appended[len(log) :] and "earlier run" in appended[len(log) :]
    with pytest.raises(
        EfficientTrackError, match=r"other settings.*\(config.collect.seed: 0 here, 1 now; config.seed: 0 here, 1 now\)"
    ):
        run_pipeline(TOY, *refs, out, replace(TOY_CFG, seed=1))
    train, test = refs
    moved = [Reference(train[0].name, train[0].q + 0.01), *train[1:]]  # the same names, other positions
    with pytest.raises(EfficientTrackError, match=r"\(references_sha256: "):
        run_pipeline(TOY, moved, test, out, TOY_CFG)


@pytest.mark.slow
def test_interrupted_run_resumes(tmp_path, refs, finished_run, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(dynamics, "train_model", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(TOY, *refs, tmp_path, TOY_CFG)
    assert (tmp_path / "stages" / "collect.json").is_file() and not (tmp_path / "model.pt").exists()
    stamp = {p: p.stat().st_mtime_ns for p in (tmp_path / "records" / "train").rglob("*.npz")}
    assert len(stamp) == TOY_CFG.collect.passes * 4
    monkeypatch.undo()
    result = run_pipeline(TOY, *refs, tmp_path, TOY_CFG, max_plots=0)  # the plots are the finished run's test's
    assert result.skipped == ("collect", "evaluate_pd")
    assert {p: p.stat().st_mtime_ns for p in stamp} == stamp
    assert result.metrics["efficienttrack"]["mae_deg"] < result.metrics["pd"]["mae_deg"]
    # seeded: the resumed run ends where the uninterrupted one (the same settings and references) ended
    assert result.metrics["efficienttrack"] == finished_run[1].metrics["efficienttrack"]


@pytest.mark.slow
def test_cli_run_resumes_evaluate_and_collect(tmp_path, refs, finished_run, monkeypatch, capsys):
    train, test = refs
    save_references(train, tmp_path / "train")
    save_references(test, tmp_path / "test")
    TOY_CFG.save(tmp_path / "cfg.yaml")
    shutil.copytree(finished_run[0], tmp_path / "out")
    # --plots 0: the run's tracking plots are test_run_writes_everything_and_beats_pd's; the evaluation's are checked below
    code, out, err = cli_main(
        monkeypatch, capsys, "run", "--system", "toy_system:make", "--train-refs", tmp_path / "train",
        "--test-refs", tmp_path / "test", "--out", tmp_path / "out", "--preset", "tiny", "--config", tmp_path / "cfg.yaml",
        "--plots", "0",
    )  # fmt: skip
    assert code == 0, err
    assert "EfficientTrack" in out and "train model" not in out + err  # everything resumed, nothing retrained
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert set(metrics["efficienttrack"]) == set(METRIC_KEYS) and metrics["config"] == TOY_CFG.to_dict()
    assert metrics["efficienttrack"]["mae_deg"] < 0.5 * metrics["pd"]["mae_deg"]
    code, out, err = cli_main(
        monkeypatch, capsys, "evaluate", "--system", "toy_system:make", "--refs", tmp_path / "test",
        "--policy", tmp_path / "out" / "policy.pt", "--out", tmp_path / "eval", "--device", "cpu",
    )  # fmt: skip
    assert code == 0, err
    evaluated = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert set(evaluated) == set(metrics) == RESULT_KEYS
    assert evaluated["pd"] == metrics["pd"] and evaluated["efficienttrack"] == metrics["efficienttrack"]
    assert evaluated["interaction_steps"] == metrics["interaction_steps"]  # read from the policy's run folder
    assert evaluated["model"] is None and evaluated["config"] is None
    assert tuple(evaluated["provenance"]) == PROVENANCE_KEYS
    for method in ("pd", "efficienttrack"):
        assert len(list((tmp_path / "eval" / "records" / method).glob("*.npz"))) == 2
    assert {p.name for p in (tmp_path / "eval" / "plots").iterdir()} == {
        "tracking_ref_04.png",
        "tracking_ref_05.png",
        "tracking_error.png",
    }
    assert "EfficientTrack" in (tmp_path / "eval" / "run.log").read_text()
    code, out, err = cli_main(
        monkeypatch, capsys, "collect", "--plant", "toy_system:make_plant", "--pd", "xe75", "--refs", tmp_path / "test",
        "--out", tmp_path / "col", "--passes", "2", "--noise-ratio", "1:1",
    )  # fmt: skip
    assert code == 0, err
    assert "collected 4 episodes, 286 interaction steps" in out
    assert sorted(p.name for p in (tmp_path / "col").iterdir()) == ["collect.json", "pass_000", "pass_001"]


def test_evaluate_pd_alone_writes_the_run_schema(tmp_path, refs):
    metrics = evaluate(TOY, refs[1], tmp_path, max_plots=1)
    assert set(metrics) == RESULT_KEYS and json.loads((tmp_path / "metrics.json").read_text()) == metrics
    assert metrics["pd"]["mae_deg"] == pytest.approx(1.69, abs=0.01)
    assert metrics["efficienttrack"] is None and metrics["interaction_steps"] is None and metrics["policy"] is None
    assert {p.name for p in (tmp_path / "plots").iterdir()} == {"tracking_ref_04.png", "tracking_error.png"}
    log = (tmp_path / "run.log").read_text()
    assert " evaluate (commit " in log.splitlines()[0] and "PD" in log
    with pytest.raises(EfficientTrackError, match="--plots -1"):
        evaluate(TOY, refs[1], tmp_path, max_plots=-1)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--system", "toy_system:make", "--train-refs", "nowhere", "--test-refs", "nowhere"],
            "nowhere: no such file or folder",
        ),
        (["--system", "no_such_module:make", "--train-refs", "{refs}", "--test-refs", "{refs}"], "cannot import module"),
        (["--system", "xe75", "--plant", "xe75", "--train-refs", "{refs}", "--test-refs", "{refs}"], "not both"),
        (["--system", "xe75", "--train-refs", "{refs}", "--test-refs", "{refs}", "--preset", "huge"], "unknown, choose one"),
        (["--system", "toy_system:make", "--train-refs", "{refs}", "--test-refs", "{refs}", "--plots", "-1"], "--plots -1"),
    ],
)
def test_cli_bad_inputs_exit_2(tmp_path, refs, args, message, monkeypatch, capsys):
    save_references(refs[0], tmp_path / "refs")
    args = [a.replace("{refs}", str(tmp_path / "refs")) for a in args]
    code, out, err = cli_main(monkeypatch, capsys, "run", *args, "--out", tmp_path / "out")
    assert code == 2
    assert message in err and "Traceback" not in err


def test_config_roundtrip_and_validation(tmp_path):
    for name, cfg in PRESETS.items():
        path = tmp_path / f"{name}.yaml"
        cfg.save(path)
        assert load_config(path) == cfg
        cfg.save(tmp_path / f"{name}.json")
        assert load_config(tmp_path / f"{name}.json") == cfg
    (tmp_path / "partial.yaml").write_text("seed: 3\ncollect:\n  passes: 2\n")
    partial = load_config(tmp_path / "partial.yaml", PRESETS["tiny"])
    assert partial.seed == 3 and partial.collect.passes == 2 and partial.model == PRESETS["tiny"].model
    assert isinstance(from_dict({}), RunConfig)
    bad = [
        ({"colect": {}}, "unknown RunConfig field"),
        ({"collect": {"passes": "ten"}}, "passes"),
        ({"model": {"hidden": 1.5}}, "hidden"),
        ({"seed": True}, "seed"),
        ({"device": "tpu"}, "device"),
        ({"collect": {"sigma_max": -1.0}}, "sigma_max"),
    ]
    for data, message in bad:
        with pytest.raises(EfficientTrackError, match=message):
            from_dict(data, "x.yaml")
    assert np.isclose(PRESETS["paper"].collect.sigma_max, 0.05) and PRESETS["paper"].collect.passes == 10


def test_off_a_terminal_the_results_table_prints_whole(tmp_path, capsys):
    from efficienttrack.data.metrics import compute_metrics, metrics_table
    from efficienttrack.workflow.stages import LOG_WIDTH, RunLog

    log = RunLog(tmp_path, None)  # pytest captures the output: not a terminal, as a script piped to a file
    assert log.console.width == LOG_WIDTH
    from test_dynamics import lag_records

    records = lag_records(n=2, T=40)
    log.print(metrics_table({"PD": compute_metrics(records), "EfficientTrack": compute_metrics(records)}, title="t"))
    printed = capsys.readouterr().out
    assert "…" not in printed and "ETD-FMAE" in printed
