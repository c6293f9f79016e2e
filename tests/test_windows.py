import numpy as np
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.metrics import position_error
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import pad_time_major, window_starts


def test_pad_time_major_repeats_each_arrays_last_row():
    rng = np.random.default_rng(0)
    arrays = [rng.normal(size=(n, 3)) for n in (4, 1, 6)]
    padded = pad_time_major(arrays, extra=2)
    assert padded.shape == (8, 3, 3) and padded.dtype == np.float64
    for i, a in enumerate(arrays):  # the reference: one copy per array, then its last row
        np.testing.assert_array_equal(padded[: len(a), i], a)
        np.testing.assert_array_equal(padded[len(a) :, i], np.broadcast_to(a[-1], (8 - len(a), 3)))
    with pytest.raises(EfficientTrackError, match="empty"):
        pad_time_major([arrays[0], np.zeros((0, 3))])


@pytest.mark.parametrize("horizon, stride", [(0, 1), (2, 1), (3, 2), (5, 4), (7, 3)])
def test_window_starts_equal_the_list_of_every_strided_start_with_a_full_horizon(horizon, stride):
    lengths = [6, 2, 9, 7, 1]
    expected = [(i, t0) for i, n in enumerate(lengths) for t0 in range(0, n - horizon, stride)]
    starts = window_starts(lengths, horizon, stride)
    assert list(zip(starts.episode.tolist(), starts.t0.tolist(), strict=True)) == expected
    assert np.all(starts.t0 + horizon <= np.asarray(lengths)[starts.episode] - 1)


def test_window_starts_name_the_longest_episode_when_none_fits():
    with pytest.raises(EfficientTrackError, match="20-step window.*longest has 9 steps"):
        window_starts([9, 4], 20)


def test_learning_and_fit_windows_start_at_the_same_steps():
    from efficienttrack.systems.fit import make_windows, pad

    rng = np.random.default_rng(1)
    records = []
    for n in (12, 7, 9):
        q = rng.normal(size=(n, 4))
        records.append(EpisodeRecord(q=q, qd=q, q_ref=q, q_des=q, u=q, t=np.arange(n) * 0.05).validate())
    seqs = Sequences(records, history=2, future=3)
    batch_major = seqs.window(seqs.starts(3), horizon=3).obs_future[..., :4]  # (B, H, 4)
    time_major = make_windows(pad(records), 3).q  # (H, W, 4)
    torch.testing.assert_close(batch_major.double(), torch.as_tensor(time_major).transpose(0, 1), rtol=0, atol=1e-6)


def test_position_error_wraps_and_agrees_between_numpy_and_torch():
    q_hat = np.radians([[359.0, 10.0, -179.0, 0.5]])
    q = np.radians([[0.0, 12.0, 179.0, 0.5]])
    np.testing.assert_allclose(np.degrees(position_error(q_hat, q)), [[1.0, 2.0, 2.0, 0.0]], atol=1e-9)
    t = position_error(torch.as_tensor(q_hat), torch.as_tensor(q))
    assert isinstance(t, torch.Tensor)
    np.testing.assert_array_equal(t.numpy(), position_error(q_hat, q))
