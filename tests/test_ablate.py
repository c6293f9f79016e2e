"""The ablations: their variants' settings, a quick ablation's table, JSON and figure, reruns, the CLI, Ray."""

import json
import math
import pickle
import shutil
from dataclasses import replace

import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.references import Reference, save_references
from efficienttrack.study import (
    ABLATIONS,
    ablation_jobs,
    make_ablation_study,
    make_jobs,
    make_study,
    run_ablation,
    run_study,
)
from efficienttrack.study.ablation_report import FIELDS
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.config import PRESETS

TINY = PRESETS["tiny"]
FAST = replace(TINY, device="cpu", model=replace(TINY.model, steps=30), policy=replace(TINY.policy, steps=30))
"""The quick preset's EfficientTrack settings, with fewer training steps: a run takes a few seconds."""


@pytest.fixture(scope="module")
def refs():
    """Two short training references and one test reference (60 steps of generated loading cycles)."""
    cycles = [Reference(r.name, r.q[:60]) for r in generate_references(3, seed=1)]
    return cycles[:2], cycles[2:]


def tiny_ablation(refs, passes=1):
    return make_ablation_study(SystemSpec(), *refs, preset="tiny", passes=passes, run_config=FAST)


@pytest.fixture(scope="module")
def finished(tmp_path_factory, refs):
    """k-smooth 0 (seeds 0 and 1) and 2 (seed 0), one collection pass each, run in this process: a spread over seeds and
    a variant of one seed, in three EfficientTrack runs."""
    out = tmp_path_factory.mktemp("ablation")
    study = tiny_ablation(refs)
    jobs = ablation_jobs(ABLATIONS["k-smooth"], study, [0, 1], ["0", "2"])[:3]  # not k_smooth-2-s1
    lines = []
    return out, study, run_ablation(ABLATIONS["k-smooth"], study, jobs, out, log=lines.append), lines


def test_noise_ratio_variants_differ_only_in_the_mix_at_equal_passes(refs):
    study = tiny_ablation(refs, passes=2)
    assert study.budget == 2 * 2 * 59  # the interaction steps of every variant
    jobs = ablation_jobs(ABLATIONS["noise-ratio"], study, [0, 3])
    assert [job.name for job in jobs[::2]] == [
        f"efficienttrack-{name}-s0" for name in ("no-noise", "only-noise", "ratio-9-1", "ratio-9-2", "ratio-9-3", "ratio-9-4")
    ]
    assert jobs[1].name == "efficienttrack-no-noise-s3" and {job.loop for job in jobs} == {"closed"}
    configs = [job.run_config for job in jobs if job.seed == 0]
    assert [c.collect.noise_ratio for c in configs] == [(0, 1), (1, 0), (9, 1), (9, 2), (9, 3), (9, 4)]
    for cfg in configs:
        assert cfg.collect.passes == 2 and cfg.seed == 0 and cfg.collect.seed == 0
        assert replace(cfg, collect=replace(cfg.collect, noise_ratio=(9, 2))) == configs[3]  # nothing else differs
    assert jobs[1].run_config.seed == 3 and jobs[1].run_config.collect.seed == 3
    # the preset's passes when none are given: the quick preset's tiny run settings collect 3
    assert make_ablation_study(SystemSpec(), *refs, preset="tiny").run_config.collect.passes == 3


def test_k_smooth_and_history_variants(refs):
    study = tiny_ablation(refs)
    k = [job.run_config for job in ablation_jobs(ABLATIONS["k-smooth"], study)]
    assert [c.policy.k_smooth for c in k] == [0, 0.5, 1, 2]
    assert all(replace(c, policy=replace(c.policy, k_smooth=1.0)) == k[2] for c in k)
    history = ablation_jobs(ABLATIONS["history"], study, [0], ["1", "20"])
    assert [job.name for job in history] == ["efficienttrack-history-1-s0", "efficienttrack-history-20-s0"]
    assert [job.run_config.model.history_length for job in history] == [1, 20]
    assert all(job.run_config.model.horizon == FAST.model.horizon for job in history)
    for name, values, message in [
        ("k-smooth", ["-1"], "--values '-1': expected k_smooth"),
        ("k-smooth", ["1", "1.0"], "a variant is given twice"),
        ("history", ["0"], "--values '0': expected a history length"),
        ("history", ["500"], "variant history-500: .*history"),
        ("noise-ratio", ["9/2"], "--values"),
    ]:
        with pytest.raises(EfficientTrackError, match=message):
            ablation_jobs(ABLATIONS[name], study, [0], values)
    with pytest.raises(EfficientTrackError, match="--passes 0"):
        tiny_ablation(refs, passes=0)


