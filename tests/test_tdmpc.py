"""TD-MPC: the planner on a known toy model, the TOLD loss, prioritized replay, and train_tdmpc end to end."""

import json
import math
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

from efficienttrack.baselines.curve import training_run
from efficienttrack.baselines.resume import STATE_FILE
from efficienttrack.baselines.tdmpc import (
    PRESETS,
    TOLD,
    Learner,
    PlannerConfig,
    PrioritizedBuffer,
    Sequences,
    TDMPCSettings,
    plan,
    tdmpc_settings,
    train_tdmpc,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.metrics import METRIC_KEYS, compute_metrics
from efficienttrack.data.references import Reference
from efficienttrack.envs import evaluate
from efficienttrack.learn.checkpoints import load_tensors
from efficienttrack.systems.spec import SystemSpec

TINY = replace(PRESETS["tiny"], seed_steps=20, schedule_steps=40, device="cpu")
"""The quick preset with a shorter seeding phase, so that a few dozen steps reach the planner and the updates."""


class ToyModel:
    """A known latent system: z' = z + 0.5 a, reward −‖z' − goal‖², Q ≡ 0, π ≡ 0 (plus noise)."""

    goal = torch.tensor([0.8, -0.6])

    def next(self, z, a):
        z_next = z + 0.5 * a
        return z_next, -((z_next - self.goal) ** 2).sum(-1)

    def q(self, z, a):
        zero = torch.zeros(z.shape[:-1])
        return zero, zero

    def pi(self, z, std=0.0, generator=None):
        a = torch.zeros(*z.shape[:-1], 2)
        return a if std <= 0 else (a + std * torch.randn(a.shape, generator=generator)).clamp(-1, 1)


def toy_return(choose, steps=8, machines=3):
    """The toy's true return over ``steps`` steps from z = 0 for ``machines`` machines, actions from ``choose(z, t)``."""
    model, z, total = ToyModel(), torch.zeros(machines, 2), torch.zeros(machines)
    for t in range(steps):
        z, reward = model.next(z, choose(z, t))
        total += reward
    return total


def test_planner_beats_random_and_the_initial_policy_on_a_known_toy_model():
    config = PlannerConfig(
        horizon=4, action_dim=2, iterations=4, num_samples=64, num_pi_samples=4, num_elites=8,
        temperature=0.5, momentum=0.1, min_std=0.05, pi_std=0.05, discount=0.98,
    )  # fmt: skip
    generator = torch.Generator().manual_seed(0)
    warm = []

    def planned(z, t):
        result = plan(ToyModel(), z, config, generator, warm[-1] if warm else None, explore=False)
        warm.append(result.mean)
        assert result.action.shape == (3, 2) and result.mean.shape == (4, 3, 2)
        return result.action

    rng = torch.Generator().manual_seed(1)
    planner = toy_return(planned)
    random = toy_return(lambda z, t: torch.rand(z.shape, generator=rng) * 2 - 1)
    initial = toy_return(lambda z, t: ToyModel().pi(z))
    # the best possible return: reach the goal in two steps (−0.25 − 0 …); π ≡ 0 stays at −1 per step
    assert initial.tolist() == pytest.approx([-8.0] * 3)
    assert (planner > -0.6).all(), planner
    assert (planner > random + 2).all() and (planner > initial + 7).all()


def told_batch(rng, batch=32, horizon=3, obs_dim=6):
    """Sequences of a linear system o' = 0.9 o + B a with reward −‖o'‖²."""
    b = rng.normal(size=(2, obs_dim)).astype(np.float32) * 0.3
    obs = rng.normal(size=(batch, obs_dim)).astype(np.float32)
    action = rng.uniform(-1, 1, (horizon, batch, 2)).astype(np.float32)
    next_obs, reward, o = [], [], obs
    for a in action:
        o = 0.9 * o + a @ b
        next_obs.append(o)
        reward.append(-(o**2).sum(-1))
    return Sequences(obs, np.stack(next_obs), action, np.stack(reward), np.arange(batch), np.ones(batch, np.float32))


def test_told_loss_falls_on_a_small_batch():
    torch.manual_seed(0)
    settings = replace(TINY, hidden=64, latent_dim=8)
    model = TOLD(6, 2, settings)
    learner = Learner(model, settings, torch.Generator().manual_seed(0))
    batch = told_batch(np.random.default_rng(0))
    losses = [learner.update(batch)[0] for _ in range(150)]
    first, last = losses[0], losses[-1]
    assert last.reward < 0.1 * first.reward
    assert last.total < 0.5 * first.total
    assert learner.updates == 150 and all(math.isfinite(x.pi) for x in losses)


def test_prioritized_replay_samples_in_proportion_to_priority():
    buffer = PrioritizedBuffer(capacity=50, obs_dim=1, action_dim=1, horizon=2, alpha=0.6, beta=0.4)
    for episode, length in enumerate((5, 1, 3)):
        for t in range(length):
            value = np.array([10 * episode + t], np.float32)
            buffer.add(value, value, float(value[0]), value + 1, first=t == 0)
    # starts: 0…3 (episode 0), none in the one-step episode 1 (position 5), 6 and 7 (episode 2)
    assert np.flatnonzero(buffer.priority).tolist() == [0, 1, 2, 3, 6, 7]
    buffer.update(np.array([0, 1, 2, 3, 6, 7]), np.array([1.0, 2.0, 3.0, 4.0, 0.5, 8.0]) - 1e-6)
    batch = buffer.sample(60_000, np.random.default_rng(0))
    p = np.array([1.0, 2.0, 3.0, 4.0, 0.5, 8.0]) ** 0.6
    expected = p / p.sum()
    frequency = np.array([(batch.index == i).mean() for i in (0, 1, 2, 3, 6, 7)])
    np.testing.assert_allclose(frequency, expected, atol=0.006)
    weight = (6 * expected) ** -0.4
    np.testing.assert_allclose(batch.weight[batch.index == 0][0], weight[0] / weight.max(), rtol=1e-5)
    assert batch.weight.max() == pytest.approx(1.0)
    # a sequence is two consecutive steps of one episode
    assert batch.next_obs.shape == (2, 60_000, 1) and batch.obs.shape == (60_000, 1)
    np.testing.assert_array_equal(batch.action[1, :, 0], batch.action[0, :, 0] + 1)
    np.testing.assert_array_equal(batch.next_obs[0], batch.obs + 1)
    np.testing.assert_array_equal(batch.reward[0], batch.obs[:, 0])


def test_replay_overwrites_the_oldest_and_refuses_an_empty_sample():
    buffer = PrioritizedBuffer(capacity=4, obs_dim=1, action_dim=1, horizon=2, alpha=1.0, beta=0.0)
    with pytest.raises(EfficientTrackError, match="no sequence of 2 steps stored yet"):
        buffer.sample(1, np.random.default_rng(0))
    for t in range(6):
        buffer.add(np.array([t], np.float32), np.zeros(1, np.float32), 0.0, np.array([t + 1], np.float32), first=t == 0)
    # positions hold steps 4, 5, 2, 3; starts 2 (2→3), 3 (3→4) and 0 (4→5); position 1 (step 5) waits for step 6
    assert np.flatnonzero(buffer.priority).tolist() == [0, 2, 3]
    batch = buffer.sample(200, np.random.default_rng(1))
    np.testing.assert_array_equal(batch.next_obs[1, :, 0], batch.obs[:, 0] + 2)


@pytest.fixture(scope="module")
def refs():
    """Two training and two test references, cut short (40 and 30 steps) to keep training and evaluation fast."""
    cycles = generate_references(4, seed=1)
    return [Reference(r.name, r.q[:40]) for r in cycles[:2]], [Reference(r.name, r.q[:30]) for r in cycles[2:]]


def finite(metrics):
    return all(math.isfinite(metrics[key]) for key in METRIC_KEYS if key != "per_joint_mae_deg")


def test_quick_preset_trains_on_the_closed_loop(refs, tmp_path):
    train, test = refs
    settings = replace(tdmpc_settings("tiny"), device="cpu")
    curve = train_tdmpc(training_run("closed", SystemSpec(), train, test, 70, 0, tmp_path, eval_at=[1, 50, 70]), settings)
    assert [p["interaction_steps"] for p in curve] == [1, 50, 70]
    assert all(finite(p["metrics"]) and p["metrics"]["episodes"] == len(test) for p in curve)
    walls = [p["wall_seconds"] for p in curve]
    assert walls == sorted(walls) and walls[0] >= 0
    # seeding, then 50 updates at once at step 50, then one update a step: sequences of the batch per update
    assert [p["gradient_samples"] for p in curve] == [0, 50 * 16, 70 * 16]
    written = json.loads((tmp_path / "curve.json").read_text())
    assert (written["method"], written["loop"], written["seed"], written["budget"]) == ("tdmpc", "closed", 0, 70)
    assert written["curve"] == json.loads(json.dumps(curve))
    assert written["settings"]["latent_dim"] == 8
    state = torch.load(tmp_path / "model.pt", weights_only=True)
    assert state["h.0.weight"].shape == (32, 332)


def test_open_loop_trains_and_evaluates_with_the_planner(refs, tmp_path):
    train, test = refs
    settings = replace(TINY, evaluate_with="plan")
    curve = train_tdmpc(training_run("open", SystemSpec(plant="xe75"), train, test, 30, 1, tmp_path, eval_at=[30]), settings)
    assert [p["interaction_steps"] for p in curve] == [30] and finite(curve[0]["metrics"])


def test_same_seed_same_curve(refs, tmp_path):
    """Evaluated with the policy; with the planner, test_validation_leaves_the_planners_test_curve_alone."""
    train, test = refs
    settings = replace(TINY, evaluate_with="policy")
    state = torch.get_rng_state()

    def metrics(seed, name):
        return train_tdmpc(training_run("closed", SystemSpec(), train, test, 30, seed, tmp_path / name, [30]), settings)[-1][
            "metrics"
        ]

    first = metrics(3, "a")
    assert metrics(3, "b") == first
    assert metrics(4, "c") != first
    assert torch.equal(torch.get_rng_state(), state)  # the global generator is left alone


def test_validation_leaves_the_planners_test_curve_alone(refs, tmp_path):
    """Also the planner's same seed, same curve (test_same_seed_same_curve evaluates with the policy)."""
    train, test = refs
    settings = replace(TINY, evaluate_with="plan")  # an agent with a state: its generator
    validation = [Reference("val", generate_references(1, seed=5)[0].q[:25])]
    state = torch.get_rng_state()

    def curve(name, validation_refs, seed=3):
        return train_tdmpc(
            training_run("closed", SystemSpec(), train, test, 30, seed, tmp_path / name, [1, 30], validation_refs), settings
        )

    plain, validated = curve("plain", ()), curve("validated", validation)
    assert [p["metrics"] for p in validated] == [p["metrics"] for p in plain]
    assert all(p["validation"]["episodes"] == 1 and finite(p["validation"]) for p in validated)
    assert curve("other", (), seed=4)[-1]["metrics"] != plain[-1]["metrics"]
    assert torch.equal(torch.get_rng_state(), state)  # the global generator is left alone


def test_an_interrupted_run_resumes_as_if_uninterrupted(refs, tmp_path, monkeypatch, interrupt_at):
    train = [Reference(r.name, r.q[:11]) for r in generate_references(8, seed=2)]  # 10-step episodes, drawn at random
    test = refs[1]

    def run(folder, seed=3):
        spec = training_run("closed", SystemSpec(), train, test, 70, seed, folder, [25, 50, 70])
        return train_tdmpc(spec, TINY, save_every_seconds=0)

    uninterrupted = run(tmp_path / "a")
    interrupt_at(50)
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "b")
    monkeypatch.undo()
    assert load_tensors(tmp_path / "b" / STATE_FILE)["count"] == 40  # the end of the fourth episode
    before = json.loads((tmp_path / "b" / "curve.json").read_text())["curve"]
    with pytest.raises(EfficientTrackError, match="training_state.pt: the training state of another run"):
        run(tmp_path / "b", seed=4)
    resumed = run(tmp_path / "b")
    assert resumed[0] == before[0]  # kept as measured (its wall time too), not measured again
    assert [p["metrics"] for p in resumed] == [p["metrics"] for p in uninterrupted]  # 3 episodes drawn after the state
    assert not (tmp_path / "b" / STATE_FILE).exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"loop": "half"}, "loop: unknown loop 'half'"),
        ({"budget": 0}, "budget: must be an integer ≥ 1"),
        ({"eval_at": [5, 101]}, r"eval_at: each point must be an integer in \[1, budget = 100\], got 101"),
        ({"preset": "huge"}, "preset 'huge': unknown for tdmpc"),
        ({"preset": 3}, "tdmpc takes a preset name or TDMPCSettings, got int"),
        ({"seed": -1}, "seed: a seed must be an integer"),
        ({"system": "xe75"}, "system: expected a SystemSpec"),
        ({"train_refs": []}, "train_refs: no references given"),
        ({"test_refs": [Reference("short", np.zeros((2, 4)))]}, "test_refs: reference 'short' has 2 steps"),
    ],
)
def test_bad_input_is_refused_before_training(refs, tmp_path, change, message):
    args = {"loop": "closed", "system": SystemSpec(), "train_refs": refs[0], "test_refs": refs[1], "budget": 100}
    args |= {"seed": 0, "folder": tmp_path / "out", "preset": "tiny", "eval_at": None} | change
    with pytest.raises(EfficientTrackError, match=message):
        train_tdmpc(preset=args.pop("preset"), run=training_run(**args))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"horizon": 0}, "TDMPCSettings.horizon must be an integer ≥ 1, got 0"),
        ({"num_elites": 600}, "TDMPCSettings.num_elites must be ≤ the sequences sampled"),
        ({"rho": 1.5}, r"TDMPCSettings.rho must be a finite number in \[0, 1\]"),
        ({"min_std": 0.0}, r"TDMPCSettings.min_std must be a finite number in \(0, 2\]"),
        ({"learning_rate": float("nan")}, "TDMPCSettings.learning_rate must be a finite number > 0"),
        ({"horizon_start": 6}, "TDMPCSettings.horizon_start must be ≤ horizon = 5"),
        ({"evaluate_with": "mean"}, "TDMPCSettings.evaluate_with must be one of policy, plan"),
    ],
)
def test_bad_settings_name_the_field(change, message):
    with pytest.raises(EfficientTrackError, match=message):
        replace(TDMPCSettings(), **change)


