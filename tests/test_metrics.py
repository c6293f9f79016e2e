import json
import re
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.kinematics import tip_position
from efficienttrack.data.metrics import (
    METRIC_KEYS,
    TABLE_METRICS,
    compute_metrics,
    episode_metrics,
    fmae,
    interaction_hours,
    mae,
    metrics_table,
    moving_held_split,
    rmse,
    smoothness,
    tip_distance,
    tracking_error,
)
from efficienttrack.data.records import EpisodeRecord, load_records

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEG = np.pi / 180


def record_from(q_deg, q_des_deg):
    q, q_des = np.radians(np.asarray(q_deg, float)), np.radians(np.asarray(q_des_deg, float))
    steps = len(q)
    return EpisodeRecord(q=q, qd=np.zeros((steps, 4)), q_ref=q_des, q_des=q_des, u=None, t=0.05 * np.arange(steps))


# ------------------------------------------------------------------------------------------ kinematics


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def trans(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def chain_fk(q):
    """The README's 4×4 homogeneous-transform chain, one configuration at a time."""
    boom, arm, bucket, swing = q
    g = rot_y(1.0) @ rot_y(boom) @ trans(0, 0, 3.6957) @ rot_y(1.5) @ rot_y(arm) @ trans(0, 0, 1.62233) @ rot_y(bucket)
    u = trans(0, 0, 1.4) @ rot_z(swing)
    a = trans(0, -0.1, 0)
    return (np.linalg.inv(np.linalg.inv(a) @ np.linalg.inv(u)) @ g)[:3, 3]


def test_closed_form_tip_equals_transform_chain():
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (200, 4))
    expected = np.stack([chain_fk(row) for row in q])
    np.testing.assert_allclose(tip_position(q), expected, atol=1e-12, rtol=0)
    assert tip_position(q.reshape(10, 20, 4)).shape == (10, 20, 3)
    # the bucket does not move the tip; the swing turns it about the vertical axis
    moved = q.copy()
    moved[:, 2] += 0.7
    np.testing.assert_allclose(tip_position(moved), tip_position(q), atol=1e-12)
    zero = tip_position(np.zeros(4))
    np.testing.assert_allclose(
        zero, [3.6957 * np.sin(1) + 1.62233 * np.sin(2.5), -0.1, 1.4 + 3.6957 * np.cos(1) + 1.62233 * np.cos(2.5)]
    )


# ------------------------------------------------------------------------------------ hand-built cases


def test_constant_one_degree_offset():
    steps = 50
    q_des = np.linspace(0, 40, steps)[:, None] * np.ones(4)
    q = np.vstack([q_des[:1], q_des[:-1] + 1.0])  # q[t+1] = q_des[t] + 1°
    m = episode_metrics(record_from(q, q_des))
    for key in ("mae_deg", "rmse_deg", "fmae_deg"):
        assert m[key] == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(m["per_joint_mae_deg"], 1.0, atol=1e-12)


def test_wrap_359_degrees_is_minus_one():
    q = np.radians([[0, 0, 0, 0], [359, 1, 0, -179]])
    q_des = np.radians([[0, 0, 0, 181], [0, 0, 0, 0]])
    e = tracking_error(q, q_des)
    np.testing.assert_allclose(np.degrees(e), [[-1, 1, 0, 0]], atol=1e-9)
    assert np.degrees(mae(e)) == pytest.approx(0.5)
    # smoothness wraps the step too: 359° → 1° is a 2° step
    q = np.radians(np.array([[0, 0, 0, 0], [359, 0, 0, 0], [1, 0, 0, 0], [3, 0, 0, 0]]))
    assert np.degrees(smoothness(q, 1)) == pytest.approx(2 / 4)
    assert np.degrees(smoothness(q, 2)) == pytest.approx(0.0, abs=1e-9)


