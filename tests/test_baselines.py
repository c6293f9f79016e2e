"""The SB3 baselines: the VecEnv adapter equals N single environments, PPO and SAC train and give seeded curves."""

import ast
import dataclasses
import io
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium.vector import SyncVectorEnv
from stable_baselines3.common.vec_env import DummyVecEnv

from efficienttrack.baselines import PPOSettings, SACSettings, SB3VecEnv, default_eval_points, method_settings, train_baseline
from efficienttrack.baselines.curve import training_run
from efficienttrack.baselines.resume import STATE_FILE
from efficienttrack.baselines.sb3_state import restore_state, save_state
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.features import relative_features
from efficienttrack.data.metrics import METRIC_KEYS, compute_metrics
from efficienttrack.data.references import Reference
from efficienttrack.envs import TrackingEnv, TrackingVectorEnv, evaluate
from efficienttrack.envs.features import pd_pipeline, split_observation
from efficienttrack.learn.checkpoints import load_tensors
from efficienttrack.systems.spec import SystemSpec

TINY_PPO = PPOSettings(n_envs=2, n_steps=16, batch_size=16, n_epochs=1, net_arch=(8,), device="cpu")
TINY_SAC = SACSettings(buffer_size=1000, learning_starts=20, batch_size=8, net_arch=(8,), device="cpu")


@pytest.fixture(scope="module")
def refs():
    """Two training and two test references, cut short (40 and 30 steps) to keep training and evaluation fast."""
    cycles = generate_references(4, seed=1)
    return [Reference(r.name, r.q[:40]) for r in cycles[:2]], [Reference(r.name, r.q[:30]) for r in cycles[2:]]


def test_default_eval_points():
    assert default_eval_points(1500) == [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 1500]
    assert default_eval_points(1000) == [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000]
    assert default_eval_points(1) == [1]


def test_vec_env_equals_single_environments():
    refs = [Reference(r.name, r.q[: 12 + 3 * i]) for i, r in enumerate(generate_references(3, seed=2))]
    n = 3
    ours = SB3VecEnv(TrackingVectorEnv(n, refs=refs))
    singles = DummyVecEnv([lambda: TrackingEnv(refs=refs) for _ in range(n)])
    ours.seed(7)
    singles.seed(7)
    np.testing.assert_array_equal(ours.reset(), singles.reset())
    assert ours.observation_space == singles.observation_space and ours.action_space == singles.action_space
    actions = np.random.default_rng(0).uniform(-1, 1, (40, n, 4)).astype(np.float32)
    ended = 0
    for a in actions:
        obs, rewards, dones, infos = ours.step(a)
        obs_s, rewards_s, dones_s, infos_s = singles.step(a)
        np.testing.assert_array_equal(obs, obs_s)
        np.testing.assert_allclose(rewards, rewards_s, rtol=1e-6)
        assert rewards.dtype == np.float32 and dones.dtype == bool and obs.shape == (n, 332)
        np.testing.assert_array_equal(dones, dones_s)
        for i in range(n):
            assert infos[i].keys() == infos_s[i].keys()
            for key, value in infos[i].items():
                np.testing.assert_array_equal(value, infos_s[i][key], err_msg=key)
            assert infos[i]["TimeLimit.truncated"] == bool(dones[i])  # a reference's end is a truncation
            assert ("terminal_observation" in infos[i]) == bool(dones[i])
        for i in range(n):
            assert ours.reset_infos[i].keys() == singles.reset_infos[i].keys()
            for key, value in ours.reset_infos[i].items():
                np.testing.assert_array_equal(value, singles.reset_infos[i][key], err_msg=key)
        ended += int(dones.sum())
    assert ended >= n  # every environment finished at least one episode


def test_vec_env_needs_same_step_autoreset():
    with pytest.raises(EfficientTrackError, match="SAME_STEP"):
        SB3VecEnv(SyncVectorEnv([lambda: TrackingEnv() for _ in range(2)]))


def finite(metrics):
    return all(math.isfinite(metrics[key]) for key in METRIC_KEYS if key != "per_joint_mae_deg")


