import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import push
from efficienttrack.learn import dynamics
from efficienttrack.learn.dynamics import ClosedLoopModel, load_model, model_error, rollout, save_model
from efficienttrack.learn.settings import MODEL_PRESETS, ModelConfig
from efficienttrack.learn.training import read_scalars

LAG_GAIN = np.array([0.3, 0.5, 0.4, 0.6])
"""Per-joint fraction of the reference error closed per step in the synthetic system."""


def lag_records(n: int = 8, T: int = 100, sigma: float = 0.02, seed: int = 0) -> list[EpisodeRecord]:
    """Episodes of a linear closed-loop system with lag, q[t+1] = q[t] + k (q_ref[t] − q[t]), tracking sinusoids.

    q_ref = q_des + σ·clip(N(0, 1), −1, 1), qd[t] = (q[t] − q[t−1]) / dt (0 at t = 0).
    """
    rng = np.random.default_rng(seed)
    records = []
    for _ in range(n):
        time = np.arange(T + 1)[:, None] * 0.05
        amp, freq, phase = rng.uniform(0.2, 0.6, 4), rng.uniform(0.2, 0.5, 4), rng.uniform(0, 2 * np.pi, 4)
        ref = amp * np.sin(2 * np.pi * freq * time + phase)
        q_des = ref[1:]
        q_ref = q_des + sigma * np.clip(rng.normal(size=(T, 4)), -1, 1)
        q = np.empty((T, 4))
        q[0] = ref[0]
        for t in range(T - 1):
            q[t + 1] = q[t] + LAG_GAIN * (q_ref[t] - q[t])
        qd = np.vstack([np.zeros((1, 4)), np.diff(q, axis=0) / 0.05])
        records.append(EpisodeRecord(q=q, qd=qd, q_ref=q_ref, q_des=q_des, u=None, t=time[:T, 0]).validate())
    return records


def train_tiny_model(records, seed: int = 0, **changes):
    cfg = dataclasses.replace(MODEL_PRESETS["tiny"], **changes)
    return dynamics.train_model(cfg, records, device="cpu", seed=seed, progress=False)


@pytest.fixture(scope="module")
def trained(lag_model):
    """``train_tiny_model(lag_records())``: the session's ``lag_model`` (conftest.py), trained once for three modules."""
    return lag_model


@pytest.mark.parametrize("history", [None, 2])
def test_batched_rollout_equals_loop_of_single_steps(history):
    torch.manual_seed(1)
    model = ClosedLoopModel(dataclasses.replace(MODEL_PRESETS["tiny"], horizon=3, history=history)).eval()
    n = model.cfg.history_length
    B, H = 5, 6
    obs_hist, qref_hist, qref_future = torch.randn(B, 3, 8), torch.randn(B, 3, 4), torch.randn(B, H, 4)
    with torch.no_grad():
        batched = rollout(model, obs_hist, qref_hist, qref_future)
        for b in range(B):
            o_H, r_H = obs_hist[b : b + 1], qref_hist[b : b + 1]
            for i in range(H):
                x = dynamics.relative_features(o_H[:, -n:], r_H[:, -n:], qref_future[b : b + 1, i : i + 1])
                o_hat = o_H[:, -1] + model.g_theta(model.features(x))
                torch.testing.assert_close(batched[b, i], o_hat[0], rtol=0, atol=1e-5)
                o_H, r_H = push(o_H, o_hat), push(r_H, qref_future[b : b + 1, i])


def test_model_learns_linear_lag_system(trained):
    test = lag_records(n=4, seed=1)
    mpe = model_error(trained.model, test, steps=20)
    assert mpe.windows == 4 * (100 - 20)
    assert len(mpe.per_step_deg) == 20 and len(mpe.per_joint_deg) == 4
    assert mpe.mpe_deg == pytest.approx(np.mean(mpe.per_step_deg)) == pytest.approx(np.mean(mpe.per_joint_deg))
    # "hold the last position" predictor, for scale
    hold = np.mean([np.abs(np.rad2deg(r.q[1 + s : 81 + s] - r.q[:80])).mean() for r in test for s in range(20)])
    assert hold > 5.0
    assert mpe.mpe_deg < 0.6, mpe
    assert mpe.mpe_deg < 0.1 * hold
    assert np.isfinite(trained.losses).all() and trained.losses[-20:].mean() < 0.1 * trained.losses[:20].mean()


def test_training_is_deterministic_and_seeded():
    records = lag_records(n=2, T=40)
    a, b, c = (train_tiny_model(records, seed=s, steps=15) for s in (0, 0, 1))
    np.testing.assert_array_equal(a.losses, b.losses)
    for (name, pa), pb in zip(a.model.state_dict().items(), b.model.state_dict().values(), strict=True):
        assert torch.equal(pa, pb), name
    assert not np.array_equal(a.losses, c.losses)


