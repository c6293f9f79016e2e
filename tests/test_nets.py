import dataclasses

import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.features import feature_width, relative_features
from efficienttrack.learn.dynamics import ClosedLoopModel
from efficienttrack.learn.policy import AdjustmentPolicy, desired_length, policy_rollout, seen_lengths
from efficienttrack.learn.settings import ModelConfig, PolicyConfig


@pytest.mark.parametrize(("h", "K"), [(1, 1), (2, 1), (3, 5), (5, 1), (20, 20)])
def test_feature_width_is_the_width_of_relative_features(h, K):
    x = relative_features(torch.randn(2, h, 8), torch.randn(2, h, 4), torch.randn(2, K, 4))
    assert x.shape == (2, feature_width(h, K)) == (2, 12 * h + 4 * K)


def test_model_lengths_are_derived_from_the_stored_fields():
    cfg = ModelConfig.from_dict({"horizon": 6, "history": 2}, "model.json")
    assert (cfg.history_length, cfg.rollout_length, cfg.in_dim) == (2, 6, feature_width(2, 1))
    assert ModelConfig(horizon=6, history=None).history_length == 6
    assert ClosedLoopModel(cfg).g_theta.body[0].in_features == cfg.in_dim
    stored = dataclasses.asdict(cfg)  # what model.json holds: the inputs, never the derived lengths
    assert stored["horizon"] == 6 and stored["history"] == 2
    assert not {"history_length", "rollout_length", "in_dim"} & set(stored)


def test_policy_lengths_and_what_a_rollout_needs():
    cfg = PolicyConfig.from_dict({"horizon": 5}, "policy.json")
    assert (cfg.history_length, cfg.future_length, cfg.rollout_length) == (5, 5, 5)
    assert AdjustmentPolicy(cfg).pi_phi.body[0].in_features == cfg.in_dim == feature_width(5, 5)
    assert seen_lengths(cfg) == (5, 5) and seen_lengths(None) == (1, 1)
    # a rollout of H steps slides the F desired positions seen along q*_{t+1} … q*_{t+H−1+F}
    assert desired_length(cfg, cfg.rollout_length) == 9 and desired_length(cfg, 1) == 5 and desired_length(None, 4) == 4
    assert not {"history_length", "future_length", "rollout_length", "in_dim"} & set(dataclasses.asdict(cfg))


def test_policy_rollout_reads_exactly_the_desired_length():
    model = ClosedLoopModel(ModelConfig(hidden=8, layers=1, horizon=3, history=None))
    policy = AdjustmentPolicy(PolicyConfig(hidden=8, layers=1, horizon=3))
    obs_hist, qref_hist = torch.zeros(2, 3, 8), torch.zeros(2, 3, 4)
    need = desired_length(policy.cfg, 4)
    with torch.no_grad():
        assert policy_rollout(model, policy, obs_hist, qref_hist, torch.zeros(2, need, 4), steps=4).q_hat.shape == (2, 4, 4)
        with pytest.raises(EfficientTrackError, match=f"needs {need} future desired positions, got {need - 1}"):
            policy_rollout(model, policy, obs_hist, qref_hist, torch.zeros(2, need - 1, 4), steps=4)
