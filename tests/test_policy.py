import copy
import dataclasses
import json

import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import plain_form
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.windows import initial_history, push_observation, push_reference
from efficienttrack.learn.policy import (
    AdjustmentPolicy,
    ImaginedDeployments,
    cap_row_gradients,
    load_policy,
    path_roughness,
    policy_rollout,
    predicted_tracking_error,
    save_policy,
    seen_lengths,
    train_policy,
)
from efficienttrack.learn.settings import POLICY_PRESETS, PolicyConfig
from test_dynamics import LAG_GAIN, lag_records


@pytest.fixture(scope="module")
def model(lag_model):
    """``train_tiny_model(lag_records()).model``: a copy of the session's ``lag_model`` (conftest.py), which
    ``train_policy`` freezes."""
    return copy.deepcopy(lag_model.model)


@pytest.fixture(scope="module")
def trained(model):
    """The quick preset (imagined deployments on, the default) at half its steps: 100 steps leave 0.53-0.55 of the
    predicted and 0.23-0.25 of the true tracking error at seeds 0-2 (200 steps: 0.52-0.53 and 0.22-0.23)."""
    return train_policy(dataclasses.replace(POLICY_PRESETS["tiny"], steps=100), model, lag_records(), "cpu", progress=False)


def track_lag_system(policy, records):
    """Closed-loop MAE (deg) of the true lag system tracking the records' q_des, Algorithm 2 with ``policy`` (None: a = 0)."""
    q_des = np.stack([r.q_des for r in records])
    N, T, _ = q_des.shape
    h, F = seen_lengths(policy.cfg if policy is not None else None)
    future = np.concatenate([q_des, np.repeat(q_des[:, -1:], F, 1)], 1)
    q, qd = np.stack([r.q[0] for r in records]), np.zeros((N, 4))
    hist = initial_history(np.concatenate([q, qd], 1), h)
    errors = []
    for t in range(T - 1):
        hist = push_observation(hist, np.concatenate([q, qd], 1))
        a = np.zeros((N, 4))
        if policy is not None:
            with torch.no_grad():
                a = (
                    policy(*(torch.as_tensor(x, dtype=torch.float32) for x in (hist.obs, hist.q_ref, future[:, t : t + F])))
                    .double()
                    .numpy()
                )
        q_ref = q_des[:, t] + a
        hist = push_reference(hist, q_ref)
        q_next = q + LAG_GAIN * (q_ref - q)
        q, qd = q_next, (q_next - q) / 0.05
        errors.append(np.abs(q - q_des[:, t]))
    return float(np.rad2deg(np.mean(errors)))


def test_policy_cuts_predicted_and_true_tracking_error(model, trained):
    test = lag_records(n=4, seed=1, sigma=0.0)
    before = predicted_tracking_error(model, test, None, steps=4)
    after = predicted_tracking_error(model, test, trained.policy, steps=4)
    # from recorded (already lagging) starts: at least 35 % less model-predicted error over the 4 steps
    assert after.mae_deg < 0.65 * before.mae_deg, (before, after)
    # on the true system, closed loop (Algorithm 2): at least 55 % less tracking error than the lagging loop alone
    pd_mae, policy_mae = track_lag_system(None, test), track_lag_system(trained.policy, test)
    assert pd_mae > 1.5
    assert policy_mae < 0.45 * pd_mae, (pd_mae, policy_mae)


def test_a_rollout_split_in_two_at_its_histories_is_the_rollout_in_one(model):
    torch.manual_seed(0)
    policy = AdjustmentPolicy(POLICY_PRESETS["tiny"])
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.1)
    obs_hist, qref_hist, q_star = torch.randn(3, 4, 8) * 0.1, torch.randn(3, 4, 4) * 0.1, torch.randn(3, 12, 4) * 0.1
    with torch.no_grad():
        whole = policy_rollout(model, policy, obs_hist, qref_hist, q_star, steps=9)
        first = policy_rollout(model, policy, obs_hist, qref_hist, q_star, steps=4)
        second = policy_rollout(model, policy, first.obs_hist, first.qref_hist, q_star[:, 4:], steps=5)
    torch.testing.assert_close(torch.cat([first.q_hat, second.q_hat], 1), whole.q_hat)
    torch.testing.assert_close(torch.cat([first.a, second.a], 1), whole.a)


