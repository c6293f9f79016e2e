"""``efficienttrack limits``: limits proposed from a machine's logs (known answers, the swing's wrap, the printed reasons),
``--check`` on good and bad files, and the shipped ``xe75`` limits file (``--limits xe75``)."""

from __future__ import annotations

import json
import math
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from efficienttrack import cli
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, MAX_ABS_ANGLE, SWING
from efficienttrack.data.records import EpisodeRecord, load_records, save_records
from efficienttrack.systems.limits import GuardLimits, limits_preset_path
from efficienttrack.systems.limits_from_logs import log_stats, propose_limits, write_limits
from efficienttrack.systems.spec import SystemSpec, load_system
from test_records import make_record

PD_LOGS = Path(__file__).resolve().parents[2] / "shared" / "data" / "xe75" / "pd_noise_train"


def record(q: np.ndarray, qd: np.ndarray | None = None, name: str = "ep") -> EpisodeRecord:
    """An episode with positions ``q`` (T, 4) rad, sent and desired exactly (q_ref = q_des = q), and ``qd`` (0.1 rad/s)."""
    q = np.asarray(q, dtype=np.float64)
    qd = np.full_like(q, 0.1) if qd is None else qd
    return EpisodeRecord(q=q, qd=qd, q_ref=q.copy(), q_des=q.copy(), u=None, t=DT * np.arange(len(q)), meta={"name": name})


def ramp(lo: float, hi: float, steps: int = 51) -> np.ndarray:
    """(steps, 4): every joint from ``lo`` to ``hi`` rad."""
    return np.repeat(np.linspace(lo, hi, steps)[:, None], 4, axis=1)


def run_main(argv: list[str], monkeypatch, capsys) -> tuple[int | str | None, str, str]:
    """``efficienttrack ARGV`` through the real entry point; its exit code (0 when it returned), stdout and stderr."""
    monkeypatch.setattr(sys, "argv", ["efficienttrack", *map(str, argv)])
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # main() sets its own; put it back after
    monkeypatch.setenv("COLUMNS", "200")
    code: int | str | None = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


# ------------------------------------------------------------------------------------------- the rules


def test_joint_range_is_the_range_seen_widened_by_the_margin():
    q = ramp(-0.2, 0.3)
    q[8:13, 1] = [-0.2, -0.3, -0.4, -0.3, -0.2]  # q_ref and q_des count too: the arm is sent lower than it ever was
    rec = record(ramp(-0.2, 0.3))
    rec.q_ref = q
    limits, reasons = propose_limits([rec], margin=0.05)
    np.testing.assert_allclose(limits.q_min, [-0.25, -0.45, -0.25, -0.25], atol=1e-12)
    np.testing.assert_allclose(limits.q_max, [0.35, 0.35, 0.35, 0.35], atol=1e-12)
    assert limits.q_min[0] <= -0.25 and limits.q_max[0] >= 0.35  # rounded outward, never tighter
    limits, _ = propose_limits([rec], margin=0.0)  # exactly the range seen; the swing's wrapped −0.2 is a hair below
    assert limits.q_min[:3] == (-0.2, -0.4, -0.2) and limits.q_min[SWING] == pytest.approx(-0.2, abs=1e-4)
    assert not limits.outside(np.concatenate([rec.q, rec.q_ref])).any()
    assert limits.q_max[:3] == (0.3,) * 3
    # the XE75's bound kept, but at most half the range: the bucket's and swing's 0.4 rad lowered to 0.25
    assert limits.max_adjust[:3] == (0.15, 0.3, 0.25) and limits.max_adjust[SWING] == pytest.approx(0.25, abs=1e-4)
    assert limits.max_adjust_rate == tuple(b / 2 for b in limits.max_adjust) and not limits.implausible()
    assert "lowered to half the joint's range at the bucket, swing" in reasons[4]
    assert [line.split(":")[0] for line in reasons] == [
        "q_min", "q_max", "swing", "max_speed", "max_adjust", "max_adjust_rate", "stale_steps"
    ]  # fmt: skip
    assert "lowest q/q_ref/q_des seen [-0.2000, -0.4000, -0.2000, -0.2000]" in reasons[0] and "margin 0.05" in reasons[0]
    assert "highest q/q_ref/q_des seen [0.3000, 0.3000, 0.3000, 0.3000] + margin 0.05 rad" in reasons[1]


