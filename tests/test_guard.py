"""The runtime guard owns its limits and falls back, counted per step, on every fault a machine or a policy can show."""

import math
import threading

import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import load_records, save_records
from efficienttrack.data.references import Reference, save_references
from efficienttrack.deploy.episodes import FALLBACK, Guard, rollout
from efficienttrack.deploy.runtime import Runtime, track
from efficienttrack.learn.settings import PolicyConfig
from efficienttrack.systems.hydraulic import xe75_closed_loop, xe75_params, xe75_plant
from efficienttrack.systems.limits import DEFAULT_LIMITS, XE75_MAX_ADJUST, GuardLimits
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec, load_system
from test_cli import invoke, refused
from toy_system import LagSystem, sine_refs

XE75 = xe75_params().guard_limits()
"""The built-in machine's limits: boom [−0.55, 0.65] rad."""


class ConstantPolicy(torch.nn.Module):
    """Returns ``a`` (broadcast over the batch unless ``shape`` is given) with the checkpoint bound ``max_adjust``."""

    def __init__(self, a, max_adjust=XE75_MAX_ADJUST, horizon=2, shape=None):
        super().__init__()
        self.cfg = PolicyConfig(horizon=horizon, max_adjust=tuple(max_adjust))
        self.a = torch.as_tensor(a, dtype=torch.float32)
        self.shape = shape
        self.calls = 0
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def forward(self, obs_hist, qref_hist, qdes_future):
        self.calls += 1
        n = len(obs_hist) if self.shape is None else self.shape[0]
        return self.a.expand(n, 4).clone()


class RaisingPolicy(ConstantPolicy):
    """Raises at every 4th call, else a = 0.01."""

    def __init__(self):
        super().__init__([0.01] * 4)

    def forward(self, obs_hist, qref_hist, qdes_future):
        self.calls += 1
        if self.calls % 4 == 1:
            raise RuntimeError("CUDA error: an illegal memory access was encountered")
        return self.a.expand(len(obs_hist), 4).clone()


class LimitedLag(LagSystem):
    """The toy lag system with the xe75's joint limits as its own ``limits`` attribute."""

    limits = XE75

    def __init__(self):
        super().__init__()
        self.resets = 0

    def reset(self, q0):
        self.resets += 1
        return super().reset(q0)


def start(runtime, n=1, q=0.0):
    obs0 = np.zeros((n, 8))
    obs0[:, :4] = q
    runtime.start(obs0)
    return obs0


def desired(n, value, length=2):
    return np.broadcast_to(np.asarray(value, dtype=np.float64), (n, length, 4)).copy()


# ---------------------------------------------------------------------------------------------- limits


def test_checkpoint_bound_only_tightens_the_machines():
    edited = ConstantPolicy([9.5, 9.5, 9.5, 9.5], max_adjust=(10, 10, 10, 10))
    runtime = Runtime(edited, limits=XE75)
    np.testing.assert_array_equal(runtime.max_adjust, XE75_MAX_ADJUST)
    tight = Runtime(ConstantPolicy([0.1] * 4, max_adjust=(0.05, 1, 1, 1)), limits=XE75)
    np.testing.assert_array_equal(tight.max_adjust, (0.05, 0.30, 0.40, 0.40))
    # a policy file edited to max_adjust = 10 never gets 9.5 rad through: every step falls back, counted
    refs = [Reference("r", np.full((30, 4), 0.1))]
    (record,) = track(BatchedSystem(LimitedLag()), edited, refs, progress=False)
    np.testing.assert_array_equal(record.q_ref, record.q_des)
    assert record.meta["fallbacks"] == len(record) == 29
    assert record.meta["guard"] == {"adjust_bound": list(range(29))}
    assert np.abs(record.q_ref).max() <= 0.65


