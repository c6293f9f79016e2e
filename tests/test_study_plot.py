"""Several study folders in one table and figure (``study-plot``), and the mean curve over seeds."""

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.metrics import TABLE_METRICS
from efficienttrack.study.report import combine, report
from efficienttrack.study.summary import mean_curve, summarize
from efficienttrack.study.tables import equal_interaction_table, markdown_table

pytestmark = pytest.mark.figures  # study-plot's work is the figure

PAPER = {"system": "paper", "plant": None, "pd": None, "options": {}}


def points(*pairs):
    return [{"interaction_steps": steps, "mae_deg": mae} for steps, mae in pairs]


def test_seeds_with_as_many_points_are_averaged_evaluation_by_evaluation():
    curve = mean_curve([points((100, 1.0), (200, 0.5)), points((104, 2.0), (203, 1.5))])
    assert [(p["interaction_steps"], p["mae_deg"], p["seeds"]) for p in curve] == [(102, 1.5, 2), (202, 1.0, 2)]
    uneven = mean_curve([points((100, 1.0), (200, 0.5)), points((100, 2.0))])
    assert [(p["interaction_steps"], p["mae_deg"], p["seeds"]) for p in uneven] == [(100, 1.5, 2), (200, 0.5, 1)]


def study_folder(folder, system, *jobs):
    """A study folder with finished jobs (method, loop, seed, MAE at 10 and 20 steps)."""
    folder.mkdir()
    (folder / "study_config.json").write_text(json.dumps({"system": system}))
    for method, loop, seed, maes in jobs:
        curve = [{"interaction_steps": 10 * (i + 1), "wall_seconds": 1.0, "metrics": {**dict.fromkeys(TABLE_METRICS, 1.0),
                  "mae_deg": m, "per_joint_mae_deg": [m] * 4}} for i, m in enumerate(maes)]  # fmt: skip
        job = folder / "jobs" / f"{method}-{loop}-s{seed}"
        job.mkdir(parents=True)
        (job / "result.json").write_text(json.dumps({"method": method, "loop": loop, "seed": seed, "curve": curve}))
    return folder