def test_an_isolated_spike_does_not_reach_the_limits_and_is_reported():
    clean = record(ramp(-0.2, 0.3))
    glitchy = record(ramp(-0.2, 0.3))
    glitchy.q[20, 0], glitchy.qd[30, 2] = 6.0, 20.0  # a 6 rad reading, a 20 rad/s one: one sample each
    expected, _ = propose_limits([clean])
    limits, reasons = propose_limits([glitchy])
    assert limits == expected
    assert reasons[0].startswith("dropped 2 isolated spike(s)")
    assert "ep at 1.00 s: q boom 6.000" in reasons[0] and "ep at 1.50 s: qd bucket 20.000" in reasons[0]
    steep = record(ramp(-0.2, 0.3))
    steep.q[20:, 0] += 1.0  # a step that stays is motion (or a fault the guard judges), not a spike
    assert not log_stats([steep]).spikes


def test_a_jump_no_machine_makes_refuses_the_proposal_and_says_where():
    long_glitch = record(ramp(-0.2, 0.3))
    long_glitch.q[20:22, 0] = 6.0  # two samples: no spike, but a jump there and back
    with pytest.raises(EfficientTrackError, match=r"2 jump\(s\) .*ep at 1\.00 s: q boom moved at 120\.200 rad/s, 601×"):
        propose_limits([long_glitch])
    offset = record(ramp(-0.2, 0.3), name="offset")
    offset.q_ref[30:, 3] += 0.5  # a reference that steps by 0.5 rad and stays there
    with pytest.raises(EfficientTrackError, match=r"1 jump\(s\).*offset at 1\.50 s: q_ref swing moved at 10\.\d+ rad/s"):
        propose_limits([offset])
    fast = record(ramp(-0.2, 0.3), qd=np.full((51, 4), 0.1))
    fast.qd[10:13, 1] = 5.0  # three samples of 5 rad/s, 50× what the arm's sensor ever reads
    with pytest.raises(EfficientTrackError, match="qd arm moved at 5.000 rad/s"):
        propose_limits([fast])
    slow = record(ramp(-0.2, 0.3))
    slow.q[20:22, 0] += 0.04  # 0.8 rad/s: below the floor, however still the rest is
    assert not log_stats([slow]).jumps


def test_the_range_stays_within_two_pi():
    q = ramp(-0.2, 0.3)
    q[:, 0] = np.linspace(6.0, 6.25, len(q))
    limits, reasons = propose_limits([record(q)], margin=0.1)
    assert limits.q_max[0] == MAX_ABS_ANGLE and limits.q_min[0] == pytest.approx(5.9)
    assert "clipped to ±2π at the boom" in reasons[1]


def test_max_speed_is_the_factor_times_the_top_speed_seen_qd_or_the_move():
    q = ramp(-0.2, 0.3)  # moves 0.01 rad a step: 0.2 rad/s
    qd = np.full_like(q, 0.1)
    qd[5] = [1.0, -1.5, 0.1, 0.1]  # the sensors' rate beats the move at the boom and the arm
    limits, reasons = propose_limits([record(q, qd)], speed_factor=2.0)
    np.testing.assert_allclose(limits.max_speed, [2.0, 3.0, 0.4, 0.4], atol=1e-4)
    assert all(s >= r for s, r in zip(limits.max_speed, [2.0, 3.0, 0.4, 0.4], strict=True))
    assert reasons[3].startswith("max_speed: [2.0000, 3.0000, 0.4000, 0.4000] rad/s = factor 2 × top speed seen")
    limits, _ = propose_limits([record(q, qd)], speed_factor=3.0)
    np.testing.assert_allclose(limits.max_speed, [3.0, 4.5, 0.6, 0.6], atol=1e-4)


