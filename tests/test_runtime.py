import hashlib
import math

import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT
from efficienttrack.data.dataset import Sequences
from efficienttrack.deploy.episodes import Guard
from efficienttrack.deploy.guard import MAX_GAP, GuardedRuntime
from efficienttrack.deploy.runtime import Runtime, track
from efficienttrack.learn.settings import PolicyConfig
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits
from efficienttrack.systems.protocol import BatchedSystem
from toy_system import make, sine_refs

MAX_ADJUST = (0.15, 0.30, 0.40, 0.40)


class LinearPolicy(torch.nn.Module):
    """Stand-in with the AdjustmentPolicy interface: a seeded linear map of every input, tanh-bounded."""

    def __init__(self, horizon=3, seed=0):
        super().__init__()
        self.cfg = PolicyConfig(horizon=horizon, max_adjust=MAX_ADJUST)
        torch.manual_seed(seed)
        self.lin = torch.nn.Linear(self.cfg.in_dim, 4)

    def forward(self, obs_hist, qref_hist, qdes_future):
        x = torch.cat([obs_hist.flatten(1), qref_hist.flatten(1), qdes_future.flatten(1)], dim=1)
        return torch.tanh(self.lin(x)) * torch.tensor(self.cfg.max_adjust)


class BrokenPolicy(torch.nn.Module):
    """Returns NaN for machine 0 at every 3rd call and 2× the bound for machine 1 at every 5th call."""

    def __init__(self):
        super().__init__()
        self.cfg = PolicyConfig(horizon=2, max_adjust=MAX_ADJUST)
        self.calls = 0
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def forward(self, obs_hist, qref_hist, qdes_future):
        a = torch.full((len(obs_hist), 4), 0.01)
        if self.calls % 3 == 0:
            a[0, 1] = float("nan")
        if self.calls % 5 == 0:
            a[1] = 2 * torch.tensor(MAX_ADJUST)
        self.calls += 1
        return a


@pytest.fixture
def refs():
    return sine_refs([50, 41, 66], seed=1)


def test_pd_alone_sends_the_desired_reference(refs):
    records = track(BatchedSystem(make()), None, refs, progress=False)
    assert [len(r) for r in records] == [49, 40, 65]
    for ref, record in zip(refs, records, strict=True):
        np.testing.assert_array_equal(record.q_ref, ref.q[1:])
        np.testing.assert_array_equal(record.q_des, ref.q[1:])
        assert record.meta == {"fallbacks": 0, "guard": {}, "name": ref.name, "method": "pd"}


def test_guard_falls_back_to_raw_reference_and_counts(refs):
    records = track(BatchedSystem(make()), BrokenPolicy(), refs[:2], progress=False)
    steps = np.arange(len(records[0]))
    nan_steps = steps % 3 == 0
    d0 = records[0].q_ref - records[0].q_des
    np.testing.assert_array_equal(d0[nan_steps], 0.0)
    np.testing.assert_allclose(d0[~nan_steps], 0.01, atol=1e-7)
    assert records[0].meta["fallbacks"] == nan_steps.sum() == 17
    steps1 = np.arange(len(records[1]))
    big = steps1 % 5 == 0
    d1 = records[1].q_ref - records[1].q_des
    np.testing.assert_array_equal(d1[big], 0.0)
    np.testing.assert_allclose(d1[~big], 0.01, atol=1e-7)
    assert records[1].meta["fallbacks"] == big.sum() == 8


def test_runtime_step_reports_fallback_and_lifecycle():
    runtime = Runtime(BrokenPolicy(), limits=None)
    with pytest.raises(EfficientTrackError, match="before start"):
        runtime.step(np.zeros((2, 8)), np.zeros((2, 2, 4)))
    with runtime:
        runtime.start(np.zeros((2, 8)))
        sent = runtime.step(np.zeros((2, 8)), np.full((2, 2, 4), 0.5))
        assert sent.fallback.tolist() == [True, True]
        np.testing.assert_array_equal(sent.q_ref, 0.5)
        sent = runtime.step(np.zeros((2, 8)), np.full((2, 2, 4), 0.5))
        assert sent.fallback.tolist() == [False, False]
        np.testing.assert_allclose(sent.adjustment, 0.01, atol=1e-7)
        assert runtime.fallbacks.tolist() == [1, 1] and runtime.steps == 2
    assert not runtime.running


