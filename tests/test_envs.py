"""The Gymnasium environments: checkers, registration, seeding, vector = N singles, the reward, evaluate = PD, bad input."""

from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import efficienttrack
from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.references import Reference, save_references
from efficienttrack.deploy.runtime import track
from efficienttrack.envs import CLOSED_LOOP_ID, OPEN_LOOP_ID, TrackingEnv, TrackingVectorEnv, evaluate, observation_size
from efficienttrack.envs.core import reward
from efficienttrack.learn.policy import AdjustmentPolicy
from efficienttrack.learn.settings import POLICY_PRESETS
from efficienttrack.systems.spec import SystemSpec

H = 21
"""Index of o_t's q in the flat observation: the last row of o_H."""
Q_T = slice((H - 1) * 8, (H - 1) * 8 + 4)
"""o_t's joint positions in the observation."""
Q_NEXT = slice(H * 12, H * 12 + 4)
"""q*_{t+1} in the observation."""


@pytest.fixture(scope="module")
def cycles() -> list[Reference]:
    """Three generated loading cycles (15–25 s each)."""
    return generate_references(3, seed=5)


@pytest.fixture(scope="module")
def cycle_starts(cycles) -> list[Reference]:
    """The cycles' first 100 steps (5 s of moving joints): enough to compare two ways of running them, in a third of
    the time."""
    return [Reference(ref.name, ref.q[:100]) for ref in cycles]


@pytest.fixture(scope="module")
def short() -> list[Reference]:
    """Three short slices of loading cycles (11, 16 and 22 steps), so that episodes end often."""
    refs = generate_references(3, seed=7)
    return [Reference(f"short_{i}", ref.q[60 : 60 + n]) for i, (ref, n) in enumerate(zip(refs, (12, 17, 23), strict=True))]


def toward_next(obs: np.ndarray) -> np.ndarray:
    """A deterministic agent (N, D) → (N, 4): push toward the next desired position."""
    return np.tanh(10.0 * (obs[:, Q_NEXT] - obs[:, Q_T]))


@pytest.mark.filterwarnings("ignore:.*Box observation space m.*infinity")  # unbounded by design: any system
@pytest.mark.parametrize("env_id", [CLOSED_LOOP_ID, OPEN_LOOP_ID])
def test_both_ids_pass_gymnasiums_check_env(env_id, short):
    env = gymnasium.make(env_id, refs=short)
    check_env(env.unwrapped)
    assert env.observation_space.shape == (332,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (4,) and np.all(env.action_space.high == 1.0) and np.all(env.action_space.low == -1.0)


def test_sb3_check_env_passes_on_the_single_env(short):
    for loop in ("closed", "open"):
        env = TrackingEnv(loop, refs=short)
        sb3_check_env(env, warn=False)
        # what SB3's algorithms take from it: a flat float32 observation, a float32 action box normalized to [-1, 1]
        assert env.observation_space.shape == (observation_size(),) and env.observation_space.dtype == np.float32
        assert env.action_space.shape == (4,) and env.action_space.dtype == np.float32
        assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)
        obs, info = env.reset(seed=0)
        assert obs.shape == (observation_size(),) and obs.dtype == np.float32 and np.all(np.isfinite(obs))
        assert info["reference"] in {ref.name for ref in short}
        obs, r, terminated, truncated, _ = env.step(np.zeros(4, dtype=np.float32))
        assert obs.dtype == np.float32 and np.isfinite(r) and not terminated and not truncated