def test_a_move_between_two_episodes_is_not_a_move():
    first, second = record(ramp(-0.2, -0.1)), record(ramp(0.2, 0.3))  # 0.3 rad apart, never in one step
    np.testing.assert_allclose(log_stats([first, second]).top_move, 0.1 / 50 / DT)


def test_stale_steps_is_twice_the_longest_repeat_run_plus_one():
    assert propose_limits([record(ramp(-0.2, 0.3))])[0].stale_steps == 2  # noisy sensors: never a repeat
    q = ramp(-0.2, 0.3)
    q[20:24] = q[20]  # 3 steps repeat step 20
    limits, reasons = propose_limits([record(q), record(ramp(0, 0.1))])
    assert limits.stale_steps == 8 and "longest run of bit-identical observations seen, 3 step(s)" in reasons[6]


def test_adjustments_seen_beyond_the_kept_bound_are_named():
    rec = record(ramp(-0.2, 0.3))
    rec.q_ref = rec.q_des + np.array([0.2, 0.0, 0.0, 0.0])
    limits, reasons = propose_limits([rec])
    assert limits.max_adjust == (0.15, 0.3, 0.3, 0.3)  # the XE75's, at most half of each range seen (±0.05 margin)
    assert "largest |q_ref − q_des| seen [0.2000, 0.0000, 0.0000, 0.0000] rad, beyond the bound at the boom" in reasons[4]


def test_the_proposal_holds_every_sample_of_its_logs():
    records = [make_record(steps=60, seed=i) for i in range(3)]
    limits, _ = propose_limits(records, margin=0.0)
    for rec in records:
        for name in ("q", "q_ref", "q_des"):
            assert not limits.outside(getattr(rec, name)).any(), name
        moves = np.abs(np.diff(rec.q, axis=0))
        assert np.all(moves <= np.asarray(limits.max_speed) * DT)


# --------------------------------------------------------------------------------------------- the swing


def test_the_swing_is_limited_on_its_wrapped_angle():
    q = ramp(-0.2, 0.3)
    q[:, SWING] = np.linspace(3.5, 4.0, len(q))  # beyond π: wrapped, −2.78 … −2.28 rad
    limits, reasons = propose_limits([record(q)], margin=0.05)
    assert limits.q_min[SWING] == pytest.approx(3.5 - 2 * math.pi - 0.05, abs=1e-4)
    assert limits.q_max[SWING] == pytest.approx(4.0 - 2 * math.pi + 0.05, abs=1e-4)
    assert reasons[2].startswith("swing: limited on its wrapped angle") and "never passing ±π" in reasons[2]
    assert not limits.outside(q).any()


def test_a_swing_passing_pi_is_unlimited():
    q = ramp(-0.2, 0.3)
    q[:, SWING] = np.linspace(3.0, 3.3, len(q))  # through π: wrapped, 3.0 … π, then −π … −2.98
    limits, reasons = propose_limits([record(q)], margin=0.05)
    assert (limits.q_min[SWING], limits.q_max[SWING]) == (-math.pi, math.pi)
    assert reasons[2].startswith("swing: unlimited [−π, π]: it passed ±π in the logs")


def test_a_swing_covering_nearly_the_full_circle_is_unlimited():
    q = ramp(-0.2, 0.3, steps=400)
    q[:, SWING] = np.linspace(-3.1, 3.1, len(q))  # never through π, but 0.08 rad short of the full circle
    limits, reasons = propose_limits([record(q)], margin=0.05)
    assert (limits.q_min[SWING], limits.q_max[SWING]) == (-math.pi, math.pi)
    assert "covers nearly the full circle" in reasons[2]
    q[:, SWING] = np.linspace(-2.9, 2.9, len(q))  # 0.48 rad short: stays limited
    limits, _ = propose_limits([record(q)], margin=0.05)
    assert limits.q_min[SWING] == pytest.approx(-2.95) and limits.q_max[SWING] == pytest.approx(2.95)