def test_interrupted_training_resumes_to_the_same_model(tmp_path, monkeypatch, capsys):
    records = lag_records(n=2, T=40)
    cfg = dataclasses.replace(MODEL_PRESETS["tiny"], steps=30, save_every=10)
    full = dynamics.train_model(cfg, records, device="cpu", progress=False)
    ckpt = tmp_path / "state.pt"
    original = dynamics.TrainLoop.record

    def crash_at_25(self, step, loss):
        if step == 25:
            raise KeyboardInterrupt
        original(self, step, loss)

    monkeypatch.setattr(dynamics.TrainLoop, "record", crash_at_25)
    with pytest.raises(KeyboardInterrupt):
        dynamics.train_model(cfg, records, device="cpu", progress=False, checkpoint=ckpt)
    monkeypatch.setattr(dynamics.TrainLoop, "record", original)
    capsys.readouterr()
    resumed = dynamics.train_model(cfg, records, device="cpu", progress=True, checkpoint=ckpt)
    assert f"train model (resumed at step 20 from {ckpt})" in capsys.readouterr().out
    np.testing.assert_array_equal(resumed.losses, full.losses)
    for pa, pb in zip(full.model.state_dict().values(), resumed.model.state_dict().values(), strict=True):
        assert torch.equal(pa, pb)
    other = dataclasses.replace(cfg, lr=1e-4)
    with pytest.raises(EfficientTrackError, match=r"another run \(config lr: 0.003 here, 0.0001 now\)"):
        dynamics.train_model(other, records, device="cpu", progress=False, checkpoint=ckpt)
    # the finished state is not silently reused for other data or another seed
    with pytest.raises(EfficientTrackError, match="another run"):
        dynamics.train_model(cfg, lag_records(n=2, T=40, seed=1), device="cpu", progress=False, checkpoint=ckpt)
    with pytest.raises(EfficientTrackError, match="another run"):
        dynamics.train_model(cfg, records, device="cpu", seed=1, progress=False, checkpoint=ckpt)


def test_save_load_round_trip(trained, tmp_path):
    path = save_model(trained.model, tmp_path / "model.pt")
    assert json.loads((tmp_path / "model.json").read_text())["config"]["hidden"] == trained.model.cfg.hidden
    loaded = load_model(path)
    x = (torch.randn(7, 4, 8), torch.randn(7, 4, 4), torch.randn(7, 4))
    with torch.no_grad():
        assert torch.equal(trained.model(*x), loaded(*x))


class Payload:
    def __reduce__(self):
        return (print, ("this ran code",))


def test_load_refuses_a_config_written_for_other_weights(trained, tmp_path):
    save_model(trained.model, tmp_path / "model.pt")
    save_model(trained.model, tmp_path / "other.pt")
    config = tmp_path / "model.json"
    config.write_text(config.read_text().replace('"weights_sha256": "', '"weights_sha256": "0'))
    with pytest.raises(EfficientTrackError, match="written for other weights"):
        load_model(tmp_path / "model.pt")
    load_model(tmp_path / "other.pt")


def test_config_rejects_non_finite_values():
    with pytest.raises(EfficientTrackError, match="lr must be a finite number"):
        ModelConfig(lr=float("nan"))


def test_load_refuses_code_and_non_state_dicts(trained, tmp_path):
    save_model(trained.model, tmp_path / "model.pt")
    torch.save({"weights": Payload()}, tmp_path / "model.pt")
    with pytest.raises(EfficientTrackError, match="refused to load"):
        load_model(tmp_path / "model.pt")
    torch.save([torch.zeros(3)], tmp_path / "model.pt")
    with pytest.raises(EfficientTrackError, match="expected a dict"):
        load_model(tmp_path / "model.pt")
    (tmp_path / "other.pt").write_bytes(b"")
    with pytest.raises(EfficientTrackError, match="config .* is missing"):
        load_model(tmp_path / "other.pt")


def test_config_validation():
    cfg = ModelConfig.from_dict({"hidden": 64, "steps": 10, "grad_clip": None}, "x.json")
    assert cfg.hidden == 64 and cfg.grad_clip is None and cfg.total_steps(10**6) == 10
    assert MODEL_PRESETS["paper"].total_steps(176_720 - 400 * 20) == 2000 * math.ceil((176_720 - 8000) / 2048)
    with pytest.raises(EfficientTrackError, match="unknown ModelConfig field"):
        ModelConfig.from_dict({"hiden": 64}, "x.json")
    with pytest.raises(EfficientTrackError, match="x.json: hidden must be an integer in \\[1, 8192\\], got '64'"):
        ModelConfig.from_dict({"hidden": "64"}, "x.json")
    with pytest.raises(EfficientTrackError, match="exactly one of steps and epochs"):
        ModelConfig(steps=None, epochs=None)


def test_cli_train_model_and_model_error(tmp_path):
    from typer.testing import CliRunner

    from efficienttrack.cli import app
    from efficienttrack.data.records import save_records

    save_records(lag_records(n=2, T=40), tmp_path / "data")
    save_records(lag_records(n=1, T=40, seed=1), tmp_path / "held_out")
    runner = CliRunner()
    out = tmp_path / "model.pt"
    args = ["train-model", "--data", str(tmp_path / "data"), "--out", str(out), "--preset", "tiny", "--steps", "5"]
    result = runner.invoke(app, [*args, "--held-out", str(tmp_path / "held_out")])
    assert result.exit_code == 0, result.output
    assert out.is_file() and (tmp_path / "model.json").is_file() and (tmp_path / "model.state.pt").is_file()
    scalars = read_scalars(tmp_path / "model.logs")
    assert scalars["train/loss"][0].tolist() == [1, 2, 3, 4, 5]
    assert scalars[dynamics.HELD_OUT_TAG][0].tolist() == [1, 2, 3, 4, 5]  # a tenth of 5 steps: every step
    result = runner.invoke(app, ["model-error", "--model", str(out), "--data", str(tmp_path / "data"), "--json"])
    assert result.exit_code == 0, result.output
    mpe = json.loads(result.output.strip().splitlines()[-1])
    assert set(mpe) == {"mpe_deg", "per_joint_deg", "per_step_deg", "windows"}
    assert len(mpe["per_step_deg"]) == 20 and mpe["windows"] == 2 * (40 - 20)
