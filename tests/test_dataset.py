import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import initial_history, push, push_observation, push_reference


def hand_record(T: int, base: float) -> EpisodeRecord:
    """Distinct values per field and step: q[t] = base + 0.01 t, qd = q + 1, q_ref = q + 0.5, q_des = q + 0.7."""
    t = np.arange(T, dtype=np.float64)[:, None] * np.ones(4)
    return EpisodeRecord(
        q=base + t * 0.01,
        qd=base + 1 + t * 0.01,
        q_ref=base + 0.5 + t * 0.01,
        q_des=base + 0.7 + t * 0.01,
        u=None,
        t=np.arange(T) * 0.05,
    ).validate()


def test_window_indexing_and_padding():
    a, b = hand_record(6, 0.0), hand_record(5, 2.0)
    seq = Sequences([a, b], history=3, future=4)
    assert seq.steps == 11
    starts = seq.starts(2)
    assert len(starts) == (6 - 2) + (5 - 2)  # t = 0 … T-1-2 per episode
    w = seq.window(starts, horizon=2, desired=4)
    f = lambda x: torch.as_tensor(x, dtype=torch.float32)  # noqa: E731
    # episode a, t = 0: history padded with o_0 / q_0; future refs are q_ref[0], q_ref[1]
    assert torch.equal(w.obs_hist[0], f(np.repeat(a.obs[:1], 3, 0)))
    assert torch.equal(w.qref_hist[0], f(np.repeat(a.q[:1], 3, 0)))
    assert torch.equal(w.qref_future[0], f(a.q_ref[:2]))
    assert torch.equal(w.obs_future[0], f(a.obs[1:3]))
    assert torch.equal(w.qdes_future[0], f(a.q_des[:4]))
    # episode a, t = 1: [o0, o0, o1], [q0, q0, q^r_1 = q_ref[0]]
    assert torch.equal(w.obs_hist[1], f(a.obs[[0, 0, 1]]))
    assert torch.equal(w.qref_hist[1], f(np.stack([a.q[0], a.q[0], a.q_ref[0]])))
    # episode a, t = 3 (last start): desired q*_{4..7} = q_des[3], q_des[4], q_des[5], q_des[5] (padded with the last)
    assert torch.equal(w.qdes_future[3], f(a.q_des[[3, 4, 5, 5]]))
    assert torch.equal(w.obs_future[3], f(a.obs[4:6]))
    # episode b, t = 0 and t = 2: nothing leaks from episode a
    assert torch.equal(w.obs_hist[4], f(np.repeat(b.obs[:1], 3, 0)))
    assert torch.equal(w.obs_hist[6], f(b.obs[0:3]))
    assert torch.equal(w.qref_hist[6], f(np.stack([b.q[0], b.q_ref[0], b.q_ref[1]])))
    assert torch.equal(w.qref_future[6], f(b.q_ref[2:4]))
    # horizon 0: every step is a start
    assert len(seq.starts(0)) == 11


def test_runtime_histories_equal_training_windows():
    rec = hand_record(7, 1.0)
    h = 4
    seq = Sequences([rec], history=h, future=1)
    windows = seq.window(seq.starts(0), horizon=0)
    hist = initial_history(rec.obs[:1], h)
    for t in range(len(rec)):
        hist = push_observation(hist, rec.obs[t : t + 1])
        np.testing.assert_allclose(hist.obs[0], windows.obs_hist[t].double().numpy(), rtol=0, atol=1e-6)
        np.testing.assert_allclose(hist.q_ref[0], windows.qref_hist[t].double().numpy(), rtol=0, atol=1e-6)
        hist = push_reference(hist, rec.q_ref[t : t + 1])


def test_push_numpy_and_torch_agree():
    x = np.arange(24.0).reshape(2, 3, 4)
    new = -np.ones((2, 4))
    expected = np.concatenate([x[:, 1:], new[:, None]], 1)
    np.testing.assert_array_equal(push(x, new), expected)
    np.testing.assert_array_equal(push(torch.as_tensor(x), torch.as_tensor(new)).numpy(), expected)


def test_errors_are_clear():
    rec = hand_record(4, 0.0)
    with pytest.raises(EfficientTrackError, match="long enough"):
        Sequences([rec], history=2, future=5).starts(5)
    with pytest.raises(EfficientTrackError, match="no episode records"):
        Sequences([], history=2, future=2)
    with pytest.raises(EfficientTrackError, match=r"\(N, 8\)"):
        initial_history(np.zeros(8), 3)