QUICK_RUNS = [("ppo", [1, 64, 132], [4, 64, 132]), ("sac", [1, 60, 100], [1, 60, 100])]
"""(method, eval_at, the interaction counts measured): PPO's quick preset steps 4 environments at a time."""


@pytest.mark.parametrize(("method", "eval_at", "measured"), QUICK_RUNS)
def test_quick_preset_trains_on_the_closed_loop(refs, tmp_path, method, eval_at, measured):
    train, test = refs
    budget = measured[-1]
    curve = train_baseline(method, training_run("closed", SystemSpec(), train, test, budget, 0, tmp_path, eval_at), "tiny")
    assert [p["interaction_steps"] for p in curve] == measured
    assert all(finite(p["metrics"]) and p["metrics"]["episodes"] == len(test) for p in curve)
    walls = [p["wall_seconds"] for p in curve]
    assert walls == sorted(walls) and walls[0] >= 0
    samples = [p["gradient_samples"] for p in curve]  # none before the first update (PPO: a rollout; SAC: 50 steps)
    assert samples == sorted(samples) and samples[0] == 0 and samples[-1] > 0
    if method == "ppo":  # the first rollout, 4 environments × 32 steps, and its 2 epochs, before the point at 132
        assert samples == [0, 0, 2 * 128]
    written = json.loads((tmp_path / "curve.json").read_text())
    assert (written["method"], written["loop"], written["seed"]) == (method, "closed", 0)
    assert written["curve"] == json.loads(json.dumps(curve))
    assert written["settings"]["n_envs"] == method_settings(method, "tiny").n_envs
    assert (tmp_path / "model.zip").stat().st_size > 0


def test_open_loop_trains_with_default_points_and_progress(refs, tmp_path):
    train, test = refs
    stream = io.StringIO()
    with ProgressDisplay(stream=stream, interval=0) as bar:
        run = training_run("open", SystemSpec(plant="xe75"), train, test, 40, 1, tmp_path)
        curve = train_baseline("ppo", run, TINY_PPO, progress=bar)
    # default points 1, 2, 5, 10, 20, 40, met when the count (2 environments) first reaches them
    assert [p["interaction_steps"] for p in curve] == [2, 6, 10, 20, 40]
    assert all(finite(p["metrics"]) for p in curve)
    assert "ppo open (steps) 40/40 mae_deg" in stream.getvalue()


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_same_seed_same_curve(refs, tmp_path, method):
    train, test = refs
    settings, budget = (TINY_PPO, 48) if method == "ppo" else (TINY_SAC, 40)  # past PPO's first update, SAC's first steps

    def metrics(seed, name):
        curve = train_baseline(
            method, training_run("closed", SystemSpec(), train, test, budget, seed, tmp_path / name, [budget]), settings
        )
        return curve[-1]["metrics"]

    first = metrics(3, "a")
    assert metrics(3, "b") == first
    assert metrics(4, "c") != first


def test_a_run_with_validation_references_measures_every_point_on_them_too(refs, tmp_path):
    train, test = refs
    validation = [Reference("val", generate_references(1, seed=5)[0].q[:25])]

    def curve(name, validation_refs):
        run = training_run("closed", SystemSpec(), train, test, 40, 3, tmp_path / name, [1, 20, 40], validation_refs)
        return train_baseline("sac", run, TINY_SAC)

    plain, validated, on_test = curve("plain", ()), curve("validated", validation), curve("on_test", test)
    # the test curve is the one without validation: the same agent met the test references first
    assert [(p["interaction_steps"], p["metrics"]) for p in validated] == [
        (p["interaction_steps"], p["metrics"]) for p in plain
    ]
    assert all("validation" not in p for p in plain)
    assert all(set(p) == {"interaction_steps", "wall_seconds", "metrics", "validation", "gradient_samples"} for p in validated)
    assert all(p["validation"]["episodes"] == 1 and finite(p["validation"]) for p in validated)
    pd = compute_metrics(evaluate(lambda obs: np.zeros((len(obs), 4)), validation, "closed", SystemSpec()))
    assert validated[0]["validation"]["mae_deg"] == pytest.approx(pd["mae_deg"], abs=1e-12)  # untrained: the PD controller
    assert all(p["validation"] == p["metrics"] for p in on_test)  # each point's own agent, on the references given
    assert json.loads((tmp_path / "validated" / "curve.json").read_text())["curve"] == json.loads(json.dumps(validated))
    with pytest.raises(EfficientTrackError, match="validation_refs: reference 'short' has 2 steps, needs at least 4"):
        training_run(
            "closed", SystemSpec(), train, test, 40, 3, tmp_path, validation_refs=[Reference("short", np.zeros((2, 4)))]
        )


