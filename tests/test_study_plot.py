"""Several study folders in one table and figure (``study-plot``), and the mean curve over seeds."""

import json

import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.study.report import METRICS, combine, mean_curve

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
        curve = [{"interaction_steps": 10 * (i + 1), "wall_seconds": 1.0, "metrics": {**dict.fromkeys(METRICS, 1.0),
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
    assert [row.split(" | ")[:3] for row in rows] == [["| EfficientTrack", "open", "1"], ["| SuperTrack", "closed", "2"]]
    assert "*paper, Table I*" in result.output  # the paper's rows under ours: these studies ran on its simulator
    again = study_folder(tmp_path / "again", PAPER, ("supertrack", "closed", 1, [0.7, 0.5]))
    with pytest.raises(EfficientTrackError, match=r"again and .*one both hold supertrack-closed-s1"):
        combine([one, again], tmp_path / "x.png")
    pd_here, pd_there = (study_folder(tmp_path / f"pd{i}", PAPER, ("pd", "closed", i, [2.73])) for i in (0, 1))
    pd_only = combine([pd_here, pd_there], tmp_path / "x.png")
    assert len(pd_only.entries) == 1  # PD ignores the seed: one measurement
    assert "| *paper, Table I* | closed |  | *–* | *–* | *–* | *2.73* |" in pd_only.markdown  # PD's row has no I.S.
    pd_other = study_folder(tmp_path / "pd2", PAPER, ("pd", "closed", 0, [2.74]))
    with pytest.raises(EfficientTrackError, match="both hold pd-closed-s0"):
        combine([pd_here, pd_other], tmp_path / "x.png")  # not the same figures: not the same measurement
    other = study_folder(tmp_path / "other", {**PAPER, "system": "xe75"}, ("pd", "closed", 0, [4.9]))
    with pytest.raises(EfficientTrackError, match="other: ran on .*xe75.*one system only"):
        combine([one, other], tmp_path / "x.png")
    with pytest.raises(EfficientTrackError, match="no study here"):
        combine([tmp_path / "nothing"], tmp_path / "x.png")