def test_bad_margins_and_flat_joints_are_refused_naming_them():
    rec = record(ramp(-0.2, 0.3))
    for margin in (-1.0, math.nan, 5.0):
        with pytest.raises(EfficientTrackError, match="margin"):
            propose_limits([rec], margin=margin)
    with pytest.raises(EfficientTrackError, match="speed_factor"):
        propose_limits([rec], speed_factor=0.5)
    q = ramp(-0.2, 0.3)
    q[:, 2] = 1.0
    with pytest.raises(EfficientTrackError, match="the bucket never moved in the logs and the margin is 0"):
        propose_limits([record(q)], margin=0.0)


# ---------------------------------------------------------------------------------------- command line


def test_from_logs_prints_why_and_writes_a_file_that_loads_as_proposed(tmp_path, monkeypatch, capsys):
    records = [record(ramp(-0.2, 0.3), name="a"), record(ramp(-0.1, 0.2), name="b")]
    save_records(records, tmp_path / "logs")
    out = tmp_path / "xe.yaml"
    code, stdout, err = run_main(
        ["limits", "--from-logs", tmp_path / "logs", "--out", out, "--margin", "0.1"], monkeypatch, capsys
    )
    assert code == 0, err
    limits, reasons = propose_limits(load_records(tmp_path / "logs"), margin=0.1)
    assert GuardLimits.load(out) == limits and limits.q_min[0] == pytest.approx(-0.3)
    lines = stdout.splitlines()
    assert lines[: len(reasons)] == reasons
    assert "boom    -17.19° (-0.3000 rad)" in stdout  # the per-joint report, degrees and radians
    text = out.read_text()
    assert f"efficienttrack limits --from-logs {tmp_path / 'logs'} --out {out} --margin 0.1 --speed-factor 2" in text
    assert "Logs: 2 episode(s), 102 steps" in text and "#   q_min: [-0.3000" in text
    code, _, err = run_main(["limits", "--from-logs", tmp_path / "logs", "--out", tmp_path / "xe.json"], monkeypatch, capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "xe.json").read_text())["q_min"][0] == pytest.approx(-0.25)


def test_from_logs_with_a_jump_writes_nothing_and_says_where(tmp_path, monkeypatch, capsys):
    glitchy = record(ramp(-0.2, 0.3), name="ep_07")
    glitchy.q[20:22, 0] = 6.0
    save_records([glitchy], tmp_path / "logs")
    code, _, err = run_main(["limits", "--from-logs", tmp_path / "logs", "--out", tmp_path / "xe.yaml"], monkeypatch, capsys)
    assert code != 0 and "ep_07 at 1.00 s: q boom moved at 120.200 rad/s" in err and "Traceback" not in err
    assert not (tmp_path / "xe.yaml").exists()