RESUMED_RUNS = [
    ("ppo", TINY_PPO, [16, 48, 96], 64),
    ("sac", TINY_SAC, [10, 30, 60], 59),
    ("sac", dataclasses.replace(TINY_SAC, n_envs=4), [12, 32, 60], 56),  # a replay buffer of 4 columns, as `cpu`'s
]
"""Method, settings, points, and the count of the last state saved before the last point (a rollout's start)."""


@pytest.mark.parametrize(("method", "settings", "points", "saved_at"), RESUMED_RUNS, ids=["ppo", "sac", "sac-4-envs"])
def test_an_interrupted_run_resumes_from_its_training_state(
    refs, tmp_path, monkeypatch, interrupt_at, method, settings, points, saved_at
):
    train, test = refs

    def run(seed=0):
        spec = training_run("closed", SystemSpec(), train, test, points[-1], seed, tmp_path, points)
        return train_baseline(method, spec, settings, save_every_seconds=0)

    interrupt_at(points[-1])
    with pytest.raises(KeyboardInterrupt):
        run()
    monkeypatch.undo()
    assert load_tensors(tmp_path / STATE_FILE)["num_timesteps"] == saved_at
    before = json.loads((tmp_path / "curve.json").read_text())["curve"]
    assert [p["interaction_steps"] for p in before] == points[:-1]
    with pytest.raises(EfficientTrackError, match="training_state.pt: the training state of another run"):
        run(seed=1)
    curve = run()
    assert [p["interaction_steps"] for p in curve] == points
    assert curve[:-1] == before  # kept as measured (wall times too), not measured again
    assert curve[-1]["wall_seconds"] >= before[-1]["wall_seconds"] and finite(curve[-1]["metrics"])
    assert not (tmp_path / STATE_FILE).exists() and (tmp_path / "model.zip").exists()


