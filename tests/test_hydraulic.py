import json
import math

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.systems import check_system, load_plant, load_system
from efficienttrack.systems.hydraulic import (
    HydraulicExcavator,
    HydraulicParams,
    initial_state,
    preset_path,
    step,
    xe75_closed_loop,
    xe75_params,
    xe75_plant,
)

# A simple, fully known model: linear flow, no rest dead zone, no spool lag, fast actuator lag.
SIMPLE = HydraulicParams(
    delay=(3, 2, 4, 5),
    tau=(0.02, 0.02, 0.02, 0.02),
    dead_zone_pos=(400.0, 400.0, 400.0, 400.0),
    dead_zone_neg=(450.0, 450.0, 450.0, 450.0),
    v_max_pos=(0.2, 0.4, 1.0, 0.3),
    v_max_neg=(0.3, 0.3, 0.8, 0.3),
    payload_pos=(-0.5, 0.0, 0.0, 0.0),
    payload_neg=(0.2, 0.0, 0.0, 0.0),
    pump_coupling=((0.0, 0.5, 0.5, 0.5), (0.5, 0.0, 0.5, 0.5), (0.5, 0.5, 0.0, 0.5), (0.5, 0.5, 0.5, 0.0)),
    q_min=(-0.5, -1.0, -0.5, -math.pi),
    q_max=(0.6, 0.5, 2.3, math.pi),
    noise_q=(0.001, 0.001, 0.001, 0.001),
    noise_qd=(0.01, 0.01, 0.01, 0.01),
)


def run(params, q0, u_seq, **kw):
    plant = HydraulicExcavator(params, **kw)
    obs = [plant.reset(q0)]
    for u in u_seq:
        obs.append(plant.step(u))
    return np.array(obs)


def test_pwm_step_shows_the_delay_per_joint():
    u = np.full((12, 4), 800.0)
    obs = run(SIMPLE, np.zeros(4), u)
    for j, d in enumerate(SIMPLE.delay):
        assert np.all(obs[: d + 1, j] == 0.0), f"joint {j} moved before its delay of {d} steps"
        assert obs[d + 1, j] != 0.0
    # sign convention: positive PWM -> boom/arm/bucket smaller, swing larger
    assert np.all(obs[-1, :3] < 0) and obs[-1, 3] > 0


def test_pwm_inside_dead_zone_does_not_move():
    inside = np.tile([390.0, -440.0, 390.0, -440.0], (40, 1))
    obs = run(SIMPLE, np.full(4, 0.1), inside)
    np.testing.assert_allclose(obs[:, :4], 0.1, rtol=0, atol=1e-15)
    assert np.all(obs[:, 4:] == 0.0)
    outside = np.tile([420.0, -470.0, 420.0, -470.0], (40, 1))
    assert np.all(np.abs(run(SIMPLE, np.full(4, 0.1), outside)[-1, 4:]) > 1e-3)


def test_linear_flow_reaches_saturation_speed():
    obs = run(SIMPLE.replace(delay=(0, 0, 0, 0)), np.zeros(4), np.tile([1000.0, -1000.0, 700.0, 1000.0], (40, 1)))
    # full PWM: v_max slowed by the others' openings (3 joints fully open, the bucket half open)
    others = np.array([2.5, 2.5, 3.0, 2.5])
    share = 1.0 / (1.0 + 0.5 * others)
    np.testing.assert_allclose(obs[-1, 4:], np.array([-0.2, 0.3, -0.5, 0.3]) * share, rtol=1e-9)


def test_saturation_is_per_direction():
    early = SIMPLE.replace(delay=(0, 0, 0, 0), pwm_sat_neg=(700.0,) * 4)
    lowering = run(early, np.zeros(4), np.tile([-700.0, 0.0, 0.0, 0.0], (30, 1)))[-1, 4]
    raising = run(early, np.zeros(4), np.tile([700.0, 0.0, 0.0, 0.0], (30, 1)))[-1, 4]
    np.testing.assert_allclose([lowering, raising], [0.3, -0.2 * 0.5], rtol=1e-9)  # full vs half open