def test_a_cut_rollout_predicts_the_same_and_a_truncated_one_credits_an_action_with_k_steps_at_most(model):
    torch.manual_seed(0)
    policy = AdjustmentPolicy(POLICY_PRESETS["tiny"])
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.1)
    obs_hist = (torch.randn(3, 4, 8) * 0.1).requires_grad_(True)
    qref_hist, q_star = torch.randn(3, 4, 4) * 0.1, torch.randn(3, 12, 4) * 0.1
    whole = policy_rollout(model, policy, obs_hist, qref_hist, q_star, steps=9)
    cut = policy_rollout(model, policy, obs_hist, qref_hist, q_star, steps=9, truncate=3)
    capped = policy_rollout(model, policy, obs_hist, qref_hist, q_star, steps=9, row_cap=2.0)
    for other in (cut, capped):  # the same predictions: only the gradient is cut
        torch.testing.assert_close(other.q_hat, whole.q_hat)
        torch.testing.assert_close(other.a, whole.a)

    def reach(rollout, step):
        return torch.autograd.grad(rollout.q_hat[:, step].sum(), obs_hist, retain_graph=True)[0].abs().sum().item()

    assert reach(cut, 2) > 0 and reach(whole, 3) > 0 and reach(whole, 8) > 0 and reach(capped, 8) > 0
    assert reach(cut, 3) == 0 and reach(cut, 8) == 0  # past the first cut the start gets no gradient


def test_a_row_gradient_cap_passes_values_and_cuts_only_the_rows_above_its_share_of_the_median():
    x = torch.zeros(5, 2, requires_grad=True)
    weights = torch.tensor([[1.0, 0.0], [0.0, 2.0], [3.0, 0.0], [0.0, 4.0], [300.0, 400.0]])  # row norms 1, 2, 3, 4, 500
    capped = cap_row_gradients(x, 2.0)
    assert torch.equal(capped, x)
    (capped * weights).sum().backward()
    norms = x.grad.norm(dim=1)
    torch.testing.assert_close(norms, torch.tensor([1.0, 2.0, 3.0, 4.0, 6.0]))  # 2 × the median 3: only the last is cut
    torch.testing.assert_close(x.grad[4] / norms[4], torch.tensor([0.6, 0.8]))  # its direction kept
    y = torch.zeros(3, 2, requires_grad=True)
    (cap_row_gradients(y, 2.0) * torch.tensor([[0.0, 0.0], [0.0, 0.0], [5.0, 0.0]])).sum().backward()
    assert y.grad[2, 0] == 5.0  # a median of zero cuts nothing


@pytest.mark.parametrize("field, value", [("truncate", 2), ("row_cap", 3.0)])
def test_a_policy_trained_with_its_rollout_gradient_cut_cuts_the_true_tracking_error(model, field, value):
    cfg = dataclasses.replace(POLICY_PRESETS["tiny"], steps=60, **({"row_cap": 0.0} | {field: value}))  # each cut alone
    assert plain_form(cfg)[field] == value
    trained = train_policy(cfg, model, lag_records(), device="cpu", progress=False)
    test = lag_records(n=4, seed=1, sigma=0.0)
    pd_mae, policy_mae = track_lag_system(None, test), track_lag_system(trained.policy, test)
    assert policy_mae < 0.45 * pd_mae, (pd_mae, policy_mae)


@pytest.mark.parametrize("share", [1.0, 0.5])
def test_a_policy_trained_after_a_burn_in_cuts_the_true_tracking_error(model, share):
    # 60 steps: 0.23-0.27 of the lagging loop's error at seeds 0-2, as 200 steps (0.20-0.24)
    cfg = dataclasses.replace(POLICY_PRESETS["tiny"], burn_in=6, burn_in_share=share, imagined_share=0.0, steps=60)
    assert plain_form(cfg)["burn_in"] == 6 and "burn_in" not in plain_form(POLICY_PRESETS["tiny"])  # old folders resume
    trained = train_policy(cfg, model, lag_records(), device="cpu", progress=False)
    test = lag_records(n=4, seed=1, sigma=0.0)
    pd_mae, policy_mae = track_lag_system(None, test), track_lag_system(trained.policy, test)
    assert policy_mae < 0.45 * pd_mae, (pd_mae, policy_mae)
    assert trained.windows == sum(len(r.q) - 6 for r in lag_records())  # B steps still within each episode