def test_make_with_a_reference_folder_after_importing_the_package(tmp_path, short):
    assert efficienttrack.__version__
    save_references(short, tmp_path / "refs")
    env = gymnasium.make(CLOSED_LOOP_ID, system="xe75", refs=str(tmp_path / "refs"))
    obs, info = env.reset(seed=1, options={"reference": "short_1"})
    assert obs.shape == (observation_size(),) and info["reference"] == "short_1"
    assert np.allclose(obs[Q_NEXT], short[1].q[1])  # q*_{t+1} as the paper orders the observation
    steps = 0
    while True:
        obs, r, terminated, truncated, info = env.step(np.zeros(4, dtype=np.float32))
        steps += 1
        assert not terminated and np.isfinite(r)
        if truncated:
            break
    assert steps == len(short[1]) - 1 == info["step"]
    vec = gymnasium.make_vec(OPEN_LOOP_ID, num_envs=3, refs=str(tmp_path / "refs"))
    assert isinstance(vec, TrackingVectorEnv) and vec.loop == "open"
    assert vec.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert vec.observation_space.shape == (3, 332) and vec.single_action_space.shape == (4,)


def test_the_same_seed_gives_the_same_episodes(cycles):
    def run(seed):
        env = TrackingEnv("closed", refs=cycles)
        rng = np.random.default_rng(0)
        out = []
        for episode in range(3):
            obs, info = env.reset(seed=seed if episode == 0 else None)
            out.append((info["reference"], obs))
            for _ in range(15):
                obs, r, *_ = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
                out.append((r, obs))
        return out

    first, again = run(3), run(3)
    for (a, obs_a), (b, obs_b) in zip(first, again, strict=True):
        assert a == b and np.array_equal(obs_a, obs_b)
    drawn = {tuple(info for info, _ in run(seed)[::16]) for seed in range(6)}
    assert len(drawn) > 1  # the seed does choose the references


@pytest.mark.parametrize("loop", ["closed", "open"])
def test_vector_env_equals_n_single_envs_across_autoresets(loop, short):
    n = 4
    vec = TrackingVectorEnv(n, loop, refs=short)
    singles = SyncVectorEnv([lambda: TrackingEnv(loop, refs=short)] * n, autoreset_mode=AutoresetMode.SAME_STEP)
    obs_v, info_v = vec.reset(seed=11)
    obs_s, info_s = singles.reset(seed=11)
    np.testing.assert_array_equal(obs_v, obs_s)
    assert list(info_v["reference"]) == list(info_s["reference"])
    rng = np.random.default_rng(2)
    ended = 0
    for _ in range(60):
        actions = rng.uniform(-1, 1, (n, 4)).astype(np.float32)
        obs_v, r_v, term_v, trunc_v, info_v = vec.step(actions)
        obs_s, r_s, term_s, trunc_s, info_s = singles.step(actions)
        np.testing.assert_array_equal(obs_v, obs_s)
        np.testing.assert_array_equal(r_v, r_s)
        np.testing.assert_array_equal(term_v, term_s)
        np.testing.assert_array_equal(trunc_v, trunc_s)
        assert list(info_v["reference"]) == list(info_s["reference"])
        np.testing.assert_array_equal(info_v["step"], info_s["step"])
        np.testing.assert_array_equal(info_v["tracking_error"], info_s["tracking_error"])
        if trunc_s.any():
            np.testing.assert_array_equal(info_v["_final_obs"], info_s["_final_obs"])
            for i in np.flatnonzero(trunc_s):
                np.testing.assert_array_equal(info_v["final_obs"][i], info_s["final_obs"][i])
                assert info_v["final_info"]["step"][i] == info_s["final_info"]["step"][i] > 0
            ended += int(trunc_s.sum())
    assert ended >= 8  # several autoresets happened on the way


def test_reward_has_the_papers_value():
    zero = np.zeros((1, 4))
    assert reward(zero, zero)[0] == pytest.approx(1.0)  # 5·0.1 + 5·0.1: perfect tracking, no change
    assert reward(np.full((1, 4), 0.1), zero)[0] == pytest.approx(0.5)  # RMS 0.1 rad uses up the first term
    change = np.array([[0.2, 0.0, 0.0, 0.0]])  # RMS_j = sqrt(0.04 / 4) = 0.1
    assert reward(zero, change)[0] == pytest.approx(0.5)
    assert reward(np.array([[0.3, 0.0, 0.0, 0.0]]), change)[0] == pytest.approx(5 * (0.1 - 0.15) + 0.0)