def test_tiny_hand_example():
    q = np.zeros((4, 4))
    q[:, 0] = [0, 3, 0, 4]  # e on boom = q[1:] = 3, 0, 4; other joints 0
    record = record_from(q, np.zeros((4, 4)))
    e = np.degrees(tracking_error(record.q, record.q_des))
    np.testing.assert_allclose(e[:, 0], [3, 0, 4], atol=1e-12)
    m = episode_metrics(record)
    assert m["mae_deg"] == pytest.approx(7 / 12)
    assert m["rmse_deg"] == pytest.approx(np.sqrt(25 / 3) / 4)
    assert m["fmae_deg"] == pytest.approx(4 / 4)
    # over q[1..3] = 3, 0, 4: steps −3, 4; one second difference 7
    assert m["smt1_deg"] == pytest.approx(np.sqrt(25 / 2) / 4)
    assert m["smt2_deg"] == pytest.approx(7 / 4)
    np.testing.assert_allclose(m["per_joint_mae_deg"], [7 / 3, 0, 0, 0], atol=1e-12)
    assert m["steps"] == 4
    # rad-level functions agree
    e_rad = np.radians(e)
    assert rmse(e_rad) == pytest.approx(np.radians(np.sqrt(25 / 3) / 4))
    assert fmae(e_rad) == pytest.approx(np.radians(1.0))


def test_tip_distance_of_a_pure_swing_error():
    q_des = np.zeros((4, 4))
    q = np.zeros((4, 4))
    q[1:, 3] = 0.1  # swing 0.1 rad off: the tip moves on a circle of the tip's horizontal radius
    radius = np.hypot(*tip_position(np.zeros(4))[:2])
    np.testing.assert_allclose(tip_distance(q, q_des), 2 * radius * np.sin(0.05), atol=1e-12)
    m = episode_metrics(record_from(np.degrees(q), q_des))
    assert m["etd_mae_cm"] == pytest.approx(200 * radius * np.sin(0.05))
    assert m["etd_fmae_cm"] == pytest.approx(200 * radius * np.sin(0.05))


def test_compute_metrics_averages_per_episode():
    def offset_episode(steps, offset):
        q_des = np.zeros((steps, 4))
        return record_from(np.vstack([np.zeros((1, 4)), q_des[:-1] + offset]), q_des)

    m = compute_metrics([offset_episode(4, 1.0), offset_episode(11, 3.0)])
    assert set(m) == set(METRIC_KEYS)
    assert (m["episodes"], m["steps"]) == (2, 15)
    assert m["mae_deg"] == pytest.approx(2.0)  # per-episode mean, not pooled ((3·1 + 10·3)/13 = 2.54)
    assert m["per_joint_mae_deg"] == pytest.approx([2.0] * 4)
    assert isinstance(m["per_joint_mae_deg"], list) and all(isinstance(m[k], float) for k in TABLE_METRICS)
    json.dumps(m)
    with pytest.raises(EfficientTrackError, match="no episodes"):
        compute_metrics([])
    with pytest.raises(EfficientTrackError, match="fewer than 4 steps"):
        compute_metrics([offset_episode(3, 1.0)])


def table_rows(table):
    console = Console(record=True, width=200)
    console.print(table)
    lines = [line for line in console.export_text().splitlines() if line.count("│") > 5]
    return {line.split("│")[1].strip(): [cell.strip() for cell in line.split("│")[2:-1]] for line in lines}


def test_metrics_table_renders_each_method():
    a = compute_metrics([record_from(np.full((5, 4), 1.0), np.zeros((5, 4)))])
    b = dict(a, mae_deg=0.6944, steps=3472, episodes=8)
    rows = table_rows(metrics_table({"PD": a, "EfficientTrack": b}, title="XE75", training_steps={"EfficientTrack": 176720}))
    assert set(rows) == {"PD", "EfficientTrack"}
    # MAE … swing, then the test episodes and their steps, then the training interactions I.S. and I.T. (h)
    assert rows["EfficientTrack"][0] == "0.69" and rows["EfficientTrack"][-4:] == ["8", "3472", "176720", "2.45"]
    assert f"{interaction_hours(176720):.2f}" == "2.45"
    assert rows["PD"][0] == "1.00" and rows["PD"][-4:] == ["1", "5", "–", "–"]  # PD is not trained
    untrained = table_rows(metrics_table({"PD": a}, title="episodes"))  # the metrics command: no training interactions
    assert untrained["PD"][-2:] == ["–", "–"]