def test_runtime_refuses_non_finite_inputs_before_sending():
    runtime = Runtime(BrokenPolicy(), device="auto", limits=None)
    runtime.start(np.zeros((1, 8)))
    with pytest.raises(EfficientTrackError, match="non-finite"):
        runtime.step(np.zeros((1, 8)), np.full((1, 2, 4), np.nan))
    assert runtime.steps == 0


def test_runtime_keeps_the_policy_lengths_and_refuses_too_few_desired_positions():
    runtime = Runtime(LinearPolicy(horizon=3), limits=None)
    assert (runtime.history_length, runtime.future_length) == (3, 3)
    assert (Runtime(None, limits=None).history_length, Runtime(None, limits=None).future_length) == (1, 1)
    runtime.start(np.zeros((1, 8)))
    with pytest.raises(EfficientTrackError, match="needs 3 future desired positions, got 2"):
        runtime.step(np.zeros((1, 8)), np.zeros((1, 2, 4)))


def test_runtime_equals_offline_policy_on_the_log(refs):
    """Alg. 2 vs offline: the policy applied to the training windows of the recorded log gives the logged adjustments."""
    pi = LinearPolicy(horizon=3)
    records = track(BatchedSystem(make()), pi, refs, progress=False)
    assert sum(r.meta["fallbacks"] for r in records) == 0
    for record in records:
        seqs = Sequences([record], history=pi.cfg.history_length, future=pi.cfg.future_length)
        w = seqs.window(seqs.starts(0), horizon=0, desired=pi.cfg.future_length)
        with torch.no_grad():
            offline = pi(w.obs_hist, w.qref_hist, w.qdes_future).double().numpy()
        logged = record.q_ref - record.q_des
        assert np.abs(logged).max() > 0.01  # the policy really adjusts
        np.testing.assert_allclose(offline, logged, atol=2e-6)


def test_batched_and_unbatched_tracking_agree(refs):
    pi = LinearPolicy(horizon=2, seed=3)
    batched = track(BatchedSystem(make(batched=True)), pi, refs, progress=False)
    single = track(BatchedSystem(make(batched=False)), pi, refs, progress=False)
    for a, b in zip(batched, single, strict=True):
        np.testing.assert_allclose(a.q, b.q, atol=1e-6)
        np.testing.assert_allclose(a.q_ref, b.q_ref, atol=1e-6)


def test_a_runtime_needs_limits_or_says_it_goes_without():
    with pytest.raises(TypeError, match="limits"):
        Runtime(LinearPolicy(horizon=3))  # a forgotten argument never means "anything within ±2π"
    assert Runtime(None, limits=None).limits == DEFAULT_LIMITS


# ------------------------------------------------------------------------------------- time stamps, dropped samples


def _obs(q, n=1):
    obs = np.zeros((n, 8))
    obs[:, :4] = q
    return obs