def test_reward_of_an_env_step_by_hand(cycles):
    env = TrackingEnv("closed", refs=cycles)
    env.reset(seed=0, options={"reference": 0})
    bound = np.asarray(env.episodes.system.limits.max_adjust)
    obs, r, _, _, info = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))
    e = wrap(env.episodes.history.obs[0, -1, :4] - cycles[0].q[1])
    np.testing.assert_allclose(info["tracking_error"], e)
    assert r == pytest.approx(5 * (0.1 - np.sqrt(np.mean(e**2))) + 5 * (0.1 - bound[0] / 2))
    obs, r, _, _, info = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))  # no change: only tracking counts
    assert r == pytest.approx(5 * (0.1 - np.sqrt(np.mean(info["tracking_error"] ** 2))) + 0.5)
    open_env = TrackingEnv("open", refs=cycles)
    open_env.reset(seed=0, options={"reference": 0})
    _, r, _, _, info = open_env.step(np.full(4, 0.5, dtype=np.float32))  # the action's change: RMS 0.5
    assert r == pytest.approx(5 * (0.1 - np.sqrt(np.mean(info["tracking_error"] ** 2))) + 5 * (0.1 - 0.5))


def test_evaluate_with_zero_actions_is_the_pd_controller(cycle_starts):
    records = evaluate(lambda obs: np.zeros((len(obs), 4)), cycle_starts, loop="closed", system=SystemSpec())
    pd = track(SystemSpec().open(), None, cycle_starts, progress=False)
    assert [r.meta["name"] for r in records] == [ref.name for ref in cycle_starts]
    for ours, theirs in zip(records, pd, strict=True):
        for field in ("q", "qd", "q_ref", "q_des", "u", "t"):
            np.testing.assert_array_equal(getattr(ours, field), getattr(theirs, field))
    assert compute_metrics(records)["mae_deg"] == compute_metrics(pd)["mae_deg"] > 0


def gentle(obs: np.ndarray) -> np.ndarray:
    """``toward_next`` within ±0.2: its adjustment never changes faster than the guard's rate (max_adjust / 2 a step)."""
    return 0.2 * toward_next(obs)


@pytest.mark.parametrize(("loop", "agent"), [("closed", gentle), ("open", toward_next)])
def test_evaluate_equals_stepping_the_env(loop, agent, cycle_starts):
    records = evaluate(agent, cycle_starts, loop=loop)
    env = TrackingEnv(loop, refs=cycle_starts)
    for i, record in enumerate(records):
        obs, _ = env.reset(options={"reference": i})
        positions = [obs[Q_T]]
        truncated = False
        while not truncated:
            obs, _, _, truncated, _ = env.step(agent(obs[None])[0])
            positions.append(obs[Q_T])
        np.testing.assert_allclose(record.q, np.array(positions[:-1]), atol=1e-6)
        assert len(record) == len(cycle_starts[i]) - 1
        if loop == "open":
            np.testing.assert_array_equal(record.q_ref, record.q_des)
            assert record.u is not None and np.abs(record.u).max() <= 1000.0
    assert compute_metrics(records)["mae_deg"] > 0


def test_a_restarted_machine_runs_as_if_it_were_alone(cycles):
    system = SystemSpec().open()
    system.reset(np.stack([ref.q[0] for ref in cycles]))
    for t in range(1, 120):  # all three moving: the PD's last errors are not zero
        system.step(np.stack([ref.q[t] for ref in cycles]))
    assert np.abs(system.system._e_prev[1]).max() > 1e-3
    start = cycles[0].q[150]
    obs_restart = system.reset_machines(np.array([1]), start[None])
    alone = SystemSpec().open()
    np.testing.assert_array_equal(obs_restart, alone.reset(start[None]))
    for t in range(151, 161):
        obs = system.step(np.stack([cycles[0].q[t - 30], cycles[0].q[t], cycles[2].q[t - 30]]))
        np.testing.assert_array_equal(obs[1], alone.step(cycles[0].q[t][None])[0])
        np.testing.assert_array_equal(system.last_command[1], alone.last_command[0])  # PWM: the PD's first step again
    assert np.abs(alone.last_command).max() > 0


