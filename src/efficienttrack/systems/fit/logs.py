"""A machine's PD logs as the fit and the fidelity check see them: loaded, selected, padded, cut into windows.

Episodes are stacked time-major (:class:`Padded`, (T, N, 4)), shorter ones padded with their last row
(:func:`efficienttrack.data.windows.pad_time_major`) and masked. Windows are gathered time-major too
(:class:`Windows`, (H, W, 4)), since the simulator steps all of them at once; which windows exist is
:func:`efficienttrack.data.windows.window_starts`, the same function the learned model's (batch-major) windows use.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, N_JOINTS
from efficienttrack.data.metrics import position_error, tracking_error
from efficienttrack.data.records import EpisodeRecord, load_records
from efficienttrack.data.windows import pad_time_major, window_starts


def load_logs(paths: Sequence[str | Path], need_u: bool = True, recursive: bool = False) -> list[EpisodeRecord]:
    """Read the episodes of the given files or folders with :func:`efficienttrack.data.records.load_records`.

    Args:
        paths: episode files or folders (e.g. ``/work/shared/data/xe75/pd_noise_train``).
        need_u: refuse records without the PWM command ``u``.
        recursive: read the subfolders of a folder too (by default only the episodes directly in it).

    Returns:
        The records, in the order of ``paths`` (folders sorted).
    """
    if not paths:
        raise EfficientTrackError("--logs: give at least one folder of episode logs")
    records = load_records(paths, recursive)
    lacking = [str(r.meta.get("name", i)) for i, r in enumerate(records) if r.u is None]
    if need_u and lacking:
        raise EfficientTrackError(
            f"--logs: episode {lacking[0]} has no PWM command 'u' (needed to fit and replay the plant)"
            + (f", nor have {len(lacking) - 1} more" if len(lacking) > 1 else "")
        )
    return records


def reference_jitter(record: EpisodeRecord) -> float:
    """RMS step-to-step change of an episode's reference perturbation ``wrap(q_ref − q_des)``, rad.

    About the noise level σ of a noisy-reference pass (√2 × the 0.72 σ standard deviation of clipped Gaussian
    noise; on ``pd_noise_train`` 0.0081 rad for σ = 0.008), zero for a plain PD run. Strongly perturbed
    passes make the PD law chatter between full PWM in both directions; fitted on those, the model
    generalizes worse to smooth commands (on the XE75, keeping the passes up to σ = 0.008 rad of
    ``pd_noise_train`` gave a simulator closer to the real machine under the learned policies).

    Args:
        record: an episode with ``q_ref`` and ``q_des`` (T, 4) rad.
    """
    offset = wrap(record.q_ref - record.q_des)
    return float(np.sqrt(np.mean(np.diff(offset, axis=0) ** 2))) if len(offset) > 1 else 0.0


def select_by_jitter(
    records: Sequence[EpisodeRecord], low: float = 0.0, high: float = np.inf, option: str = "reference jitter"
) -> list[EpisodeRecord]:
    """The episodes whose :func:`reference_jitter` lies in ``[low, high]`` rad; an error names ``option`` if none does.

    Args:
        records: the episodes (``q_ref``, ``q_des`` (T, 4) rad).
        low: smallest jitter kept, rad.
        high: largest jitter kept, rad.
        option: the setting the bounds come from, named in the error message.
    """
    if not 0 <= low <= high:  # also refuses NaN
        raise EfficientTrackError(f"{option}: needs bounds 0 ≤ low ≤ high rad, got [{low:g}, {high:g}]")
    jitter = np.array([reference_jitter(r) for r in records])
    kept = [r for r, j in zip(records, jitter, strict=True) if low <= j <= high]
    if not kept:
        raise EfficientTrackError(
            f"{option}: no episode's reference jitter lies in [{low:g}, {high:g}] rad "
            f"(the logs' range: {jitter.min():.4g} … {jitter.max():.4g} rad)"
        )
    return kept


class Padded(NamedTuple):
    """Episodes of different lengths stacked time-major, each padded with its last row.

    Attributes:
        q: (T, N, 4) rad.
        qd: (T, N, 4) rad/s.
        u: (T, N, 4) PWM (zeros where a record has none).
        q_ref: (T, N, 4) rad.
        q_des: (T, N, 4) rad.
        lengths: (N,) number of real steps of each episode.
    """

    q: np.ndarray
    qd: np.ndarray
    u: np.ndarray
    q_ref: np.ndarray
    q_des: np.ndarray
    lengths: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(T, N) True on the real (unpadded) steps."""
        return np.arange(len(self.q))[:, None] < self.lengths[None, :]


def pad(records: Sequence[EpisodeRecord]) -> Padded:
    """Stack records time-major, padding each with its last row (:func:`efficienttrack.data.windows.pad_time_major`).

    Args:
        records: N episodes (T_i, 4) per field; a record without ``u`` gets zeros.

    Returns:
        The padded logs, T = max T_i.
    """
    u = [np.zeros((len(r), N_JOINTS)) if r.u is None else r.u for r in records]
    fields = (pad_time_major([getattr(r, name) for r in records]) for name in ("q", "qd", "q_ref", "q_des"))
    q, qd, q_ref, q_des = fields
    return Padded(q, qd, pad_time_major(u), q_ref, q_des, np.array([len(r) for r in records]))