def test_sent_reference_is_clamped_into_the_joint_limits():
    runtime = Runtime(ConstantPolicy([0.07, 0.0, 0.0, 0.0]), limits=XE75)
    start(runtime, q=0.6)
    sent = runtime.step(np.c_[np.full((1, 4), 0.6), np.zeros((1, 4))], desired(1, [0.6, 0.0, 0.0, 0.0]))
    assert sent.q_ref[0, 0] == 0.65 and sent.adjustment[0, 0] == pytest.approx(0.05)
    assert sent.guard[0] == Guard.CLAMPED and not sent.fallback[0]
    assert runtime.counts["clamped"].tolist() == [1] and runtime.fallbacks.tolist() == [0]


def test_the_rate_limit_bounds_each_joints_change_from_the_last_adjustment_sent():
    rate = np.asarray(XE75.max_adjust_rate)
    last = np.array([[0.0, 0.1, -0.1, 0.0]])
    wanted = np.array([[1.0, 0.1, -1.0, 0.01]])
    np.testing.assert_allclose(XE75.rate_limit(wanted, last), [[rate[0], 0.1, -0.1 - rate[2], 0.01]])


def test_swing_is_unlimited_but_wrapped_for_the_check():
    limits = XE75.replace(q_min=(*XE75.q_min[:3], -1.0), q_max=(*XE75.q_max[:3], 1.0))
    np.testing.assert_array_equal(limits.clamp(np.array([0.0, 0.0, 0.0, 2 * math.pi + 0.5])), [0, 0, 0, 2 * math.pi + 0.5])
    np.testing.assert_allclose(limits.clamp(np.array([0.0, 0.0, 0.0, 3.0])), [0, 0, 0, 1.0])
    np.testing.assert_array_equal(XE75.clamp(np.array([0.0, 0.0, 0.0, 3.2])), [0, 0, 0, 3.2])


def test_reference_outside_the_limits_is_refused_before_the_machine_moves():
    system = LimitedLag()
    q = np.zeros((40, 4))
    q[:, 0] = np.linspace(0.0, 2.5, 40)  # boom up to 2.5 rad against a 0.65 rad limit
    with pytest.raises(EfficientTrackError, match=r"reference 'bad': boom is 0\.7051 rad at step 11.*\[-0\.55, 0\.65\]"):
        track(BatchedSystem(system), None, [Reference("ok", np.zeros((40, 4))), Reference("bad", q)], progress=False)
    assert system.resets == 0


def test_desired_position_outside_the_limits_falls_back_and_is_clamped():
    runtime = Runtime(ConstantPolicy([0.01] * 4), limits=XE75)
    start(runtime)
    future = desired(1, 0.1)
    future[0, 1, 0] = 6.0  # a 6 rad future reference
    sent = runtime.step(np.zeros((1, 8)), future)
    assert sent.guard[0] == Guard.DESIRED_OUTSIDE and sent.fallback[0]
    np.testing.assert_array_equal(sent.q_ref, [[0.1, 0.1, 0.1, 0.1]])
    future[0, 0, 0] = 6.0
    sent = runtime.step(np.zeros((1, 8)), future)
    assert sent.q_ref[0, 0] == 0.65 and sent.guard[0] == Guard.DESIRED_OUTSIDE | Guard.CLAMPED


def test_adjustment_rate_is_limited_per_step():
    runtime = Runtime(ConstantPolicy([0.15, 0.0, 0.0, 0.0]), limits=XE75.replace(max_adjust_rate=(0.04, 0.1, 0.1, 0.1)))
    start(runtime)
    adjustments = []
    for _ in range(5):
        sent = runtime.step(np.zeros((1, 8)), desired(1, 0.0))
        adjustments.append(sent.adjustment[0, 0])
        assert not sent.fallback[0]
    np.testing.assert_allclose(adjustments, [0.04, 0.08, 0.12, 0.15, 0.15])
    assert runtime.counts["rate_limited"].tolist() == [3]