def test_check_prints_a_good_file_per_joint_in_degrees_and_radians(tmp_path, monkeypatch, capsys):
    path = tmp_path / "mine.yaml"
    path.write_text("q_min: [-0.5, -1, -0.5, -1.5]\nq_max: [0.6, 0.5, 2.3, 1.5]\nstale_steps: 4\n")
    code, stdout, err = run_main(["limits", "--check", path], monkeypatch, capsys)
    assert code == 0, err
    assert f"{path}: valid limits" in stdout
    assert "boom    -28.65° (-0.5000 rad)   34.38° (0.6000 rad)" in stdout
    assert "limited to [-85.94°, 85.94°]" in stdout and "stale_steps: 4 repeated" in stdout
    assert "left out: max_adjust, max_adjust_rate, max_speed" in stdout
    code, stdout, _ = run_main(["limits", "--check", "xe75"], monkeypatch, capsys)
    assert code == 0 and "xe75 (" in stdout and "swing: compared wrapped to (−180°, 180°]; unlimited" in stdout


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("q_min: [1, -1, -1, -1]\nq_max: [0, 1, 1, 1]\n", "q_min"),
        ("max_speed: [1, 2, 3]\n", "max_speed"),
        ("max_adjust: [0.1, .nan, 0.1, 0.1]\n", "max_adjust"),
        ("speed: 3\n", "speed"),
    ],
)
def test_check_refuses_a_bad_file_in_one_line_naming_file_and_field(tmp_path, monkeypatch, capsys, text, field):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    code, _, err = run_main(["limits", "--check", path], monkeypatch, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and str(path) in lines[0] and field in lines[0], err


def test_the_command_refuses_unclear_requests(tmp_path, monkeypatch, capsys):
    for argv, message in [
        (["limits"], "nothing to do"),
        (["limits", tmp_path], "episode logs need --from-logs"),
        (["limits", "--from-logs", "--out", tmp_path / "a.yaml"], "give one or more episode files"),
        (["limits", "--from-logs", tmp_path], "give --out FILE"),
        (["limits", "--check", "xe75", "--from-logs", tmp_path], "give --check FILE [--out FILE], or --from-logs"),
        (["limits", "--check", tmp_path / "nosuch.yaml"], "neither a limits preset (xe75) nor an existing"),
    ]:
        code, _, err = run_main(argv, monkeypatch, capsys)
        assert code == 2 and message in err, (argv, err)


# ------------------------------------------------------------------------------------ the shipped file


def test_limits_xe75_is_the_built_in_systems_own():
    built_in = load_system("xe75").limits
    assert GuardLimits.load("xe75") == built_in
    assert GuardLimits.load(limits_preset_path("xe75")) == built_in
    assert SystemSpec(limits="xe75").open().limits == built_in
    assert SystemSpec(system="paper", limits="xe75").open().limits == built_in  # every field given: the paper's replaced
    assert limits_preset_path("xe75").suffix == ".json"  # packaged by pyproject's systems/presets/*.json
    with pytest.raises(EfficientTrackError, match=r"limits 'xe76': neither a limits preset \(xe75\) nor an existing"):
        SystemSpec(limits="xe76").open()


# ------------------------------------------------------------------------------------------- real logs


@pytest.mark.skipif(not PD_LOGS.is_dir(), reason=f"the real XE75 logs not found at {PD_LOGS}")
def test_on_the_real_xe75_pd_logs_the_documented_numbers():
    """Also: no sample of the real logs is taken for a spike or a jump (in this test, as the logs take a second to read)."""
    records = load_records(PD_LOGS)
    stats = log_stats(records)
    assert stats.spikes == () and stats.jumps == ()
    limits, reasons = propose_limits(records)
    assert (len(records), sum(map(len, records))) == (400, 176720)
    np.testing.assert_allclose(limits.q_min, [-0.5148, -1.0693, -0.4284, -1.2505])
    np.testing.assert_allclose(limits.q_max, [0.5517, 0.4460, 2.3272, 1.7510])
    np.testing.assert_allclose(limits.max_speed, [1.2357, 1.6337, 6.8836, 1.6452])
    assert limits.stale_steps == 2 and reasons[2].startswith("swing: limited")
    shipped = GuardLimits.load("xe75")
    for rec in records[::20]:  # both hold the logs
        for lim in (limits, shipped):
            assert not lim.outside(np.concatenate([rec.q, rec.q_ref, rec.q_des])).any()
            assert np.all(np.abs(np.diff(rec.q, axis=0)) <= np.asarray(lim.max_speed) * DT)


# ---------------------------------------------------------------------------------------- ros2_control's joint_limits.yaml

ROS2_FILE = """\
# a MoveIt / ros2_control joint_limits.yaml
default_velocity_scaling_factor: 0.1
joint_limits:
  boom_joint:
    has_position_limits: true
    min_position: -0.55
    max_position: 0.65
    has_velocity_limits: true
    max_velocity: 0.8
    has_acceleration_limits: false
    max_acceleration: 0
  arm_joint: {has_position_limits: true, min_position: -1.1, max_position: 0.5, has_velocity_limits: true, max_velocity: 1.2}
  bucket_joint: {has_position_limits: true, min_position: -0.5, max_position: 2.3, has_velocity_limits: true,
                 max_velocity: 3.5}
  swing_joint: {has_position_limits: false, angle_wraparound: true, has_velocity_limits: true, max_velocity: 1.0}
  blade_joint: {has_position_limits: true, min_position: 0, max_position: 0.3}
stale_steps: 4
"""


def test_a_ros2_control_joint_limits_file_reads_as_limits_and_round_trips(tmp_path):
    path = tmp_path / "joint_limits.yaml"
    path.write_text(ROS2_FILE)
    limits = GuardLimits.load(path)
    assert limits.q_min == (-0.55, -1.1, -0.5, -math.pi) and limits.q_max == (0.65, 0.5, 2.3, math.pi)
    assert limits.max_speed == (0.8, 1.2, 3.5, 1.0) and limits.stale_steps == 4  # the guard's own field beside
    names = ["boom_joint", "arm_joint", "bucket_joint", "swing_joint"]
    write_limits(limits, tmp_path / "again.yaml", ros2_names=names)
    assert GuardLimits.load(tmp_path / "again.yaml") == limits
    written = yaml.safe_load((tmp_path / "again.yaml").read_text())
    assert list(written["joint_limits"]) == names and written["joint_limits"]["swing_joint"]["angle_wraparound"] is True
    assert written["joint_limits"]["boom_joint"] == {
        "has_position_limits": True, "min_position": -0.55, "max_position": 0.65,
        "has_velocity_limits": True, "max_velocity": 0.8, "has_acceleration_limits": False,
    }  # fmt: skip
    write_limits(limits, tmp_path / "again.json", ros2_names=names)
    assert GuardLimits.load(tmp_path / "again.json") == limits


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t: t.replace("swing_joint", "slew_joint"), "no joint of joint_limits names the swing"),
        (lambda t: t.replace("blade_joint", "boom_extra"), "joints 'boom_joint' and 'boom_extra' both name the boom"),
        (lambda t: t.replace("blade_joint", "boom_swing"), "joint 'boom_swing' names boom and swing"),
        (lambda t: t.replace("max_acceleration: 0", "max_accel: 0"), "joint_limits.boom_joint: unknown key"),
        (lambda t: t.replace("max_velocity: 0.8", "max_velocity: fast"), "boom_joint: max_velocity must be a finite"),
        (lambda t: t.replace("stale_steps: 4", "stale_step: 4"), "unknown top-level key(s) stale_step"),
        (lambda t: t.replace("min_position: -0.55", "min_position: 0.9"), "boom needs −2π ≤ q_min < q_max"),
        (lambda t: t.replace("max_velocity: 1.0}", "}").replace("has_velocity_limits: true, }", "}"), "velocity limits"),
    ],
)
def test_a_ros2_file_that_does_not_fit_is_refused_naming_the_joint(tmp_path, change, message):
    path = tmp_path / "joint_limits.yaml"
    path.write_text(change(ROS2_FILE))
    with pytest.raises(EfficientTrackError, match=re.escape(message)) as info:
        GuardLimits.load(path)
    assert str(path) in str(info.value)