def test_a_gap_of_dropped_samples_falls_back_and_starts_the_histories_afresh():
    runtime = Runtime(LinearPolicy(horizon=3), limits=None)  # max_speed 2π rad/s: 0.31 rad in one period
    q_des = np.full((1, 3, 4), 0.25)
    runtime.start(_obs(0.0), t=10.0)
    for k in range(1, 4):
        assert not runtime.step(_obs(0.01 * k), q_des, t=10.0 + k * DT).fallback[0]
    jumped = _obs(0.03 + 0.2)  # 5 periods without a call, then the position 0.2 rad on
    sent = runtime.step(jumped, q_des, t=10.0 + 9 * DT)
    assert sent.fallback[0] and sent.guard[0] == Guard.OBS_STALE
    np.testing.assert_array_equal(sent.adjustment, 0.0)
    np.testing.assert_array_equal(sent.q_ref, q_des[:, 0])
    # the histories start afresh from the observation after the gap, as at a start: no jump inside them
    np.testing.assert_array_equal(runtime._history.obs, np.repeat(jumped[:, None], 3, axis=1))
    np.testing.assert_array_equal(runtime._history.q_ref[:, :2], np.repeat(jumped[:, None, :4], 2, axis=1))
    np.testing.assert_array_equal(runtime._history.q_ref[:, 2], sent.q_ref)
    after = runtime.step(_obs(0.24), q_des, t=10.0 + 10 * DT)  # the next period: the policy again, from a = 0
    assert not after.fallback[0] and np.all(np.abs(after.adjustment) <= np.asarray(DEFAULT_LIMITS.max_adjust_rate))
    assert runtime.counts["obs_stale"].tolist() == [1] and runtime.fallbacks.tolist() == [1]
    # without time stamps each call is one period: the jump is within max_speed, but not what the velocities (0) allow
    unstamped = Runtime(LinearPolicy(horizon=3), limits=None)
    unstamped.start(_obs(0.0))
    for k in range(1, 4):
        unstamped.step(_obs(0.01 * k), q_des)
    sent = unstamped.step(jumped, q_des)
    assert sent.fallback[0] and sent.guard[0] == Guard.OBS_JUMP
    np.testing.assert_array_equal(unstamped._history.obs, np.repeat(jumped[:, None], 3, axis=1))  # afresh, as a gap


def test_a_gap_up_to_max_gap_periods_is_not_one():
    runtime = Runtime(None, limits=None)
    runtime.start(_obs(0.0), t=0.0)
    assert runtime.step(_obs(0.0), np.zeros((1, 1, 4)), t=0.95 * MAX_GAP * DT).guard[0] == 0  # late, none dropped
    assert runtime.step(_obs(0.0), np.zeros((1, 1, 4)), t=(2 * MAX_GAP + 0.01) * DT).guard[0] == Guard.OBS_STALE
    strict = Runtime(None, limits=None, max_gap=1.5)
    strict.start(_obs(0.0), t=0.0)
    assert strict.step(_obs(0.0), np.zeros((1, 1, 4)), t=1.6 * DT).guard[0] == Guard.OBS_STALE


def test_the_jump_check_allows_the_real_time_since_the_last_observation():
    limits = GuardLimits(max_speed=(1.0,) * 4)  # 0.05 rad per period
    runtime = Runtime(None, limits=limits)
    runtime.start(_obs(0.0), t=0.0)
    assert runtime.step(_obs(0.07), np.zeros((1, 1, 4)), t=1.5 * DT).guard[0] == 0  # 0.07 rad in 1.5 periods
    assert runtime.step(_obs(0.10), np.zeros((1, 1, 4)), t=2.0 * DT).guard[0] == Guard.OBS_JUMP  # 0.03 in half a period
    unstamped = Runtime(None, limits=limits)
    unstamped.start(_obs(0.0))
    assert unstamped.step(_obs(0.07), np.zeros((1, 1, 4))).guard[0] == Guard.OBS_JUMP  # one period: too far


def test_time_stamps_must_be_finite_and_increase():
    runtime = Runtime(None, limits=None)
    with pytest.raises(EfficientTrackError, match=r"runtime: start needs t as a finite number of seconds or None, got nan"):
        runtime.start(_obs(0.0), t=math.nan)
    runtime.start(_obs(0.0), t=5.0)
    for t in (5.0, 4.9):
        with pytest.raises(EfficientTrackError, match=r"not after the last call's 5.0 s; t must come from a monotonic clock"):
            runtime.step(_obs(0.0), np.zeros((1, 1, 4)), t=t)
    with pytest.raises(EfficientTrackError, match=r"step needs t as a finite number"):
        runtime.step(_obs(0.0), np.zeros((1, 1, 4)), t="5.1")
    assert runtime.steps == 0
    runtime.step(_obs(0.0), np.zeros((1, 1, 4)))  # no stamp: one period; the next stamp counts one period too
    assert runtime.step(_obs(0.0), np.zeros((1, 1, 4)), t=100.0).guard[0] == 0
    for bad in (1.0, 0.5, math.inf):
        with pytest.raises(EfficientTrackError, match=r"runtime: max_gap must be a number of control periods > 1"):
            Runtime(None, limits=None, max_gap=bad)


