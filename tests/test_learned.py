import dataclasses
import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import save_records
from efficienttrack.learn.dynamics import ClosedLoopModel, rollout, save_model
from efficienttrack.learn.learned_system import LearnedSystem
from efficienttrack.learn.settings import MODEL_PRESETS
from efficienttrack.systems import check_system, load_system
from efficienttrack.systems.fit import fidelity
from test_dynamics import lag_records


@pytest.fixture(scope="module")
def trained(lag_model):
    """``train_tiny_model(lag_records()).model``: the session's ``lag_model`` (conftest.py)."""
    return lag_model.model


def random_model(history: int | None = 3) -> ClosedLoopModel:
    torch.manual_seed(2)
    return ClosedLoopModel(dataclasses.replace(MODEL_PRESETS["tiny"], horizon=3, history=history)).eval()


@pytest.mark.parametrize("history", [None, 3])
def test_learned_system_steps_as_the_model_rolls_out_from_rest(history):
    model = random_model(history)
    rng = np.random.default_rng(0)
    q0, q_ref = rng.uniform(-0.5, 0.5, (5, 4)), rng.uniform(-0.5, 0.5, (7, 5, 4))
    system = LearnedSystem(model, device="cpu")
    obs0 = system.reset(q0)
    obs = np.stack([system.step(r) for r in q_ref])
    np.testing.assert_array_equal(obs0, np.hstack([q0, np.zeros((5, 4))]))
    h = model.cfg.history_length
    start = torch.as_tensor(obs0, dtype=torch.float32)[:, None].repeat(1, h, 1)
    refs = torch.as_tensor(q0, dtype=torch.float32)[:, None].repeat(1, h, 1)
    with torch.no_grad():
        expected = rollout(model, start, refs, torch.as_tensor(q_ref, dtype=torch.float32).transpose(0, 1))
    # float32: stepwise and batched products round alike on one machine, to ~20 ulps apart on another CPU or torch
    np.testing.assert_allclose(obs, expected.transpose(0, 1).numpy(), rtol=0, atol=1e-5)


def test_learned_system_takes_single_machines_and_wraps_the_swing():
    model = random_model()
    with torch.no_grad():  # a model that turns the swing by 0.3 rad per step
        model.g_theta.out_scale.zero_()
        model.g_theta.out_scale[3] = 0.3
        model.g_theta.body[-1].bias.fill_(10.0)
    system = LearnedSystem(model, device="cpu")
    assert system.reset(np.array([0.1, 0.2, 0.3, 3.0])).shape == (8,)
    obs = np.stack([system.step(np.zeros(4)) for _ in range(3)])
    assert obs.shape == (3, 8)
    np.testing.assert_allclose(obs[:, 3], [3.3 - 2 * np.pi, 3.6 - 2 * np.pi, 3.9 - 2 * np.pi], atol=1e-4)
    check_system(LearnedSystem(random_model(), device="cpu"))


def test_learned_system_restarts_some_machines_while_the_others_run_on():
    model = random_model()
    rng = np.random.default_rng(1)
    q0, q_new, q_ref = rng.uniform(-0.5, 0.5, (3, 4)), rng.uniform(-0.5, 0.5, (1, 4)), rng.uniform(-0.5, 0.5, (7, 3, 4))
    restarted, uninterrupted, fresh = (LearnedSystem(model, device="cpu") for _ in range(3))
    restarted.reset(q0)
    uninterrupted.reset(q0)
    for r in q_ref[:4]:
        restarted.step(r)
        uninterrupted.step(r)
    np.testing.assert_array_equal(restarted.reset_machines(np.array([1]), q_new), fresh.reset(q_new))
    after = np.stack([restarted.step(r) for r in q_ref[4:]])
    np.testing.assert_allclose(after[:, [0, 2]], np.stack([uninterrupted.step(r) for r in q_ref[4:]])[:, [0, 2]], atol=1e-6)
    np.testing.assert_allclose(after[:, 1], np.stack([fresh.step(r[1:2]) for r in q_ref[4:]])[:, 0], atol=1e-6)


def test_the_vector_env_runs_episodes_side_by_side_on_a_learned_system(tmp_path):
    from efficienttrack.data.references import Reference
    from efficienttrack.envs import TrackingVectorEnv

    save_model(random_model(), tmp_path / "model.pt")
    refs = [Reference(f"r{k}", np.linspace(0, 0.1 * (k + 1), 6 + 3 * k)[:, None].repeat(4, 1)) for k in range(2)]
    vec = TrackingVectorEnv(2, system="learned", system_opts={"model": str(tmp_path / "model.pt")}, refs=refs)
    vec.reset(seed=0, options={"reference": [0, 1]})
    ends = []
    for t in range(1, 10):  # the short episode ends and restarts alone while the long one runs on to its own end
        _, reward, terminated, truncated, _ = vec.step(np.zeros((2, 4)))
        assert np.isfinite(reward).all()
        ends += [(t, k) for k in np.flatnonzero(terminated | truncated)]
    assert ends[:2] == [(len(refs[0]) - 1, 0), (len(refs[1]) - 1, 1)]


def test_learned_system_reports_misuse():
    system = LearnedSystem(random_model(), device="cpu")
    with pytest.raises(EfficientTrackError, match="before reset"):
        system.step(np.zeros(4))
    with pytest.raises(EfficientTrackError, match="q0 of shape"):
        system.reset(np.zeros(3))
    system.reset(np.zeros((2, 4)))
    with pytest.raises(EfficientTrackError, match=r"q_ref of shape \(2, 4\)"):
        system.step(np.zeros((3, 4)))
    system.reset(np.zeros(4))
    with pytest.raises(EfficientTrackError, match="needs a batched reset"):
        system.reset_machines(np.array([0]), np.zeros((1, 4)))
    with pytest.raises(EfficientTrackError, match="dt"):
        LearnedSystem(random_model(), dt=0.0)


def test_a_trained_model_as_system_matches_the_machine_it_learned(trained, tmp_path):
    records = lag_records(n=4, seed=1)
    save_model(trained, tmp_path / "model.pt")
    learned = fidelity(records, load_system("learned", model=str(tmp_path / "model.pt")))
    untrained = fidelity(records, load_system("learned", model=str(save_model(random_model(), tmp_path / "r.pt"))))
    np.testing.assert_allclose(learned.ratio, 1.0, atol=0.15)
    assert np.abs(untrained.ratio - 1.0).max() > 0.5


def test_cli_fidelity_of_a_learned_model(trained, tmp_path):
    save_records(lag_records(n=2, T=60, seed=3), tmp_path / "logs")
    save_model(trained, tmp_path / "model.pt")
    args = ["sim", "fidelity", "--logs", str(tmp_path / "logs"), "--system", "learned"]
    result = CliRunner().invoke(app, [*args, "--system-opt", f"model={tmp_path / 'model.pt'}", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output.strip().splitlines()[-1])
    assert report["open_loop"]["mpe20_deg"] is None
    assert len(report["closed_loop"]["ratio"]) == 4 and all(0.5 < r < 2.0 for r in report["closed_loop"]["ratio"])
    result = CliRunner().invoke(app, [*args, "--system-opt", f"model={tmp_path / 'missing.pt'}"])
    assert result.exit_code != 0 and "missing.pt" in str(result.exception or result.output)
