import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.dataset import Sequences
from efficienttrack.deploy.runtime import Runtime, track
from efficienttrack.learn.policy import PolicyConfig
from efficienttrack.systems.limits import DEFAULT_LIMITS
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