def test_limits_file_amends_the_systems_and_is_validated(tmp_path):
    path = tmp_path / "limits.yaml"
    path.write_text("q_max: [0.5, 0.5, 2.0, 3.14159]\nmax_adjust: [0.1, 0.2, 0.2, 0.2]\nstale_steps: 5\n")
    spec = SystemSpec(limits=str(path))
    limits = spec.open().limits
    assert limits.q_max == (0.5, 0.5, 2.0, 3.14159) and limits.q_min == XE75.q_min and limits.stale_steps == 5
    assert spec.to_dict()["limits"] == str(path) and "limits" not in SystemSpec().to_dict()
    bad = {
        "q_min: [1, 0, 0, 0]\nq_max: [0.5, 1, 1, 1]\n": "boom needs",
        "q_max: high\n": "q_max must be a list of finite numbers",
        "max_adjust: [0.1, -1, 0.2, 0.2]\n": "'max_adjust'",
        "max_speed: [1, 2, 3]\n": "'max_speed'",
        "max_adjust_rate: [0.1, .nan, 0.1, 0.1]\n": "max_adjust_rate must be a list of finite numbers",
        "stale_steps: 1\n": "'stale_steps'",
        "speed: 3\n": "unknown GuardLimits field",
        "- 1\n": "expected a mapping",
    }
    for text, message in bad.items():
        path.write_text(text)
        with pytest.raises(EfficientTrackError, match=message) as info:
            GuardLimits.load(path)
        assert str(path) in str(info.value)


def test_systems_give_their_own_limits():
    assert load_system("xe75").limits == XE75
    assert XE75.q_min[:3] == (-0.55, -1.1, -0.5) and XE75.q_max[:3] == (0.65, 0.5, 2.3)
    assert (XE75.q_min[3], XE75.q_max[3]) == (-math.pi, math.pi)
    assert BatchedSystem(LagSystem()).limits == DEFAULT_LIMITS

    class Own(LagSystem):
        limits = {"q_max": [1, 1, 1, 3]}

    assert BatchedSystem(Own()).limits.q_max == (1, 1, 1, 3)
    Own.limits = {"q_max": "high"}
    with pytest.raises(EfficientTrackError, match="attribute 'limits'.*q_max"):
        BatchedSystem(Own(), name="system 'own'")