def test_a_policy_trained_on_imagined_deployments_cuts_the_true_tracking_error(trained):
    cfg = POLICY_PRESETS["tiny"]
    assert cfg.imagined_share == 0.5 and plain_form(cfg)["imagined_share"] == 0.5  # the default, in every preset
    assert trained.policy.cfg.imagined_share == 0.5  # the module's policy: trained on imagined deployments
    test = lag_records(n=4, seed=1, sigma=0.0)
    pd_mae, policy_mae = track_lag_system(None, test), track_lag_system(trained.policy, test)
    assert policy_mae < 0.45 * pd_mae, (pd_mae, policy_mae)
    with pytest.raises(EfficientTrackError, match=r"burn_in \(2\) and imagined_share \(0.5\).*imagined_share=0"):
        dataclasses.replace(cfg, burn_in=2)


def test_a_policy_from_before_imagined_deployments_and_the_cap_reads_back_as_trained_without_them(tmp_path):
    assert all(cfg.row_cap == 10.0 for cfg in POLICY_PRESETS.values())  # the cap: the default, in every preset
    assert "truncate" not in plain_form(POLICY_PRESETS["tiny"])  # the cut: off, as before it was a setting
    paper_way = dataclasses.replace(POLICY_PRESETS["tiny"], imagined_share=0.0, row_cap=0.0)
    assert not {"imagined_share", "row_cap"} & set(plain_form(paper_way))  # stored as from before the fields were
    save_policy(AdjustmentPolicy(paper_way), tmp_path / "policy.pt")
    loaded = load_policy(tmp_path / "policy.pt", device="cpu").cfg
    assert (loaded.imagined_share, loaded.row_cap) == (0.0, 0.0)  # not today's defaults, 0.5 and 10


def test_imagined_deployments_go_on_from_the_model_and_restart_at_an_episode_start(model):
    records = lag_records(n=2, T=10)
    data = Sequences(records, history=4, future=8)
    generator = torch.Generator().manual_seed(0)
    rows = ImaginedDeployments(data, data.starts(0), 5, 4, lambda n, k: torch.randint(n, (k,), generator=generator))
    for _ in range(6):
        obs_hist, qref_hist, q_star = rows.batch(desired=7)
        assert q_star.shape == (5, 7, 4) and obs_hist.shape == (5, 4, 8)
        before = rows.t.clone()
        with torch.no_grad():
            rolled = policy_rollout(model, None, obs_hist, qref_hist, q_star, steps=4)
        rows.advance(rolled.obs_hist, rolled.qref_hist)
        went_on = rows.t == before + 4
        assert torch.equal(rows.obs_hist[went_on], rolled.obs_hist[went_on])  # the model's own predictions, not records
        assert torch.isin(rows.t[~went_on], data.origin).all()  # the others begin an episode
        assert (rows.t + 4 <= rows.end + 1).all()


def test_an_imagined_deployment_that_leaves_the_records_tracking_errors_begins_again_at_a_recorded_window():
    data = Sequences(lag_records(n=2, T=30), history=4, future=8)
    generator = torch.Generator().manual_seed(1)
    rows = ImaginedDeployments(data, data.starts(0), 3, 4, lambda n, k: torch.randint(n, (k,), generator=generator))
    rows.t[:] = data.origin[0] + 2
    rows.end[:] = data.origin[0] + 29
    after = data.window(rows.t + 4, horizon=0)  # as if the model had predicted the records h steps on
    far = after.obs_hist.clone()
    far[0, -1, :4] += 1.0  # row 0 far beyond any tracking error of the records
    rows.advance(far, after.qref_hist)
    assert rows.t[1] == rows.t[2] == data.origin[0] + 6  # the others go on
    recorded = data.window(rows.t[:1], horizon=0)
    assert torch.equal(rows.obs_hist[:1], recorded.obs_hist) and torch.equal(rows.qref_hist[:1], recorded.qref_hist)


def test_untrained_policy_is_the_position_controller_and_output_is_bounded():
    cfg = dataclasses.replace(POLICY_PRESETS["tiny"], max_adjust=(0.1, 0.2, 0.3, 0.4))
    policy = AdjustmentPolicy(cfg)
    x = (torch.randn(6, 4, 8), torch.randn(6, 4, 4), torch.randn(6, 4, 4))
    assert torch.equal(policy(*x), torch.zeros(6, 4))
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=100.0)
    a = policy(*(100 * v for v in x))
    assert (a.abs() <= torch.tensor(cfg.max_adjust)).all() and (a.abs().amax(0) > 0.99 * torch.tensor(cfg.max_adjust)).all()