@pytest.mark.parametrize("settings", [TINY_PPO, TINY_SAC], ids=["ppo", "sac"])
def test_a_restored_state_is_the_saved_one(refs, tmp_path, settings):
    env = SB3VecEnv(TrackingVectorEnv(settings.n_envs, refs=refs[0]))
    model = settings.build(env, seed=0)
    model.learn(total_timesteps=40)
    save_state(model, tmp_path / STATE_FILE, "run", [{"interaction_steps": 1}], 2.5)
    torch_draws, numpy_draws = torch.rand(3), np.random.rand(3)  # what the saved random states give next
    fresh = settings.build(env, seed=5)
    assert restore_state(fresh, tmp_path / STATE_FILE, "run") == ([{"interaction_steps": 1}], 2.5)
    assert torch.equal(torch.rand(3), torch_draws) and np.array_equal(np.random.rand(3), numpy_draws)
    for name, tensor in model.policy.state_dict().items():
        assert torch.equal(fresh.policy.state_dict()[name], tensor), name
    assert (fresh.num_timesteps, fresh._n_updates) == (model.num_timesteps, model._n_updates) and model._n_updates > 0
    if settings is TINY_SAC:
        filled = model.replay_buffer.pos
        assert filled == 40 and fresh.replay_buffer.pos == filled
        np.testing.assert_array_equal(fresh.replay_buffer.observations[:filled], model.replay_buffer.observations[:filled])
        assert torch.equal(fresh.log_ent_coef, model.log_ent_coef)
    with pytest.raises(EfficientTrackError, match="another run"):
        restore_state(fresh, tmp_path / STATE_FILE, "another")
    (tmp_path / "junk.pt").write_bytes(b"not a state")
    with pytest.raises(EfficientTrackError, match="junk.pt: refused to load"):
        restore_state(fresh, tmp_path / "junk.pt", "run")
    torch.save({"run": "run", "modules": {}}, tmp_path / "partial.pt")
    with pytest.raises(EfficientTrackError, match=r"partial.pt: a damaged training state \(KeyError"):
        restore_state(fresh, tmp_path / "partial.pt", "run")
    env.close()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"method": "td3"}, "method 'td3': unknown"),
        ({"loop": "half"}, "loop: unknown loop 'half'"),
        ({"budget": 0}, "budget: must be an integer ≥ 1"),
        ({"budget": 2.5}, "budget: must be an integer ≥ 1"),
        ({"eval_at": [5, 101]}, r"eval_at: each point must be an integer in \[1, budget = 100\], got 101"),
        ({"eval_at": []}, "eval_at: no evaluation point given"),
        ({"preset": "huge"}, "preset 'huge': unknown for ppo"),
        ({"preset": TINY_SAC}, "ppo takes a preset name or PPOSettings, got SACSettings"),
        ({"seed": -1}, "seed: a seed must be an integer"),
        ({"train_refs": []}, "train_refs: no references given"),
    ],
)
def test_bad_input_is_refused_before_training(refs, tmp_path, change, message):
    args = {"method": "ppo", "loop": "closed", "system": SystemSpec(), "train_refs": refs[0], "test_refs": refs[1]}
    args |= {"budget": 100, "seed": 0, "folder": tmp_path / "out", "preset": "tiny", "eval_at": None} | change
    with pytest.raises(EfficientTrackError, match=message):
        train_baseline(args.pop("method"), preset=args.pop("preset"), run=training_run(**args))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (lambda: PPOSettings(n_envs=0), "PPOSettings.n_envs must be an integer ≥ 1, got 0"),
        (lambda: PPOSettings(gamma=1.5), r"PPOSettings.gamma must be a finite number in \[0, 1\], got 1.5"),
        (lambda: PPOSettings(net_arch=()), "PPOSettings.net_arch must be a list of at least one integer ≥ 1"),
        (lambda: SACSettings(learning_rate=float("nan")), "SACSettings.learning_rate must be a finite number > 0"),
        (lambda: SACSettings(learning_starts=-1), "SACSettings.learning_starts must be an integer ≥ 0"),
        (lambda: SACSettings(ent_coef=0.0), "SACSettings.ent_coef must be a finite number > 0"),
    ],
)
def test_bad_settings_name_the_field(settings, message):
    with pytest.raises(EfficientTrackError, match=message):
        settings()


def test_presets_keep_the_papers_settings():
    assert method_settings("ppo").n_envs == 16
    assert method_settings("sac").buffer_size == 100_000
    assert method_settings("ppo", "tiny").n_envs < 16 and method_settings("sac", "tiny").net_arch == (32, 32)


def test_the_sac_cpu_preset_takes_one_gradient_step_per_four_interaction_steps():
    cpu = method_settings("sac", "cpu")
    assert (cpu.n_envs, cpu.train_freq, cpu.gradient_steps, cpu.batch_size) == (4, 1, 1, 256)
    assert (cpu.gamma, cpu.learning_rate, cpu.net_arch) == (0.98, 3e-5, (256, 256))  # the research code's γ and rate
    assert method_settings("sac", "sb3") == SACSettings() == SACSettings(n_envs=1, learning_rate=3e-4, gamma=0.99)


def test_the_ppo_cpu_preset_updates_every_4096_steps_and_explores_near_the_reference():
    cpu = method_settings("ppo", "cpu")
    assert (cpu.n_envs * cpu.n_steps, cpu.batch_size, cpu.n_epochs) == (4096, 512, 10)
    assert (cpu.gamma, cpu.gae_lambda, cpu.learning_rate) == (0.98, 0.95, 3e-4)
    assert math.exp(cpu.log_std_init) == pytest.approx(0.2, abs=0.005)  # SB3's default: σ = 1, the whole action range
    assert method_settings("ppo", "sb3") == PPOSettings() == PPOSettings(n_steps=2048, batch_size=64, log_std_init=0.0)