def test_bad_inputs_name_the_problem(tmp_path, short):
    with pytest.raises(EfficientTrackError, match="loop"):
        TrackingEnv("half", refs=short)
    with pytest.raises(EfficientTrackError, match="no-such-folder"):
        TrackingEnv("closed", refs=str(tmp_path / "no-such-folder"))
    with pytest.raises(EfficientTrackError, match="refs: expected a folder or a list of Reference, got int"):
        TrackingEnv("closed", refs=42)
    with pytest.raises(EfficientTrackError, match="no PWM-level plant"):
        TrackingEnv("open", system="toy_system:make", refs=short)
    with pytest.raises(EfficientTrackError, match="no PWM-level plant"):
        gymnasium.make(OPEN_LOOP_ID, system="learned", refs=short)
    env = TrackingEnv("closed", refs=short)
    with pytest.raises(EfficientTrackError, match="before reset"):
        env.step(np.zeros(4))
    env.reset(seed=0)
    with pytest.raises(EfficientTrackError, match=r"action: expected shape \(4,\)"):
        env.step(np.zeros(3))
    with pytest.raises(EfficientTrackError, match="NaN"):
        env.step(np.full(4, np.nan))
    with pytest.raises(EfficientTrackError, match="reference"):
        env.reset(options={"reference": 99})
    with pytest.raises(EfficientTrackError, match="unknown key"):
        env.reset(options={"refrence": 0})
    vec = TrackingVectorEnv(2, refs=short)
    vec.reset(seed=0)
    with pytest.raises(EfficientTrackError, match=r"action: expected shape \(2, 4\)"):
        vec.step(np.zeros((3, 4)))
    with pytest.raises(EfficientTrackError, match="reset_machines"):
        TrackingVectorEnv(2, system="toy_system:make", refs=short)
    with pytest.raises(EfficientTrackError, match="single machines only"):
        TrackingVectorEnv(2, system="toy_system:make", system_opts={"batched": False}, refs=short)
    outside = Reference("outside", np.tile([0.0, 0.0, 3.0, 0.0], (5, 1)))
    with pytest.raises(EfficientTrackError, match="'outside'.*joint limits"):
        TrackingEnv("closed", refs=[outside])


def test_the_package_imports_no_gymnasium_and_registers_the_ids_when_gymnasium_is_imported(tmp_path, short):
    save_references(short, tmp_path / "refs")
    code = (
        "import sys, efficienttrack\n"
        "print('gymnasium' in sys.modules)\n"
        "import gymnasium\n"
        "print(gymnasium.make('EfficientTrack/ClosedLoop-v0', refs=sys.argv[1]).reset(seed=0)[0].shape)\n"
    )
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "refs")], capture_output=True, text=True)
    assert out.stdout.splitlines() == ["False", "(332,)"], out.stderr
    code = "import sys; sys.modules['gymnasium'] = None; import efficienttrack; print(efficienttrack.__version__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == efficienttrack.__version__, out.stderr  # without Gymnasium


def test_the_vector_env_takes_one_reference_per_sub_environment(short):
    vec = TrackingVectorEnv(3, refs=short)
    obs, info = vec.reset(seed=0, options={"reference": [2, "short_0", 1]})
    assert list(info["reference"]) == ["short_2", "short_0", "short_1"]
    np.testing.assert_allclose(obs[:, Q_NEXT], np.stack([short[2].q[1], short[0].q[1], short[1].q[1]]), atol=1e-6)
    with pytest.raises(EfficientTrackError, match="one entry per sub-environment"):
        vec.reset(options={"reference": [0, 1]})