def test_study_folders_of_one_system_make_one_table_and_figure(tmp_path):
    one = study_folder(
        tmp_path / "one", PAPER, ("supertrack", "closed", 0, [0.6, 0.4]), ("supertrack", "closed", 1, [0.8, 0.6])
    )
    two = study_folder(tmp_path / "two", PAPER, ("efficienttrack", "open", 0, [1.2, 1.7]))
    result = CliRunner().invoke(app, ["study-plot", str(one), str(two), "--out", str(tmp_path / "all.png")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "all.png").stat().st_size > 0
    rows = [line for line in result.output.splitlines() if line.startswith("| SuperTrack") or line.startswith("| Effic")]
    assert [row.split(" | ")[:3] for row in rows] == [
        ["| EfficientTrack", "open", "1"],
        ["| SuperTrack (reduced)", "closed", "2"],
    ]
    assert "*paper, Table I*" in result.output  # the paper's rows under ours: these studies ran on its simulator
    again = study_folder(tmp_path / "again", PAPER, ("supertrack", "closed", 1, [0.7, 0.5]))
    with pytest.raises(EfficientTrackError, match=r"again and .*one both hold supertrack-closed-s1"):
        combine([one, again], tmp_path / "x.png")
    pd_here, pd_there = (study_folder(tmp_path / f"pd{i}", PAPER, ("pd", "closed", i, [2.73])) for i in (0, 1))
    pd_only = combine([pd_here, pd_there], tmp_path / "x.png")
    assert len(pd_only.entries) == 1  # PD ignores the seed: one measurement
    assert "| *paper, Table I* | closed |  | *–* | *–* | *–* | *–* | *2.73* |" in pd_only.markdown  # PD's row has no I.S.
    pd_other = study_folder(tmp_path / "pd2", PAPER, ("pd", "closed", 0, [2.74]))
    with pytest.raises(EfficientTrackError, match="both hold pd-closed-s0"):
        combine([pd_here, pd_other], tmp_path / "x.png")  # not the same figures: not the same measurement
    other = study_folder(tmp_path / "other", {**PAPER, "system": "xe75"}, ("pd", "closed", 0, [4.9]))
    with pytest.raises(EfficientTrackError, match="other: ran on .*xe75.*one system only"):
        combine([one, other], tmp_path / "x.png")
    with pytest.raises(EfficientTrackError, match="no study here"):
        combine([tmp_path / "nothing"], tmp_path / "x.png")


def test_a_job_run_again_with_a_larger_budget_is_shown_once_at_its_longer_run(tmp_path):
    short = study_folder(tmp_path / "short", PAPER, ("sac", "open", 0, [4.0, 3.0]), ("ppo", "open", 0, [9.0, 5.0]))
    long = study_folder(tmp_path / "long", PAPER, ("sac", "open", 0, [4.0, 3.0, 2.0, 1.5]))
    for folder, budget in ((short, 20), (long, 40)):
        job = folder / "jobs" / "sac-open-s0" / "result.json"
        job.write_text(json.dumps({**json.loads(job.read_text()), "budget": budget}))
    for order in ([short, long], [long, short]):
        report = combine(order, tmp_path / "x.png")
        sac = next(entry for entry in report.entries if entry["method"] == "sac")
        assert sac["seeds"] == [0] and sac["mae_deg"] == 1.5  # the longer run, once
        assert {entry["method"] for entry in report.entries} == {"sac", "ppo"}  # the short folder's other jobs stay
        assert f"sac-open-s0: {long}'s 40 steps in place of {short}'s 20" in report.markdown


def result(method, loop, seed, *pairs):
    """A job's result with its curve's (interaction steps, test MAE)."""
    curve = [{"interaction_steps": steps, "metrics": {**dict.fromkeys(TABLE_METRICS, 1.0), "mae_deg": mae,
              "per_joint_mae_deg": [mae] * 4}} for steps, mae in pairs]  # fmt: skip
    return {"method": method, "loop": loop, "seed": seed, "curve": curve}


def table_rows(markdown):
    """A table's rows: (method, loop) → the cells after them."""
    rows = [line.split(" | ") for line in markdown.splitlines() if line.startswith("| ") and "---" not in line]
    return {(row[0][2:], row[1]): [c.rstrip(" |") for c in row[2:]] for row in rows[1:]}


def test_equal_interaction_cells_hold_each_seeds_last_point_at_or_below_the_count():
    results = [
        result("efficienttrack", "closed", 0, (10, 0.5), (20, 0.4)),
        result("efficienttrack", "closed", 1, (12, 0.7), (20, 0.6)),
        result("pd", "closed", 0, (0, 2.73)),
        result("sac", "closed", 0, (10, 1.0), (100, 0.8)),
    ]
    markdown = equal_interaction_table(summarize(results), [30, 5, 11, 15, 20, 20])
    assert "| method | loop | seeds | ≤ 5 | ≤ 11 | ≤ 15 | ≤ 20 | ≤ 30 |" in markdown  # sorted, once each
    rows = table_rows(markdown)
    assert list(rows) == [
        ("PD", "closed"),
        ("EfficientTrack", "closed"),
        ("SAC (reduced)", "closed"),
    ]  # the main table's order
    assert rows["PD", "closed"] == ["1", "2.730 (0)", "", "", "", ""]  # in the first column only
    assert rows["EfficientTrack", "closed"] == [
        "2",
        "",  # no point at or below 5 steps
        "",  # seed 1 has none at or below 11
        "0.600 ± 0.141 (10–12)",  # the seeds' points differ: min–max
        "0.500 ± 0.141 (20)",
        "",  # past the final points, already shown
    ]
    assert rows["SAC (reduced)", "closed"] == ["1", "", "1.000 (10)", "1.000 (10)", "1.000 (10)", "1.000 (10)"]  # no ± alone
    assert "last curve point at or below the column's interaction steps" in markdown


def test_study_plot_at_prints_the_equal_interaction_table_and_refuses_bad_counts(tmp_path):
    one = study_folder(tmp_path / "one", PAPER, ("sac", "closed", 0, [0.6, 0.4]), ("sac", "closed", 1, [0.8, 0.6]))
    figure = tmp_path / "all.png"
    result = CliRunner().invoke(app, ["study-plot", str(one), "--out", str(figure), "--at", "15,20,1000"])
    assert result.exit_code == 0, result.output
    assert "| SAC (reduced) | closed | 2 | 0.700 ± 0.141 (10) | 0.500 ± 0.141 (20) |  |" in result.output
    for bad in ("15,abc", "15,0", "-5", "1.5"):
        result = CliRunner().invoke(app, ["study-plot", str(one), "--out", str(tmp_path / "x.png"), "--at", bad])
        assert result.exit_code != 0 and f"--at '{bad.split(',')[-1]}'" in str(result.exception)
    assert not (tmp_path / "x.png").exists()


def validated(method, loop, seed, *points):
    """A job's result with validation figures: each point (interaction steps, test MAE, validation MAE, the other
    metrics' value), its wall time equal to its interaction steps."""
    curve = [{"interaction_steps": steps, "wall_seconds": steps, "metrics": {**dict.fromkeys(TABLE_METRICS, other),
              "mae_deg": mae, "per_joint_mae_deg": [mae] * 4}, "validation": {"mae_deg": val}}
             for steps, mae, val, other in points]  # fmt: skip
    return {"method": method, "loop": loop, "seed": seed, "curve": curve}


def split_tables(markdown):
    """The first table's text and the second's (the points chosen on validation; empty without it)."""
    first, _, second = markdown.partition("## Each method at the point its validation references chose")
    return first, second


def test_a_second_table_gives_each_method_at_its_points_chosen_on_validation_with_every_metric():
    results = [
        validated("pd", "closed", 0, (0, 2.7, 2.9, 1.0)),
        # validation chooses 10 steps on seed 0 and 20 on seed 1; both seeds' final points, at 30, have lower test MAEs
        validated("efficienttrack", "closed", 0, (10, 0.4, 0.5, 2.0), (20, 0.3, 0.6, 5.0), (30, 0.2, 0.7, 6.0)),
        validated("efficienttrack", "closed", 1, (10, 0.9, 0.9, 9.0), (20, 0.8, 0.5, 4.0), (30, 0.1, 0.8, 8.0)),
        result("ilc", "closed", 0, (0, 2.7), (10, 0.05)),  # the oracle: no validation
    ]
    entries = summarize(results)
    first, second = split_tables(markdown_table(entries, {}))
    assert table_rows(first)["EfficientTrack", "closed"][:6] == ["2", "30 ± 0", "0.000 ± 0.000", "30 ± 0", "–", "0.15 ± 0.07"]
    assert table_rows(first)["EfficientTrack", "closed"][-6:] == [
        "[0.100, 0.200]",  # the final MAE's (0.2 and 0.1) bootstrap interval over the two seeds: their extremes
        "0.60 ± 0.28",
        "[0.400, 0.800]",
        "15 ± 7",
        "0.15 ± 0.07",
        "30 ± 0",
    ]
    assert entries[1]["mae_deg_ci95"] == [0.1, 0.2] and entries[0]["mae_deg_ci95"] is None  # PD: one seed
    selected = table_rows(second)
    ilc = ("ILC (oracle: sees the test references)", "closed")
    assert list(selected) == [("PD", "closed"), ("EfficientTrack", "closed"), ilc]
    assert selected["EfficientTrack", "closed"] == [
        "2",
        "15 ± 7",  # I.S.: 10 and 20
        "0.000 ± 0.000",
        "15 ± 7",  # wall time
        "–",  # gradient samples per interaction step: these points do not count them
        "0.60 ± 0.28",  # MAE: 0.4 and 0.8
        "3.00 ± 1.41",  # RMSE, FMAE: 2 and 4
        "3.00 ± 1.41",
        "3.000 ± 1.414",  # 1st and 2nd oSMT
        "3.000 ± 1.414",
        "3.00 ± 1.41",  # ETD-MAE, ETD-FMAE
        "3.00 ± 1.41",
    ]
    assert selected["PD", "closed"] == table_rows(first)["PD", "closed"][:-6]  # its single point, in both tables
    assert selected[ilc] == table_rows(first)[ilc][:-6] and selected[ilc][5] == "0.05"  # no choice: its final point
    assert "lowest MAE on the validation references (held out of every method's training), its test metrics." in second
    assert "Table I" not in second


def test_the_papers_rows_are_under_the_second_table_on_its_simulator_and_no_second_table_without_validation():
    results = [
        validated("efficienttrack", "closed", 0, (10, 0.4, 0.5, 2.0), (20, 0.3, 0.6, 5.0)),
        validated("efficienttrack", "closed", 1, (10, 0.9, 0.9, 9.0), (20, 0.8, 0.5, 4.0)),
    ]
    first, second = split_tables(markdown_table(summarize(results), {}, paper=True))
    lines = second.splitlines()
    ours = next(i for i, line in enumerate(lines) if line.startswith("| EfficientTrack | closed | 2 | 15 ± 7 |"))
    assert lines[ours + 1] == (
        "| *paper, Table I* | closed |  | *176,720* | *2.454* | *–* | *–* | *0.32* | *0.46* | *0.23* | *0.670* | *0.590* "
        "| *3.94* | *2.00* |"
    )  # as in the first table, without its selected and best columns
    assert lines[ours + 1] + "  |  |  |  |" in first
    assert second.rstrip().endswith("its test metrics; the paper's rows are each method's best point.")
    plain = markdown_table(summarize([result("efficienttrack", "closed", 0, (10, 0.4), (20, 0.3))]), {}, paper=True)
    assert split_tables(plain)[1] == "" and "validation references chose" not in plain


def test_a_studys_results_file_redraws_its_table_and_figure_without_the_folder(tmp_path):
    folder = study_folder(
        tmp_path / "study", PAPER, ("supertrack", "closed", 0, [0.6, 0.4]), ("efficienttrack", "closed", 0, [0.5, 0.3])
    )
    (folder / "jobs" / "sac-closed-s0").mkdir()
    (folder / "jobs" / "sac-closed-s0" / "error.json").write_text(json.dumps({"error": "ran out of time"}))
    written = report(folder)
    committed = tmp_path / "docs" / "table.json"
    committed.parent.mkdir()
    shutil.copy(folder / "results.json", committed)
    shutil.rmtree(folder)
    redrawn = combine([committed], tmp_path / "redrawn.png")
    assert redrawn.markdown.replace(f"{committed}/", "") == written.markdown  # a failed job named with its source
    assert "sac-closed-s0`: ran out of time" in written.markdown
    assert redrawn.entries == json.loads(json.dumps(written.entries))  # the numbers, as study.json holds them
    assert (tmp_path / "redrawn.png").stat().st_size > 0
    committed.write_text(json.dumps({"format": "something else", "jobs": []}))
    with pytest.raises(EfficientTrackError, match="not a study's results.json"):
        combine([committed], tmp_path / "x.png")


COMMITTED = sorted((Path(__file__).resolve().parents[1] / "docs" / "results").glob("*.json"))
"""The results files committed for the published tables (docs/results/NAME.json, its tables in NAME.md)."""


def test_results_for_the_published_tables_are_committed():
    assert COMMITTED, "docs/results/ holds no study results file"


@pytest.mark.parametrize("path", COMMITTED, ids=[p.stem for p in COMMITTED])
def test_a_committed_results_file_redraws_its_published_table(path, tmp_path):
    """What ``study-plot docs/results/NAME.json`` prints is the committed NAME.md, from the data file alone."""
    drawn = combine([path], tmp_path / "figure.png")
    assert drawn.markdown in path.with_suffix(".md").read_text(), f"{path.name} no longer gives {path.stem}.md"
    assert (tmp_path / "figure.png").stat().st_size > 0