DOCS = Path(__file__).resolve().parents[1] / "docs" / "baselines.md"


def documented_presets(title: str) -> dict[str, dict[str, object]]:
    """The preset table under ``title`` in docs/baselines.md: {preset: {field: value}} (``a``, ``b`` rows give both)."""
    lines = DOCS.read_text().split(title, 1)[1].strip().splitlines()
    header = [cell.strip(" `") for cell in lines[0].strip("|").split("|")]
    presets: dict[str, dict[str, object]] = {name: {} for name in ("paper", "cpu", "sb3", "tiny")}
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        fields = re.findall(r"`(\w+)`", cells[0].split(":")[0])
        for name in presets:
            text = re.sub(r"(?<=\d),(?=\d{3}\b)", "", cells[header.index(name)])  # 100,000 → 100000
            value = text if text == "relative" else ast.literal_eval(text)
            values = value if len(fields) > 1 else (value,)
            presets[name] |= dict(zip(fields, values, strict=True))
    return presets


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_the_docs_preset_tables_match_the_code(method):
    documented = documented_presets(f"{method.upper()} (SB3 `{method.upper()}`, `MlpPolicy`):")
    for preset, values in documented.items():
        settings = dataclasses.asdict(method_settings(method, preset))
        settings.pop("device")  # "auto" everywhere, described in the text
        assert values == settings, f"{method} {preset}"


def test_the_paper_presets_carry_the_research_codes_settings():
    sac, ppo = method_settings("sac", "paper"), method_settings("ppo", "paper")
    assert (sac.gamma, sac.batch_size, sac.learning_rate, sac.net_arch) == (0.98, 4096, 3e-5, (512, 512, 512, 128))
    assert (ppo.gamma, ppo.gae_lambda, ppo.learning_rate, ppo.clip_range) == (0.98, 0.99, 3e-5, 3.0)
    assert ppo.n_envs * ppo.n_steps == ppo.batch_size == 4096  # one batch of parallel episodes per update
    assert all(method_settings(m, p).inputs == "relative" for m in ("ppo", "sac") for p in ("paper", "cpu", "sb3", "tiny"))


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_an_untrained_baseline_is_the_pd_controller(refs, tmp_path, method):
    train, test = refs
    settings = TINY_PPO if method == "ppo" else TINY_SAC
    curve = train_baseline(method, training_run("closed", SystemSpec(), train, test, 2, 0, tmp_path, eval_at=[1]), settings)
    pd = evaluate(lambda obs: np.zeros((len(obs), 4)), test, "closed", SystemSpec())
    assert curve[0]["metrics"]["mae_deg"] == pytest.approx(compute_metrics(pd)["mae_deg"], abs=1e-12)


def test_the_observation_pipeline_is_the_networks_input_standardized_on_a_pd_pass(refs):
    train, _ = refs
    pipeline = pd_pipeline("closed", SystemSpec(), train)
    seen = []
    evaluate(lambda obs: (seen.append(obs), np.zeros((len(obs), 4)))[1], train, "closed", SystemSpec())
    flat = np.concatenate(seen)
    features = pipeline(flat)
    assert features.shape == (len(flat), pipeline.size) and features.dtype == np.float32
    np.testing.assert_allclose(features.mean(axis=0), 0.0, atol=1e-4)  # standardized on exactly this pass
    varying = pipeline.std != 1.0
    np.testing.assert_allclose(features[:, varying].std(axis=0), 1.0, atol=1e-3)
    obs_hist, second, future = split_observation(flat, 21, 20)
    as_torch = relative_features(*(torch.as_tensor(x) for x in (obs_hist, second, future))).numpy()
    np.testing.assert_allclose(pipeline.features(flat), as_torch, rtol=0, atol=1e-12)  # the networks' own features