class Windows(NamedTuple):
    """Windows cut from logs, time-major (the simulator steps all windows at once; learning's are batch-major).

    Attributes:
        q0: (W, 4) rad, logged position at the window start t0.
        qd0: (W, 4) rad/s, logged velocity at t0.
        u_past: (K, W, 4) PWM, the K commands before t0 in time order (zeros before the log starts).
        e_prev: (W, 4) rad, the PD law's error of step t0 − 1 (its own error at t0 = 0).
        u: (H, W, 4) PWM, logged commands u[t0 … t0+H−1].
        q_ref: (H, W, 4) rad, logged references q_ref[t0 … t0+H−1].
        q: (H, W, 4) rad, logged positions q[t0+1 … t0+H].
    """

    q0: np.ndarray
    qd0: np.ndarray
    u_past: np.ndarray
    e_prev: np.ndarray
    u: np.ndarray
    q_ref: np.ndarray
    q: np.ndarray


def make_windows(data: Padded, horizon: int, stride: int = 1, history: int = 21) -> Windows:
    """Every ``stride``-th start t0 (per episode) with a full ``horizon`` of logged steps after it.

    The starts are :func:`efficienttrack.data.windows.window_starts` (t0 + horizon ≤ T − 1), gathered time-major.

    Args:
        data: padded logs.
        horizon: H, steps per window.
        stride: distance between window starts, steps.
        history: K, commands before t0 kept for the delay line.

    Returns:
        The windows (W of them).
    """
    ep, t0 = window_starts(data.lengths, horizon, stride)
    steps = t0[None, :] + np.arange(horizon)[:, None]
    past = t0[None, :] + np.arange(-history, 0)[:, None]
    u_past = np.where((past >= 0)[..., None], data.u[np.maximum(past, 0), ep], 0.0)
    prev = np.maximum(t0 - 1, 0)
    e_prev = wrap(data.q_ref[prev, ep] - data.q[prev, ep])
    return Windows(
        data.q[t0, ep], data.qd[t0, ep], u_past, e_prev, data.u[steps, ep], data.q_ref[steps, ep], data.q[steps + 1, ep]
    )


def episode_windows(data: Padded) -> Windows:
    """Whole episodes as one window each, started as :class:`~efficienttrack.systems.pd.ClosedLoop` resets a plant.

    At rest at the logged start, with an empty delay line and the PD law's first-step convention
    (``e_prev`` = its own error); ``u``, ``q_ref`` and ``q`` are the padded steps 0 … T−2 (``q`` from 1).

    Args:
        data: padded logs (T steps, N episodes).

    Returns:
        N windows of H = T − 1 steps (K = 0 past commands).
    """
    start = data.q[0]
    return Windows(
        start,
        np.zeros_like(start),
        np.zeros((0, *start.shape)),
        wrap(data.q_ref[0] - start),
        data.u[:-1],
        data.q_ref[:-1],
        data.q[1:],
    )


def window_error(q_sim: np.ndarray, windows: Windows) -> np.ndarray:
    """Per-joint mean position error |wrap(q_sim − q_log)| over the steps and windows, (4,) rad.

    Args:
        q_sim: (H, W, 4) rad, simulated positions of the windows' steps 1 … H.
        windows: the windows (their logged positions ``q`` (H, W, 4)).
    """
    return position_error(q_sim, windows.q).mean(axis=(0, 1))


def tracking_mae(q: np.ndarray, data: Padded) -> np.ndarray:
    """Per-episode, per-joint MAE ``mean_t |wrap(q[t+1] − q_des[t])|`` over the real steps, (N, 4) rad.

    Args:
        q: (T, N, 4) rad, positions (logged or simulated).
        data: the padded logs the positions belong to (for ``q_des`` and the lengths).
    """
    err = np.abs(tracking_error(q, data.q_des))
    mask = data.mask[1:]
    return (err * mask[..., None]).sum(axis=0) / mask.sum(axis=0)[:, None]


def estimate_sensor_noise(data: Padded, dt: float = DT) -> tuple[np.ndarray, np.ndarray]:
    """Robust sensor-noise levels of the logs: (noise_q (4,) rad, noise_qd (4,) rad/s).

    ``noise_q`` from the second difference of q (6σ² for white noise on a smooth motion),
    ``noise_qd`` from the sensor rate against the position difference, ``qd[t+1] − (q[t+1] − q[t]) / dt``;
    both as 1.4826 × median absolute deviation over the real steps (upper bounds: motion leaks in).

    Args:
        data: padded logs (T steps, N episodes); only the real (unpadded) steps count.
        dt: sample period of the logs, s.
    """
    mask = data.mask
    d2 = (data.q[2:] - 2 * data.q[1:-1] + data.q[:-2])[mask[2:]]
    dv = (data.qd[1:] - wrap(data.q[1:] - data.q[:-1]) / dt)[mask[1:]]

    def mad(x: np.ndarray) -> np.ndarray:
        return 1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0)

    return mad(d2) / np.sqrt(6.0), mad(dv)


def logged_accel(data: Padded, dt: float = DT, quantile: float = 0.999) -> np.ndarray:
    """The largest joint accelerations in the logs, (4,) rad/s²: a quantile of ``|qd[t+1] − qd[t−1]| / 2dt``.

    The calibration starts the acceleration limit here: started above every logged acceleration the
    limit never acts, and a local fit cannot find it.

    Args:
        data: padded logs; only the real steps count.
        dt: sample period, s.
        quantile: the quantile taken (the very largest values are sensor noise).
    """
    accel = np.abs(data.qd[2:] - data.qd[:-2]) / (2 * dt)
    return np.quantile(accel[data.mask[2:]], quantile, axis=0)
