import json
from pathlib import Path

import numpy as np
import pytest

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import load_records
from efficienttrack.systems.pd import XE75_PD, ClosedLoop, PDGains

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DT = 0.05
SIGN = np.array(XE75_PD.sign)


class Integrator:
    """Pure integrator plant q̇ = k·u per joint (k in rad/s per PWM), batched or single."""

    dt = DT

    def __init__(self, k, batched):
        self.k = np.asarray(k, dtype=float)
        self.batched = batched

    def reset(self, q0):
        q0 = np.asarray(q0, dtype=float)
        assert q0.shape[-1] == 4 and (q0.ndim == 2) == self.batched
        self.q = q0.copy()
        return np.concatenate([self.q, np.zeros_like(self.q)], axis=-1)

    def step(self, u):
        qd = self.k * np.asarray(u)
        self.q = self.q + qd * self.dt
        return np.concatenate([self.q, qd], axis=-1)


# ------------------------------------------------------------------------------------- the real machine


def test_xe75_pd_reproduces_the_logged_pwm():
    folder = DATA / "xe75" / "pd_clean_train"
    if not folder.is_dir():
        pytest.skip(f"shared XE75 data not found at {folder}")
    logged, replayed, first = [], [], []
    for record in load_records(folder):
        e = wrap(record.q_ref - record.q)  # (T, 4) rad
        e_prev = np.vstack([e[:1], e[:-1]])  # e[−1] = e[0]
        logged.append(record.u)
        replayed.append(XE75_PD.command(e, e_prev))
        first.append(np.arange(len(record)) == 0)
    u, u_hat, first = np.vstack(logged), np.vstack(replayed), np.concatenate(first)
    r2 = 1 - np.sum((u - u_hat) ** 2, axis=0) / np.sum((u - u.mean(axis=0)) ** 2, axis=0)
    assert u.shape == (17672, 4)
    assert np.all(r2 >= 0.997), r2
    # from t = 1 on the law is exact (README: max |residual| 1e-11 PWM)
    assert np.max(np.abs(u - u_hat)[~first]) < 1e-6
    assert np.mean(np.abs(u) >= 1000, axis=0)[0] == pytest.approx(0.034, abs=0.001)  # boom saturation 3.4 %


# ------------------------------------------------------------------------------- closed-form responses


def test_p_control_of_an_integrator_decays_geometrically():
    k0 = 1e-3
    gains = PDGains(kp=XE75_PD.kp, kd=(0.0,) * 4, sign=XE75_PD.sign, c=0.0, u_max=1e9)
    system = ClosedLoop(Integrator(k0 * SIGN, batched=False), gains)  # k·s = k0 > 0: stable
    q0, r = np.array([0.1, -0.2, 0.3, -0.4]), np.array([0.15, -0.1, 0.2, 0.0])
    system.reset(q0)
    a = DT * k0 * np.array(XE75_PD.kp)  # e[t+1] = (1 − a)·e[t]
    for step in range(1, 11):
        obs = system.step(r)
        np.testing.assert_allclose(obs[:4], r - (1 - a) ** step * (r - q0), atol=1e-12, rtol=0)
        np.testing.assert_allclose(obs[4:], k0 * np.array(XE75_PD.kp) * (1 - a) ** (step - 1) * (r - q0), atol=1e-12, rtol=0)


def test_xe75_pd_first_steps_by_hand():
    k = 1e-4 * SIGN
    system = ClosedLoop(Integrator(k, batched=False))
    q0, r = np.array([0.0, 0.1, 0.2, 0.3]), np.array([0.05, 0.05, 0.25, 0.2])
    kp, kd, c = np.array(XE75_PD.kp), np.array(XE75_PD.kd), 400.0
    system.reset(q0)
    assert system.last_command is None

    e0 = r - q0
    u0 = SIGN * (kp * e0 + c * np.sign(e0))  # first step: e[−1] = e[0], no derivative kick
    q1 = q0 + DT * k * u0
    np.testing.assert_allclose(system.step(r)[:4], q1, atol=1e-15)
    np.testing.assert_allclose(system.last_command, u0, atol=1e-9)

    e1 = r - q1
    u1 = SIGN * (kp * e1 + kd * (e1 - e0) + c * np.sign(e1))
    np.testing.assert_allclose(system.step(r)[:4], q1 + DT * k * u1, atol=1e-15)
    np.testing.assert_allclose(system.last_command, u1, atol=1e-9)
    assert np.all(np.abs(u1) < 1000)

    # a large error saturates at ±1000 PWM
    system.reset(q0)
    system.step(q0 + np.array([1.0, -1.0, 1.0, -2.0]))  # swing: 500·2 + 400 = 1400 > 1000
    np.testing.assert_array_equal(system.last_command, SIGN * np.array([1000.0, -1000.0, 1000.0, -1000.0]))