# ------------------------------------------------------------------------------------- published sets


def published_rows():
    readme = DATA / "README.md"
    if not readme.is_file():
        return []
    text = readme.read_text().split("### Figures of the shared sets", 1)[1]
    rows = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 11 and re.fullmatch(r"[\w/]+", cells[0]) and cells[1].isdigit():
            rows.append((cells[0], [float(c) for c in cells[1:10]] + [[float(v) for v in cells[10].split(",")]]))
    return rows


def test_readme_table_was_parsed():
    if not (DATA / "README.md").is_file():
        pytest.skip(f"shared XE75 data not found at {DATA}")
    assert [name for name, _ in published_rows()][-1] == "upstream_format_samples"
    assert len(published_rows()) == 8


NO_DATA = pytest.param("-", None, marks=pytest.mark.skip(f"shared XE75 data not found at {DATA}"))


@pytest.mark.parametrize("name,published", published_rows() or [NO_DATA])
def test_figures_of_the_shared_sets(name, published):
    m = compute_metrics(load_records(DATA / name))
    assert m["episodes"] == published[0] and m["steps"] == published[1]
    for key, value in zip(TABLE_METRICS, published[2:9], strict=True):
        assert abs(m[key] - value) <= 0.005 + 1e-9, (name, key, m[key], value)
    np.testing.assert_allclose(m["per_joint_mae_deg"], published[9], atol=0.005 + 1e-9, rtol=0)


def test_metrics_cli_json_pd_clean():
    if not DATA.is_dir():
        pytest.skip(f"shared XE75 data not found at {DATA}")
    result = CliRunner().invoke(app, ["metrics", "--json", str(DATA / "xe75" / "pd_clean_train")])
    assert result.exit_code == 0, result.output
    figures = json.loads(result.output)
    assert list(figures) == ["path", *METRIC_KEYS]
    assert figures["mae_deg"] == 5.4391 and figures["per_joint_mae_deg"] == [1.4497, 4.722, 5.0496, 10.5352]
    result = CliRunner().invoke(app, ["metrics", str(DATA / "xe75" / "pd_clean_train")], env={"COLUMNS": "80"})
    assert result.exit_code == 0 and "pd_clean_train" in result.output and "80.02" in result.output


def test_moving_held_split_tells_lag_from_an_offset_at_rest():
    t = np.arange(200)
    q_des = np.zeros((200, 4))
    q_des[:100, 0] = np.radians(0.5) * t[:100]  # boom moves at 10 °/s, then holds; the other joints hold
    q_des[100:, 0] = q_des[99, 0]
    q = np.empty_like(q_des)
    q[0] = q_des[0]
    q[1:] = q_des[:-1]
    q[1:101, 0] -= np.radians(1.0)  # 1° behind while moving
    q[101:, 0] -= np.radians(0.25)  # 0.25° below the held reference
    record = EpisodeRecord(q=q, qd=np.zeros_like(q), q_ref=q_des, q_des=q_des, u=None, t=t / 20.0)
    split = moving_held_split([record])
    assert split["held_share"][0] == pytest.approx(100 / 199, abs=0.01) and split["held_share"][1] == 1.0
    assert split["moving_mae_deg"][0] == pytest.approx(1.0) and split["held_mae_deg"][0] == pytest.approx(0.25, abs=0.01)
    assert split["held_bias_deg"][0] == pytest.approx(-0.25, abs=0.01)
    assert split["moving_mae_deg"][1] is None and split["held_mae_deg"][1] == 0.0