def test_the_command_converts_limits_to_ros2_and_checks_a_ros2_file(tmp_path, monkeypatch, capsys):
    out = tmp_path / "joint_limits.yaml"
    names = "boom_joint,arm_joint,bucket_joint,swing_joint"
    code, stdout, err = run_main(["limits", "--check", "xe75", "--out", out, "--ros2", "--joint-names", names],
                                 monkeypatch, capsys)  # fmt: skip
    assert code == 0, err
    assert "(ros2_control joint_limits.yaml)" in stdout and GuardLimits.load(out) == GuardLimits.load("xe75")
    code, stdout, err = run_main(["limits", "--check", out], monkeypatch, capsys)
    assert code == 0 and f"{out}: valid limits" in stdout and "left out" not in stdout, err
    code, _, err = run_main(["limits", "--check", "xe75", "--out", out, "--ros2", "--joint-names", "a,b"], monkeypatch, capsys)
    assert code == 2 and "give four, naming boom, arm, bucket and swing" in err
    code, _, err = run_main(["limits", "--check", "xe75", "--ros2"], monkeypatch, capsys)
    assert code == 2 and "--ros2 and --joint-names say how --out is written; give --out FILE" in err
    code, _, err = run_main(["limits", "--check", "xe75", "--out", out, "--joint-names", names], monkeypatch, capsys)
    assert code == 2 and "give --ros2 too" in err