def test_batched_closed_loop_equals_single_loops():
    rng = np.random.default_rng(7)
    n, steps = 5, 30
    k = 2e-4 * SIGN
    q0 = rng.uniform(-0.5, 0.5, (n, 4))
    q_ref = q0 + np.cumsum(rng.normal(0, 0.02, (steps, n, 4)), axis=0)  # (T, N, 4) rad

    batched = ClosedLoop(Integrator(k, batched=True))
    assert batched.batched
    obs_batched = [batched.reset(q0)] + [batched.step(q_ref[t]) for t in range(steps)]
    obs_batched = np.stack(obs_batched)  # (T+1, N, 8)

    for i in range(n):
        single = ClosedLoop(Integrator(k, batched=False))
        assert not single.batched
        obs = np.stack([single.reset(q0[i])] + [single.step(q_ref[t, i]) for t in range(steps)])
        np.testing.assert_allclose(obs, obs_batched[:, i], atol=1e-12, rtol=0)
    assert np.abs(obs_batched[-1, :, :4] - q_ref[-1]).max() < 0.2  # it tracks


def test_pd_step_wraps_the_error_and_takes_the_first_step_without_derivative_kick():
    q_ref, q = np.full(4, np.pi - 0.01), np.full(4, -np.pi + 0.01)  # 0.02 rad apart across ±π
    u, e = XE75_PD.step(q_ref, q, None)
    np.testing.assert_allclose(e, -0.02, atol=1e-12)
    np.testing.assert_array_equal(u, XE75_PD.command(e, e))
    u_next, _ = XE75_PD.step(q_ref, q, e_prev=np.zeros(4))
    np.testing.assert_array_equal(u_next, XE75_PD.command(e, np.zeros(4)))


# ------------------------------------------------------------------------------------- the gains file


def _gains_file(tmp_path, **changes):
    fields = {**XE75_PD.to_dict(), **changes}
    path = tmp_path / "gains.json"
    path.write_text(json.dumps(fields))
    return path


def test_a_gains_file_round_trips(tmp_path):
    assert PDGains.load(str(_gains_file(tmp_path))) == XE75_PD


@pytest.mark.parametrize(
    ("changes", "field", "problem"),
    [
        ({"u_max": -5}, "u_max", "> 0"),
        ({"u_max": 0}, "u_max", "> 0"),
        ({"u_max": "1000"}, "u_max", "one number"),
        ({"c": -1.0}, "c", "≥ 0"),
        ({"c": [1, 2, 3, 4]}, "c", "one number"),
        ({"kp": [float("nan"), 1, 1, 1]}, "kp", "4 numbers"),
        ({"kp": float("nan")}, "kp", "4 numbers"),
        ({"kp": "5000"}, "kp", "4 numbers"),
        ({"kp": [1, 2, 3]}, "kp", "4 numbers"),
        ({"kp": [[1, 2], [3, 4]]}, "kp", "4 numbers"),
        ({"kp": [1, 2, 3, True]}, "kp", "4 numbers"),
        ({"kd": [1, 2, 3, float("inf")]}, "kd", "4 numbers"),
        ({"kd": [1, 2, 3, -4]}, "kd", "≥ 0"),
        ({"sign": [1, 1, 1, 0.5]}, "sign", "−1 or 1"),
    ],
)
def test_a_bad_gains_file_is_refused_naming_the_file_and_field(tmp_path, changes, field, problem):
    path = _gains_file(tmp_path, **changes)
    with pytest.raises(EfficientTrackError, match=rf"{path}: PD gains: field '{field}'.*{problem}"):
        PDGains.load(str(path))


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("[1, 2]", "expected an object"),
        ('{"kp": [1, 1, 1, 1], "kd": [1, 1, 1, 1]}', "missing field.*sign"),
        ('{"kp": [1, 1, 1, 1], "kd": [1, 1, 1, 1], "sign": [1, 1, 1, 1], "ki": 3}', "unknown field.*ki"),
        ('{"kp": [1, 1, 1, 1], "kd": [1, 1, 1, 1], "sign": [1, 1, 1, 1], "c": 1e999}', "field 'c'"),
        ("{truncated", "cannot read the config .not valid JSON"),
        ('{"kp": [1, 1, 1, 1], "kd": [1, 1, 1, 1], "sign": [1, 1, 1, 1], "kp": [9, 9, 9, 9]}', "the key 'kp' is given twice"),
    ],
)
def test_a_malformed_gains_file_is_refused(tmp_path, text, problem):
    path = tmp_path / "gains.json"
    path.write_text(text)
    with pytest.raises(EfficientTrackError, match=problem):
        PDGains.load(str(path))


def test_gains_built_in_code_are_checked_too():
    with pytest.raises(EfficientTrackError, match="field 'u_max'"):
        PDGains(kp=XE75_PD.kp, kd=XE75_PD.kd, sign=XE75_PD.sign, u_max=float("nan"))
    assert PDGains(kp=[1, 2, 3, 4], kd=XE75_PD.kd, sign=XE75_PD.sign).kp == (1.0, 2.0, 3.0, 4.0)