def test_rollout_without_policy_follows_desired_positions(model):
    records = lag_records(n=1, T=30)
    B = 3
    q_star = torch.randn(B, 6, 4) * 0.1
    obs_hist, qref_hist = torch.randn(B, 4, 8) * 0.1, torch.randn(B, 4, 4) * 0.1
    with torch.no_grad():
        rolled = policy_rollout(model, None, obs_hist, qref_hist, q_star, steps=6)
        from efficienttrack.learn.dynamics import rollout

        expected = rollout(model, obs_hist, qref_hist, q_star)
    assert torch.equal(rolled.q_ref, q_star) and torch.equal(rolled.a, torch.zeros(B, 6, 4))
    torch.testing.assert_close(rolled.q_hat, expected[..., :4])
    assert predicted_tracking_error(model, records, None, steps=3).windows == 30


def test_save_load_round_trip_and_refuse_other_kind(trained, model, tmp_path):
    path = save_policy(trained.policy, tmp_path / "policy.pt")
    loaded = load_policy(path)
    assert loaded.cfg == trained.policy.cfg
    x = (torch.randn(5, 4, 8), torch.randn(5, 4, 4), torch.randn(5, 4, 4))
    with torch.no_grad():
        assert torch.equal(trained.policy(*x), loaded(*x))
    from efficienttrack.learn.dynamics import save_model

    save_model(model, tmp_path / "model.pt")
    with pytest.raises(EfficientTrackError, match="expected a 'adjustment_policy' config"):
        load_policy(tmp_path / "model.pt")


def test_policy_training_is_deterministic(model):
    records = lag_records(n=2, T=40)
    cfg = dataclasses.replace(POLICY_PRESETS["tiny"], steps=10)
    a, b = (train_policy(cfg, model, records, device="cpu", seed=3, progress=False) for _ in range(2))
    np.testing.assert_array_equal(a.losses, b.losses)


def test_config_validation():
    assert PolicyConfig.from_dict({"max_adjust": [0.1, 0.1, 0.1, 0.1]}).max_adjust == (0.1, 0.1, 0.1, 0.1)
    with pytest.raises(EfficientTrackError, match=r"PolicyConfig.max_adjust must be a list of 4 finite numbers > 0"):
        PolicyConfig(max_adjust=(0.1, 0.1))
    with pytest.raises(EfficientTrackError, match="max_adjust must be a list of 4 finite numbers"):
        PolicyConfig.from_dict({"max_adjust": "0.1"})


def test_cli_train_policy(model, tmp_path):
    from typer.testing import CliRunner

    from efficienttrack.cli import app
    from efficienttrack.data.records import save_records
    from efficienttrack.learn.dynamics import save_model

    save_records(lag_records(n=2, T=30), tmp_path / "data")
    save_model(model, tmp_path / "model.pt")
    out = tmp_path / "policy.pt"
    args = ["train-policy", "--model", str(tmp_path / "model.pt"), "--data", str(tmp_path / "data"), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--preset", "tiny", "--steps", "5", "--device", "cpu"])
    assert result.exit_code == 0, result.output
    assert "model-predicted tracking error" in result.output
    assert load_policy(out).cfg.steps == 5
    # what it was trained from (records, seed 0, the model trained through, no warm start) is kept beside the weights
    from efficienttrack.data.records import load_records
    from efficienttrack.learn.dynamics import load_model
    from efficienttrack.learn.training import fingerprint

    expected = fingerprint(load_records(tmp_path / "data"), 0, load_model(tmp_path / "model.pt"), None)
    assert json.loads(out.with_suffix(".json").read_text())["training_fingerprint"] == expected
    result = CliRunner().invoke(app, [*args, "--preset", "huge"])
    assert result.exit_code != 0 and "--preset 'huge'" in str(result.exception)


def test_the_path_roughness_is_the_squared_second_difference_wrapped_across_pi():
    line = torch.linspace(0, 1, 6, dtype=torch.float64)[None, :, None].repeat(1, 1, 4)
    assert path_roughness(line).item() == pytest.approx(0.0, abs=1e-15)
    zigzag = torch.zeros(1, 5, 4, dtype=torch.float64)
    zigzag[0, 1::2, 0] = 0.1  # 0, .1, 0, .1, 0: second differences ∓0.2
    assert path_roughness(zigzag).item() == pytest.approx(0.04)
    across = torch.tensor([[[0, 0, 0, 3.1], [0, 0, 0, -3.1], [0, 0, 0, -3.0]]], dtype=torch.float64)  # the short way
    assert path_roughness(across).item() == pytest.approx((0.1 - (2 * np.pi - 6.2)) ** 2)
    with pytest.raises(EfficientTrackError, match="k_path needs a horizon of at least 3"):
        dataclasses.replace(POLICY_PRESETS["tiny"], k_path=1.0, horizon=2)