def test_a_loaded_policy_predicts_in_the_registered_environment_and_in_sb3s_evaluate_policy(short, tmp_path):
    import dataclasses

    import torch
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor

    from efficienttrack.learn.policy import AdjustmentPolicy, load_policy, save_policy
    from efficienttrack.learn.settings import POLICY_PRESETS

    cfg = dataclasses.replace(POLICY_PRESETS["tiny"], max_adjust=SystemSpec().open().limits.max_adjust)
    made = AdjustmentPolicy(cfg)
    torch.nn.init.normal_(made.pi_phi.body[-1].weight, std=0.5)  # not a = 0
    policy = load_policy(save_policy(made, tmp_path / "policy.pt"))
    env = gymnasium.make(CLOSED_LOOP_ID, system="xe75", refs=short)
    obs, _ = env.reset(seed=0)
    action, state = policy.predict(obs)
    assert action.shape == (4,) and state is None and np.all(np.abs(action) <= 1) and np.any(action != 0)
    h = 4  # the policy sees the last h of the environment's 21 observations and references, and the first 4 q*
    o, r, q = obs[: H * 8].reshape(H, 8), obs[H * 8 : H * 12].reshape(H, 4), obs[H * 12 :].reshape(-1, 4)
    with torch.no_grad():
        a = policy(*(torch.as_tensor(x[None]) for x in (o[-h:], r[-h:], q[:4]))).numpy()[0]
    np.testing.assert_allclose(action, a / np.asarray(cfg.max_adjust), rtol=1e-5)
    mean, _ = evaluate_policy(policy, Monitor(env), n_eval_episodes=2)
    assert np.isfinite(mean)
    with pytest.raises(EfficientTrackError, match="is not h·8 \\+ h·4"):
        policy.predict(obs[:-3])


@pytest.mark.parametrize(
    ("act", "message"),
    [(lambda obs: np.full((len(obs), 4), np.nan), "action: NaN or inf"), (lambda obs: np.zeros(3), "action: expected shape")],
)
def test_a_broken_agent_is_an_error_not_scored_as_pd_by_the_guards_fallback(act, message, cycle_starts):
    with pytest.raises(EfficientTrackError, match=f"evaluate: the agent failed: EfficientTrackError: {message}"):
        evaluate(act, cycle_starts, loop="closed")


def test_a_policy_scored_as_a_baseline_is_scored_as_efficienttrack_guard_included(cycles):
    starts = [Reference(ref.name, ref.q[:80]) for ref in cycles]  # before float32 round-off grows in the closed loop
    torch.manual_seed(0)
    policy = AdjustmentPolicy(POLICY_PRESETS["tiny"])
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.2)  # an untrained policy that adjusts, and jumps
    h, f = policy.cfg.history_length, policy.cfg.future_length  # the policy's own lengths: the same float32 inputs
    act = lambda obs: policy.predict(obs, future=f)[0]  # noqa: E731
    as_baseline = evaluate(act, starts, loop="closed", system=SystemSpec(), history=h, future=f)
    as_efficienttrack = track(SystemSpec().open(), policy, starts, progress=False)
    # equal but for the environments' float32 action (a / max_adjust), whose round-off a jumpy policy amplifies
    for ours, theirs in zip(as_baseline, as_efficienttrack, strict=True):
        np.testing.assert_allclose(ours.q_ref, theirs.q_ref, atol=1e-3)
        assert ours.meta["guard"] == theirs.meta["guard"] and ours.meta["fallbacks"] == theirs.meta["fallbacks"]
    assert sum(len(r.meta["guard"]["rate_limited"]) for r in as_baseline) > 3  # the guard's rate limit acted, alike
    ours, theirs = compute_metrics(as_baseline), compute_metrics(as_efficienttrack)
    for key in ("mae_deg", "rmse_deg", "fmae_deg", "smt1_deg", "smt2_deg"):
        assert ours[key] == pytest.approx(theirs[key], rel=1e-3), key