def test_simulator_clamps_a_start_outside_its_limits():
    plant = xe75_plant()
    obs = plant.reset(np.array([[2.5, 0.0, -0.6, 3.5], [0.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(obs[0, :4], [0.65, 0.0, -0.5, 3.5 - 2 * math.pi])
    np.testing.assert_array_equal(obs[:, 4:], 0.0)
    closed = xe75_closed_loop()
    assert closed.limits == XE75
    obs = closed.reset(np.array([-1.0, 0.0, 0.0, 0.0]))
    assert obs[0] == -0.55


# ---------------------------------------------------------------------------------------------- faults


def test_policy_exception_falls_back_and_is_counted_per_step():
    refs = [Reference("r", np.full((20, 4), 0.1))]
    (record,) = track(BatchedSystem(LimitedLag()), RaisingPolicy(), refs, progress=False)
    raised = list(range(0, 19, 4))
    assert record.meta["guard"] == {"policy_error": raised} and record.meta["fallbacks"] == len(raised)
    d = record.q_ref - record.q_des
    np.testing.assert_array_equal(d[raised], 0.0)
    np.testing.assert_allclose(np.delete(d, raised, axis=0), 0.01, atol=1e-7)


def test_single_row_policy_output_is_not_broadcast_to_three_machines():
    runtime = Runtime(ConstantPolicy([0.01] * 4, shape=(1, 4)), limits=XE75)
    start(runtime, n=3)
    sent = runtime.step(np.zeros((3, 8)), desired(3, 0.1))
    assert sent.fallback.tolist() == [True] * 3 and np.all(sent.guard == Guard.POLICY_SHAPE)
    np.testing.assert_array_equal(sent.q_ref, 0.1)


def test_nan_observation_falls_back_for_that_machine_and_keeps_the_last_good_one():
    policy = ConstantPolicy([0.01] * 4)
    runtime = Runtime(policy, limits=XE75)
    start(runtime, n=2)
    obs = np.zeros((2, 8))
    obs[1, 2] = np.nan
    sent = runtime.step(obs, desired(2, 0.1))
    assert sent.fallback.tolist() == [False, True] and sent.guard[1] == Guard.OBS_NONFINITE
    assert np.all(np.isfinite(runtime._history.obs))
    sent = runtime.step(np.zeros((2, 8)), desired(2, 0.1))
    assert sent.fallback.tolist() == [False, False]
    assert runtime.counts["obs_nonfinite"].tolist() == [0, 1] and runtime.fallbacks.tolist() == [0, 1]


def test_observation_jump_falls_back_for_that_step():
    runtime = Runtime(ConstantPolicy([0.01] * 4), limits=XE75, dt=0.05)
    start(runtime)
    jumped = np.zeros((1, 8))
    jumped[0, 0] = 0.05  # boom: 1 rad/s for one step, beyond twice its top speed (0.78 rad/s)
    assert runtime.step(jumped, desired(1, 0.0)).guard[0] == Guard.OBS_JUMP
    moved = jumped.copy()
    moved[0, 0] += 0.03  # 0.6 rad/s: possible
    assert not runtime.step(moved, desired(1, 0.0)).fallback[0]
    swing = moved.copy()
    swing[0, 3] = math.pi - 0.01
    runtime.step(swing, desired(1, 0.0))
    swing[0, 3] = -math.pi + 0.01  # across the wrap: 0.02 rad
    assert runtime.step(swing, desired(1, 0.0)).guard[0] == 0


def test_stale_observation_falls_back_when_checked():
    runtime = Runtime(ConstantPolicy([0.01] * 4), limits=XE75.replace(stale_steps=3))
    start(runtime)
    flags = [runtime.step(np.zeros((1, 8)), desired(1, 0.0)).guard[0] for _ in range(4)]
    assert flags == [0, 0, Guard.OBS_STALE, Guard.OBS_STALE]
    fresh = np.zeros((1, 8))
    fresh[0, 0] = 1e-4
    assert runtime.step(fresh, desired(1, 0.0)).guard[0] == 0
    unchecked = Runtime(ConstantPolicy([0.01] * 4), limits=XE75)
    start(unchecked)
    assert all(unchecked.step(np.zeros((1, 8)), desired(1, 0.0)).guard[0] == 0 for _ in range(10))


def test_non_finite_desired_next_position_is_refused():
    runtime = Runtime(None, limits=XE75)
    start(runtime)
    with pytest.raises(EfficientTrackError, match=r"non-finite desired position.*machine\(s\) \[0\]"):
        runtime.step(np.zeros((1, 8)), np.full((1, 1, 4), np.nan))
    with pytest.raises(EfficientTrackError, match="non-finite start"):
        runtime.start(np.full((1, 8), np.nan))


def test_fallback_bits_and_per_step_record_survive_saving(tmp_path):
    assert FALLBACK & Guard.CLAMPED == 0 and FALLBACK & Guard.RATE_LIMITED == 0
    refs = [Reference("r", np.full((20, 4), 0.1))]
    (record,) = track(BatchedSystem(LimitedLag()), RaisingPolicy(), refs, progress=False)
    save_records([record], tmp_path)
    (loaded,) = load_records(tmp_path)
    assert loaded.meta["guard"] == record.meta["guard"] and loaded.meta["fallbacks"] == record.meta["fallbacks"]


# ---------------------------------------------------------------------------------------------- hanging systems


class Hanging(LagSystem):
    """Never returns from its 3rd step (until released)."""

    def __init__(self):
        super().__init__()
        self.release = threading.Event()
        self.steps = 0

    def step(self, q_ref):
        self.steps += 1
        if self.steps == 3:
            self.release.wait(30)
        return super().step(q_ref)


class Failing(LagSystem):
    def step(self, q_ref):
        raise ValueError("valve driver lost")


def test_a_step_that_never_returns_ends_the_episode_with_an_error():
    system = Hanging()
    refs = [np.zeros((10, 4))]
    with pytest.raises(EfficientTrackError, match=r"system 'hang': step 2 did not return within 0\.2 s"):
        rollout(BatchedSystem(system, name="system 'hang'"), refs, Runtime(None, limits=None), step_timeout=0.2)
    system.release.set()
    with pytest.raises(ValueError, match="valve driver lost"):
        rollout(BatchedSystem(Failing()), refs, Runtime(None, limits=None), step_timeout=1.0)
    with pytest.raises(EfficientTrackError, match="step_timeout"):
        rollout(BatchedSystem(LagSystem()), refs, Runtime(None, limits=None), step_timeout=0)
    sine = [ref.q for ref in sine_refs([30])]
    direct, watched = (
        rollout(BatchedSystem(LagSystem()), sine, Runtime(None, limits=None), step_timeout=t)[0] for t in (None, 5.0)
    )
    np.testing.assert_array_equal(direct.q, watched.q)


# ---------------------------------------------------------------------------------------------- command line


def test_cli_limits_file_refuses_references_outside_before_any_work(tmp_path):
    save_references(sine_refs([30, 30], seed=1), tmp_path / "refs")  # the boom down to −0.35 rad
    (tmp_path / "limits.yaml").write_text("q_min: [-0.1, -6, -6, -3.2]\n")
    system = ["--system", "toy_system:make", "--limits", tmp_path / "limits.yaml"]
    refs = tmp_path / "refs"
    result = invoke("run", *system, "--train-refs", refs, "--test-refs", refs, "--out", tmp_path / "run", "--preset", "tiny")
    refused(result, "reference 'ref_00': boom is")
    assert not (tmp_path / "run" / "run.json").exists() and not (tmp_path / "run" / "collect").exists()
    refused(invoke("evaluate", *system, "--refs", refs, "--out", tmp_path / "eval"), "outside the joint limits [-0.1, 6.283]")
    (tmp_path / "limits.yaml").write_text("max_adjust: 0.1\n")
    message = "max_adjust must be a list of finite numbers"
    refused(invoke("evaluate", *system, "--refs", refs, "--out", tmp_path / "eval"), message)


def test_a_limits_file_with_an_adjustment_over_half_a_joints_range_needs_its_own_switch(tmp_path):
    path = tmp_path / "limits.yaml"
    path.write_text("max_adjust: [10, 0.3, 0.4, 0.4]\n")  # the reviewer's 10 rad let 2.6 rad adjustments through
    with pytest.raises(EfficientTrackError) as caught:
        SystemSpec(limits=str(path)).open()
    message = str(caught.value)
    assert message.startswith(f"{path}: max_adjust of the boom, 10.0 rad, is more than half its range [-0.55, 0.65]")
    assert "add 'accept_implausible: true' to the file" in message and "\n" not in message
    path.write_text("max_adjust: [10, 0.3, 0.4, 0.4]\naccept_implausible: true\n")
    assert SystemSpec(limits=str(path)).open().limits.max_adjust[0] == 10
    path.write_text("accept_implausible: yes please\n")
    with pytest.raises(EfficientTrackError, match="accept_implausible must be true or false"):
        GuardLimits.load(path)
    path.write_text("max_speed: [1, 1, 25, 1]\n")
    with pytest.raises(EfficientTrackError, match=r"max_speed of the bucket, 25.0 rad/s, is beyond any excavator's 20 rad/s"):
        GuardLimits.load(path)
    assert not XE75.implausible() and GuardLimits.load("xe75") == XE75
