import numpy as np
import pytest

from efficienttrack.data.metrics import adjustment, per_joint_mae, tracking_error
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.workflow import plots

pytestmark = pytest.mark.figures


def episode(steps, offset_deg, adjust_deg=0.0, seed=0):
    """A record lagging its desired positions by a constant offset; q_ref = q_des + adjust."""
    q_des = np.cumsum(np.random.default_rng(seed).normal(0, 0.01, (steps, 4)), axis=0)
    q = np.concatenate([q_des[:1], q_des[:-1] + np.radians(offset_deg)])
    return EpisodeRecord(
        q=q, qd=np.zeros((steps, 4)), q_ref=q_des + np.radians(adjust_deg), q_des=q_des, u=None, t=0.05 * np.arange(steps)
    )


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions save, kept open for inspection."""
    kept = []

    def save(fig, path):
        kept.append(fig)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"png")
        return path

    monkeypatch.setattr(plots, "_save", save)
    yield kept
    for fig in kept:
        plots.plt.close(fig)


def test_adjustment_is_wrapped_reference_minus_desired():
    q_des = np.zeros((3, 4))
    q_ref = np.full((3, 4), np.radians(359.0))
    assert np.allclose(np.degrees(adjustment(q_ref, q_des)), -1.0)


def test_tracking_plot_has_adjustment_panel_and_per_reference_mae(tmp_path, figures):
    runs = {"PD": episode(30, 2.0), "EfficientTrack": episode(30, 0.5, adjust_deg=1.5)}
    plots.plot_tracking(runs, tmp_path / "t.png", title="ref_07")
    (fig,) = figures
    assert len(fig.axes) == 5
    title = fig.axes[0].get_title()
    assert title == "ref_07 — MAE PD 2.00°, EfficientTrack 0.50°"
    panel = fig.axes[4]
    assert panel.get_ylabel() == "q_ref − q* (°)"
    assert len(panel.lines) == 4  # EfficientTrack's adjustment per joint; PD's is zero and not drawn
    assert np.allclose(panel.lines[0].get_ydata(), 1.5)
    plots.plot_tracking({"PD": runs["PD"]}, tmp_path / "pd.png", title="ref_07")
    assert not figures[1].axes[4].lines and "no adjustment" in figures[1].axes[4].texts[0].get_text()


def test_padded_errors_line_up_episodes_of_different_lengths():
    records = [episode(10, 1.0, seed=1), episode(6, 3.0, seed=2), episode(8, 2.0, seed=3)]
    padded = plots.padded_errors(records)
    assert padded.shape == (3, 9, 4)
    for i, record in enumerate(records):
        e = np.abs(tracking_error(record.q, record.q_des))
        assert np.array_equal(padded[i, : len(e)], e) and np.isnan(padded[i, len(e) :]).all()


def test_tracking_error_plot_says_how_it_averages(tmp_path, figures):
    records = [episode(10, 1.0, seed=1), episode(6, 3.0, seed=2), episode(8, 2.0, seed=3)]
    plots.plot_tracking_error({"PD": records}, tmp_path / "e.png")
    (fig,) = figures
    assert len(fig.axes) == 5
    assert "episodes still running" in fig.axes[0].get_title() and "metrics.json" in fig.axes[0].get_title()
    mean = fig.axes[0].lines[0].get_ydata()
    assert np.allclose(mean[:5], 2.0) and np.allclose(mean[5:7], 1.5) and np.allclose(mean[7:], 1.0)  # running episodes
    assert len(fig.axes[0].collections) == 1  # the 25–75 % band
    assert list(fig.axes[4].lines[0].get_ydata()) == [3] * 5 + [2] * 2 + [1] * 2
    per_episode = np.degrees(np.mean([per_joint_mae(tracking_error(r.q, r.q_des)) for r in records], axis=0))
    assert f"per-episode MAE {per_episode[0]:.2f}°" in fig.axes[0].get_legend().get_texts()[0].get_text()