def test_presets_keep_the_papers_settings_and_schedules():
    full = tdmpc_settings("paper")
    assert full == TDMPCSettings()
    assert (full.horizon, full.iterations, full.num_samples, full.num_elites, full.num_pi_samples) == (5, 6, 512, 64, 25)
    assert (full.batch_size, full.buffer_size, full.seed_steps, full.latent_dim, full.hidden) == (512, 180_000, 5000, 50, 512)
    assert (full.reward_coef, full.value_coef, full.consistency_coef, full.rho, full.discount) == (0.5, 0.1, 2.0, 0.5, 0.98)
    assert full.schedule(0) == (1, 0.5) and full.schedule(25_000) == (5, 0.05) and full.schedule(12_500)[0] == 3
    assert tdmpc_settings("tiny").latent_dim == 8 and tdmpc_settings("tiny").hidden == 32


def test_the_reduced_preset_changes_only_what_docs_tdmpc_lists():
    reduced, full = asdict(tdmpc_settings("cpu")), asdict(tdmpc_settings("paper"))
    changed = {field: value for field, value in reduced.items() if value != full[field]}
    assert changed == {
        "num_samples": 256,
        "num_elites": 32,
        "batch_size": 256,
        "hidden": 256,
        "schedule_steps": 5_000,
    }
    assert tdmpc_settings("cpu").num_pi_samples == 12 and tdmpc_settings("cpu").schedule(5_000) == (5, 0.05)


def test_an_untrained_policy_is_the_pd_controller_and_sees_the_shared_input(refs, tmp_path):
    train, test = refs
    settings = replace(TINY, evaluate_with="policy")
    curve = train_tdmpc(training_run("closed", SystemSpec(), train, test, 2, 0, tmp_path, eval_at=[1]), settings)
    pd = evaluate(lambda obs: np.zeros((len(obs), 4)), test, "closed", SystemSpec())
    assert curve[0]["metrics"]["mae_deg"] == pytest.approx(compute_metrics(pd)["mae_deg"], abs=1e-12)
    assert json.loads((tmp_path / "curve.json").read_text())["settings"]["inputs"] == "relative"