def test_two_joints_at_full_flow_move_slower_than_one_alone():
    alone = run(SIMPLE, np.zeros(4), np.tile([1000.0, 0.0, 0.0, 0.0], (30, 1)))
    both = run(SIMPLE, np.zeros(4), np.tile([1000.0, 1000.0, 0.0, 0.0], (30, 1)))
    np.testing.assert_allclose(alone[-1, 4], -0.2, rtol=1e-9)
    np.testing.assert_allclose(both[-1, 4], -0.2 / 1.5, rtol=1e-9)  # the open arm valve takes pump flow


def test_linkage_makes_speed_depend_on_the_angle():
    linked = SIMPLE.replace(delay=(0, 0, 0, 0), speed_q=(0.0, 0.0, 0.5, 0.0), speed_q2=(0.0, 0.0, 0.2, 0.0))
    middle = (SIMPLE.q_min[2] + SIMPLE.q_max[2]) / 2
    r = np.array([-0.5, 0.0, 0.5])
    speeds = [-run(linked, np.array([0.0, 0.0, middle + x, 0.0]), [[0.0, 0.0, 1000.0, 0.0]])[-1, 6] for x in r]
    first_step = 1.0 - np.exp(-0.05 / 0.02)  # of the actuator lag towards v_max_pos = 1 rad/s
    np.testing.assert_allclose(speeds, np.exp(0.5 * r + 0.2 * r**2) * first_step, rtol=1e-9)


def test_acceleration_is_capped():
    capped = SIMPLE.replace(delay=(0, 0, 0, 0), accel_max=(1.0, 1.0, 1.0, 1.0))
    obs = run(capped, np.zeros(4), np.tile([0.0, 0.0, 1000.0, 0.0], (8, 1)))
    np.testing.assert_allclose(np.diff(obs[:, 6]), -0.05, rtol=1e-9)  # 1 rad/s² · 0.05 s per step, not the lag's 0.92 rad/s
    assert np.abs(run(SIMPLE.replace(delay=(0, 0, 0, 0)), np.zeros(4), [[0.0, 0.0, 1000.0, 0.0]])[-1, 6]) > 0.9


def test_payload_slows_boom_raising_not_lowering():
    raise_u = np.tile([1000.0, 0.0, 0.0, 0.0], (30, 1))
    empty = run(SIMPLE, np.zeros(4), raise_u)[-1, 4]
    full = run(SIMPLE.replace(payload=1.0), np.zeros(4), raise_u)[-1, 4]
    np.testing.assert_allclose([empty, full], [-0.2, -0.1], rtol=1e-9)
    lower_empty = run(SIMPLE, np.zeros(4), -raise_u)[-1, 4]
    lower_full = run(SIMPLE.replace(payload=1.0), np.zeros(4), -raise_u)[-1, 4]
    assert lower_full > lower_empty > 0


def test_batched_equals_looped_exactly():
    rng = np.random.default_rng(0)
    params = xe75_params()
    q0 = rng.uniform(-0.3, 0.3, (5, 4))
    u = rng.uniform(-1000, 1000, (25, 5, 4))
    batched = run(params, q0, u)
    for i in range(5):
        single = run(params, q0[i], u[:, i])
        assert np.array_equal(batched[:, i], single)