@pytest.mark.slow
def test_ablation_writes_table_json_and_figure(finished):
    out, study, result, lines = finished
    names = ["efficienttrack-k_smooth-0-s0", "efficienttrack-k_smooth-0-s1", "efficienttrack-k_smooth-2-s0"]
    assert list(result.ran) == names and not result.failed and not result.skipped
    assert lines[0].endswith("3 jobs, 0 finished earlier (skipped), 3 to run (local)")
    document = json.loads((out / "ablation.json").read_text())
    assert document["ablation"] == "k-smooth" and document["passes"] == 1 and document["preset"] == "tiny"
    entries = document["variants"]
    assert [(e["variant"], e["label"], e["seeds"]) for e in entries] == [
        ("k_smooth-0", "k_smooth = 0", [0, 1]), ("k_smooth-2", "k_smooth = 2", [0])
    ]  # fmt: skip
    for entry in entries:
        spread = len(entry["seeds"]) > 1  # one seed: no std
        for field in FIELDS:
            std = entry[f"{field}_std"]
            assert math.isfinite(entry[field]) and (math.isfinite(std) if spread else std is None), field
        assert entry["interaction_steps"] == 118
        assert entry["overrides"] == {"policy": {"k_smooth": float(entry["variant"].split("-")[1])}}
        assert entry["mae_deg"] == pytest.approx(sum(j["mae_deg"] for j in entry["jobs"]) / len(entry["jobs"]))
    assert entries[0]["interaction_steps_std"] == 0  # equal data
    assert entries[0]["jobs"][0]["mae_deg"] != entries[1]["mae_deg"]  # seed 0 of each variant
    point = json.loads((out / "jobs" / names[0] / "result.json").read_text())["curve"][0]
    assert point["po_mae"]["train_windows"] > 0 and point["po_mae"]["heldout_windows"] > 0 and point["passes"] == 1
    assert (out / "jobs" / names[0] / "run" / "policy.pt").is_file()
    table = (out / "ablation.md").read_text()
    assert "| k_smooth = 0 | 2 | 118 ± 0 |" in table and "| k_smooth = 2 | 1 | 118 |" in table
    assert "Po.MAE, training (°)" in table and "1st oSMT" in table
    assert "The paper's values" in table and "| k_smooth = 1 | 0.27 | 0.74 | 0.60 |" in table
    header = (out / "ablation.csv").read_text().splitlines()[0].split(",")
    assert header[:5] == ["variant", "label", "seeds", "po_mae_train_deg", "po_mae_train_deg_std"]
    assert (out / "ablation.png").is_file()


@pytest.mark.slow
def test_rerun_skips_finished_jobs_and_a_folder_refuses_other_work(finished, refs):
    out, study, _, _ = finished
    results = sorted((out / "jobs").glob("*/result.json"))
    before = [path.stat().st_mtime_ns for path in results]
    jobs = ablation_jobs(ABLATIONS["k-smooth"], study, [0], ["0", "2"])
    rerun = run_ablation(ABLATIONS["k-smooth"], study, jobs, out, log=lambda line: None)
    assert rerun.skipped == ("efficienttrack-k_smooth-0-s0", "efficienttrack-k_smooth-2-s0") and rerun.ran == ()
    assert [path.stat().st_mtime_ns for path in results] == before and len(rerun.report.entries) == 2
    other = ablation_jobs(ABLATIONS["history"], study, [0], ["1"])
    with pytest.raises(EfficientTrackError, match="study_config.json: this folder holds a study, or an ablation of another"):
        run_ablation(ABLATIONS["history"], study, other, out)
    more = tiny_ablation(refs, passes=2)
    with pytest.raises(EfficientTrackError, match="an ablation of another kind, system, references, passes"):
        run_ablation(ABLATIONS["k-smooth"], more, ablation_jobs(ABLATIONS["k-smooth"], more, [0], ["0"]), out)
    plain = make_study(SystemSpec(), *refs, budget=118, preset="tiny", run_config=FAST)
    with pytest.raises(EfficientTrackError, match="holds a study of another system, references, budget, preset or settings"):
        run_study(plain, make_jobs(plain, ["pd"]), out)


@pytest.mark.figures
def test_cli_ablate(finished, refs, tmp_path, monkeypatch):
    # the command on a copy of the fixture's folder, with its settings: it finds the jobs of its --values finished, as its
    # first line says (running them, and their progress lines, is run_ablation's, which the command calls)
    monkeypatch.setitem(PRESETS, "tiny", FAST)
    save_references(refs[0], tmp_path / "train")
    save_references(refs[1], tmp_path / "test")
    out = tmp_path / "ablation"
    shutil.copytree(finished[0], out)
    common = ["ablate", "k-smooth", "--train-refs", tmp_path / "train", "--test-refs", tmp_path / "test", "--out", out,
              "--preset", "tiny", "--passes", "1"]  # fmt: skip
    result = CliRunner().invoke(app, [str(a) for a in [*common, "--values", "0,2"]], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "2 jobs, 2 finished earlier (skipped), 0 to run (local)" in result.output
    assert "| k_smooth = 0 | 2 | 118 ± 0 |" in result.output and "| k_smooth = 2 | 1 | 118 |" in result.output
    again = CliRunner().invoke(app, ["ablate", "k-smooth", "--out", str(out), "--report-only"])
    assert again.exit_code == 0 and "| k_smooth = 2 | 1 | 118 |" in again.output
    assert (out / "ablation.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for args, message in [
        ([*common, "--values", "2", "--executor", "slurm"], "--executor slurm: unknown"),
        ([*common, "--values", "x"], "--values 'x': expected k_smooth"),
        ([*common, "--values", "2", "--passes", "2"], "an ablation of another kind, system, references, passes"),
        (["ablate", "dropout", "--out", out], "ablation 'dropout': unknown, choose one of noise-ratio, k-smooth, history"),
        (["ablate", "history", "--out", out, "--report-only"], "holds the ablation k-smooth, not history"),
    ]:
        refused = CliRunner().invoke(app, [str(a) for a in args])
        assert isinstance(refused.exception, EfficientTrackError) and message in str(refused.exception), refused.output


def test_ablation_jobs_travel_to_a_worker_as_study_jobs_do(refs):
    # ablations run through the study's executors (run_jobs); a process pool or Ray sends each job pickled, and the
    # study's tests run both executors: what is left to check is that an ablation's jobs survive the trip
    study = tiny_ablation(refs)
    jobs = ablation_jobs(ABLATIONS["noise-ratio"], study, [0], ["9:2"])
    [sent] = pickle.loads(pickle.dumps(jobs))
    assert sent.name == jobs[0].name and sent.variant.overrides == jobs[0].variant.overrides
    assert sent.variant.apply(sent.study.run_config) == jobs[0].variant.apply(jobs[0].study.run_config)