SEQUENCE_LIMITS = GuardLimits(
    q_min=(-0.6, -0.6, -0.6, -math.pi), q_max=(0.6, 0.6, 0.6, math.pi), max_speed=(2.0,) * 4, stale_steps=3
)
SEQUENCE_SHA256 = "c65fc682768a7e27cf0236b8798ff58daa8a9a066cb86427b8285f8b6a4ccdd8"
"""What the guarded step sends on :func:`seeded_calls` (float64 arithmetic only: exact), since a jump starts the
histories afresh (the same steps are jumps as before: 5, 6, 16, 17, … of machine 0)."""


def linear_act(obs_hist, qref_hist, q_des_future):
    """A policy in plain float64 arithmetic (the same bits on every machine)."""
    return 0.5 * (q_des_future[:, 0] - obs_hist[:, -1, :4]) + 0.1 * (qref_hist[:, -1] - qref_hist[:, 0])


def seeded_calls(seed=7, n=2, steps=60):
    """A start observation and ``steps`` seeded calls with jumps, non-finite and stale samples, desired positions outside."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.4, 0.4, (n, 4))
    obs0 = np.concatenate([q, np.zeros((n, 4))], axis=1)
    calls = []
    for k in range(steps):
        q = np.clip(q + rng.normal(0, 0.02, (n, 4)), -0.58, 0.58)
        obs = np.concatenate([q, rng.normal(0, 0.1, (n, 4))], axis=1)
        if k % 11 == 5:
            obs[0, 0] += 0.4
        if k % 13 == 7:
            obs[1, 2] = np.nan
        if 30 <= k < 34:
            obs = calls[-1][0].copy() if k > 30 else obs
        q_des = q[:, None] + rng.normal(0, 0.05, (n, 3, 4))
        if k % 17 == 3:
            q_des[1, 1, 0] = 0.7
        calls.append((obs, q_des))
    return obs0, calls


def sent_on(runtime, stamps=None):
    """(q_ref, adjustment, fallback, guard), each stacked over :func:`seeded_calls`, with ``t = stamps[k]`` when given."""
    obs0, calls = seeded_calls()
    runtime.start(obs0, **({} if stamps is None else {"t": stamps[0]}))
    out = []
    for k, (obs, q_des) in enumerate(calls, 1):
        sent = runtime.step(obs, q_des, **({} if stamps is None else {"t": stamps[k]}))
        out.append((sent.q_ref, sent.adjustment, sent.fallback, sent.guard))
    return [np.stack(x) for x in zip(*out, strict=True)]


def sha256(arrays):
    q_ref, a, fallback, guard = arrays
    digest = hashlib.sha256()
    for x in (q_ref.astype("<f8"), a.astype("<f8"), fallback.astype(np.uint8), guard.astype("<u2")):
        digest.update(np.ascontiguousarray(x).tobytes())
    return digest.hexdigest()


def test_a_normal_call_sequence_sends_what_it_sent_before_time_stamps_existed():
    unstamped = sent_on(GuardedRuntime(linear_act, (3, 3), None, SEQUENCE_LIMITS, DT))
    assert sha256(unstamped) == SEQUENCE_SHA256
    assert set(np.unique(unstamped[3])) >= {Guard.OBS_JUMP, Guard.OBS_NONFINITE, Guard.OBS_STALE, Guard.RATE_LIMITED}
    regular = 1000.0 + DT * np.arange(61)  # one period apart: the same as no stamps
    assert sha256(sent_on(GuardedRuntime(linear_act, (3, 3), None, SEQUENCE_LIMITS, DT), regular)) == SEQUENCE_SHA256
    torch_sent = [sent_on(Runtime(LinearPolicy(horizon=3, seed=5), limits=SEQUENCE_LIMITS), s) for s in (None, regular)]
    for a, b in zip(*torch_sent, strict=True):
        np.testing.assert_array_equal(a, b)