def test_seed_makes_noisy_runs_identical():
    u = np.random.default_rng(1).uniform(-1000, 1000, (20, 3, 4))
    a = run(SIMPLE, np.zeros((3, 4)), u, sensor_noise=True, seed=7)
    b = run(SIMPLE, np.zeros((3, 4)), u, sensor_noise=True, seed=7)
    c = run(SIMPLE, np.zeros((3, 4)), u, sensor_noise=True, seed=8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.std(a[0, :, :4]) > 1e-4  # noise is on


def test_swing_wraps_at_pi():
    obs = run(SIMPLE.replace(delay=(0, 0, 0, 0)), np.array([0.0, 0.0, 0.0, 3.1]), np.tile([0, 0, 0, 1000.0], (20, 1)))
    swing = obs[:, 3]
    assert np.all(swing <= math.pi) and np.all(swing > -math.pi)
    assert -3.0 < swing[-1] < -2.8  # 3.1 rad + 20 steps at 0.3 rad/s crossed +π into negative angles
    assert np.all(np.abs(np.diff(np.unwrap(swing))) < 0.02)


def test_joint_limits_hold():
    obs = run(SIMPLE, np.zeros(4), np.tile([-1000.0, -1000.0, -1000.0, 0.0], (200, 1)))
    np.testing.assert_array_equal(obs[-1, :3], SIMPLE.q_max[:3])
    np.testing.assert_array_equal(obs[-1, 4:7], 0.0)
    obs = run(SIMPLE, np.zeros(4), np.tile([1000.0, 1000.0, 1000.0, 0.0], (200, 1)))
    np.testing.assert_array_equal(obs[-1, :3], SIMPLE.q_min[:3])


def test_spool_lag_filters_a_pwm_spike_but_not_a_held_command():
    lagged = SIMPLE.replace(delay=(0, 0, 0, 0), tau_spool=(0.1, 0.1, 0.1, 0.1))
    spike = np.zeros((20, 4))
    spike[0] = 1000.0
    peak_lagged = np.abs(run(lagged, np.zeros(4), spike)[:, 4:]).max(axis=0)
    peak_direct = np.abs(run(SIMPLE.replace(delay=(0, 0, 0, 0)), np.zeros(4), spike)[:, 4:]).max(axis=0)
    assert np.all(peak_lagged < 0.5 * peak_direct)
    held = np.tile([1000.0, 0.0, 0.0, 0.0], (30, 1))
    np.testing.assert_allclose(run(lagged, np.zeros(4), held)[-1, 4], -0.2, rtol=1e-5)


def test_reset_with_logged_history_continues_the_delay_line_and_spool():
    rng = np.random.default_rng(2)
    params = SIMPLE.replace(tau_spool=(0.03, 0.05, 0.1, 0.2))
    u = rng.uniform(-1000, 1000, (30, 2, 4))
    full = run(params, np.zeros((2, 4)), u)
    state = initial_state(np.zeros((2, 4)), params)
    for k in range(10):
        state = step(state, u[k], params)
    plant = HydraulicExcavator(params)
    plant.reset(state.q, qd0=state.qd, u_past=u[:10])
    rest = np.array([plant.step(x) for x in u[10:]])
    np.testing.assert_allclose(rest, full[11:], atol=1e-12)


def test_shapes_and_errors():
    plant = xe75_plant()
    assert plant.reset(np.zeros(4)).shape == (8,)
    assert plant.step(np.zeros(4)).shape == (8,)
    assert plant.reset(np.zeros((3, 4))).shape == (3, 8)
    assert plant.step(np.zeros((3, 4))).shape == (3, 8)
    with pytest.raises(EfficientTrackError):
        plant.step(np.zeros((2, 4)))
    with pytest.raises(EfficientTrackError):
        plant.reset(np.zeros(3))
    with pytest.raises(EfficientTrackError):
        HydraulicExcavator(SIMPLE).step(np.zeros(4))


def test_builtin_system_and_preset_files(tmp_path):
    check_system(load_system("xe75"))
    assert load_plant("xe75").batched and load_system("xe75", payload=0.5).batched
    assert xe75_closed_loop().plant.params == xe75_params()
    values = json.loads(preset_path().read_text())
    assert HydraulicParams.from_dict(values) == xe75_params()
    own = tmp_path / "mine.json"
    own.write_text(json.dumps({**values, "v_max_pos": [0.1, 0.1, 0.1, 0.1]}))
    assert xe75_plant(params_file=str(own)).params.v_max_pos == (0.1, 0.1, 0.1, 0.1)
    own.write_text(json.dumps({**values, "tau": [0.1, 0.1]}))
    with pytest.raises(EfficientTrackError, match="tau"):
        xe75_plant(params_file=str(own))
    own.write_text(json.dumps({k: v for k, v in values.items() if k != "tau_brake"}))
    with pytest.raises(EfficientTrackError, match="lacks parameter.*tau_brake"):
        xe75_plant(params_file=str(own))
    own.write_text(json.dumps({**values, "taux": 1}))
    with pytest.raises(EfficientTrackError, match="taux"):
        xe75_plant(params_file=str(own))
    with pytest.raises(EfficientTrackError, match="payload"):
        xe75_plant(payload=1.5)
