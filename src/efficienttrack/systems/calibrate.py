"""Fit the hydraulic simulator to a machine's logs (PWM → motion) and measure its fidelity.

Calibration (:func:`calibrate`) first fits the valve-to-speed map to the logged steps at which a command has
been held until the joint settled (:func:`steady_samples`; a static fit, cheap and well posed, that weighs
every band of held PWM alike: :func:`_bin_weights`), then minimizes multi-step position errors with
``scipy.optimize.least_squares``: windows are cut from the logs, the simulator is started in each window's
logged state (position, velocity and the commands still in the delay line) and driven either with the logged
PWM (open loop) or by the PD law along the logged ``q_ref`` (closed loop); the residual is
``wrap(q_sim − q_log)`` over every step of every window. Integer delays are chosen per joint on a grid. A last
stage runs whole episodes in closed loop and also matches each episode's PD tracking MAE. Episodes with a
strongly perturbed reference are left out (:func:`reference_jitter`). The shipped ``xe75`` preset was fitted
this way on ``pd_noise_train`` (its 200 passes with σ ≤ 0.008 rad).

Fidelity (:func:`fidelity`):

- **closed loop**: the system (PD law included) is reset at each log's first position and driven
  with the logged ``q_ref``; per joint, the paper's MAE ``mean_t |wrap(q[t+1] − q_des[t])|`` per
  episode, averaged over episodes, for the simulation and the log, and their ratio sim / real.
  All episodes run in one batch (shorter ones are padded with their last reference and masked).
- **open loop** ``mpe20``: from every ``stride``-th step t0 with a full horizon, the plant is reset
  at the logged state of t0 and replays ``u[t0 … t0+19]``; the error is the mean of
  ``|wrap(q_sim[t0+k] − q[t0+k])|`` over k = 1 … 20, then over windows, per joint. Plants whose
  ``reset`` accepts ``qd0`` and ``u_past`` (the built-in one) start with the logged velocity and
  the logged commands in the delay line; other plants start at rest at ``q[t0]``.
- **open loop** ``travel_ratio20``: on the same windows, the real joint's travel over the 20 steps against the
  simulated one's, ``Σ D_real·D_sim / Σ D_sim²`` with ``D = wrap(q[t0+20] − q[t0])`` (the least-squares slope
  of real over simulated travel), per joint. Above 1 the real joint goes further than the simulated one under
  the same PWM: a simulator that is too slow overall, under that set's commands.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import scipy.sparse
from scipy.optimize import least_squares

from efficienttrack.angles import wrap
from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import atomic_write
from efficienttrack.joints import DT, N_JOINTS
from efficienttrack.metrics import tracking_error
from efficienttrack.records import EpisodeRecord
from efficienttrack.systems.hydraulic import (
    U_MAX,
    HydraulicParams,
    HydraulicState,
    initial_state,
    requested_velocity,
    step,
    xe75_params,
)
from efficienttrack.systems.pd import XE75_PD, PDGains
from efficienttrack.systems.protocol import BatchedSystem

STEADY_FIELDS = (
    "pwm_sat_pos",
    "pwm_sat_neg",
    "flow_curve",
    "v_max_pos",
    "v_max_neg",
    "speed_q",
    "speed_q2",
    "pump_coupling",
)
"""The parameters of the valve-to-speed map, fitted first on the steady samples (:class:`Steady`).

The dead zones are left to the dynamic stages: on the settled samples of a creeping joint they trade off
against the extra dead zone at rest (on the XE75 the static fit put the swing's dead zone at 17 PWM).
"""
JOINT_FIELDS = (
    "tau_spool",
    "tau",
    "tau_brake",
    "accel_max",
    "dead_zone_pos",
    "dead_zone_neg",
    "dead_zone_q",
    "dead_zone_rest",
    "rest_speed",
) + STEADY_FIELDS
"""The fitted parameters (the pump coupling's columns belong to the joint they slow down)."""
BOUNDS: dict[str, tuple[float, float]] = {
    "tau_spool": (0.0, 0.5),
    "tau": (0.005, 1.0),
    "tau_brake": (0.005, 1.0),
    "accel_max": (0.5, 1000.0),
    "dead_zone_pos": (0.0, 900.0),
    "dead_zone_neg": (0.0, 900.0),
    "dead_zone_q": (-400.0, 400.0),
    "dead_zone_rest": (0.0, 400.0),
    "rest_speed": (0.005, 2.0),
    "pwm_sat_pos": (550.0, 1000.0),
    "pwm_sat_neg": (550.0, 1000.0),
    "flow_curve": (0.0, 1.5),
    "v_max_pos": (0.005, 5.0),
    "v_max_neg": (0.005, 5.0),
    "speed_q": (-3.0, 3.0),
    "speed_q2": (-2.0, 2.0),
    "pump_coupling": (0.0, 3.0),
}
"""Search bounds of the fitted parameters (units as in :class:`HydraulicParams`)."""


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


class Windows(NamedTuple):
    """Windows cut from logs, time-major.

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


def load_logs(dirs: Sequence[str | Path], need_u: bool = True) -> list[EpisodeRecord]:
    """Read every ``*.npz`` episode of the given folders (sorted by name).

    Args:
        dirs: folders of episode records (e.g. ``/work/shared/data/xe75/pd_noise_train``).
        need_u: refuse records without the PWM command ``u``.

    Returns:
        The records, folder by folder.
    """
    if not dirs:
        raise EfficientTrackError("--logs: give at least one folder of episode logs")
    records = []
    for folder in map(Path, dirs):
        files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
        if not files:
            raise EfficientTrackError(f"--logs {folder}: not a folder with .npz episode logs")
        for path in files:
            record = EpisodeRecord.load(path)
            if need_u and record.u is None:
                raise EfficientTrackError(f"{path}: has no PWM command 'u' (needed to fit and replay the plant)")
            records.append(record)
    return records


def pad(records: Sequence[EpisodeRecord]) -> Padded:
    """Stack records time-major, padding each with its last row; see :class:`Padded`."""
    lengths = np.array([len(r) for r in records])
    t_max = int(lengths.max())

    def stack(name: str) -> np.ndarray:
        out = np.empty((t_max, len(records), N_JOINTS))
        for i, r in enumerate(records):
            x = getattr(r, name)
            x = np.zeros((len(r), N_JOINTS)) if x is None else x
            out[: len(r), i] = x
            out[len(r) :, i] = x[-1]
        return out

    return Padded(stack("q"), stack("qd"), stack("u"), stack("q_ref"), stack("q_des"), lengths)


def make_windows(data: Padded, horizon: int, stride: int = 1, history: int = 21) -> Windows:
    """Every ``stride``-th start t0 (per episode) with a full ``horizon`` of logged steps after it.

    Args:
        data: padded logs.
        horizon: H, steps per window.
        stride: distance between window starts, steps.
        history: K, commands before t0 kept for the delay line.

    Returns:
        The windows (W of them).
    """
    starts = [(t0, i) for i, n in enumerate(data.lengths) for t0 in range(0, int(n) - horizon, stride)]
    if not starts:
        raise EfficientTrackError(f"logs too short for windows of {horizon} steps")
    t0, ep = (np.array(x) for x in zip(*starts, strict=True))
    steps = t0[None, :] + np.arange(horizon)[:, None]
    past = t0[None, :] + np.arange(-history, 0)[:, None]
    u_past = np.where((past >= 0)[..., None], data.u[np.maximum(past, 0), ep], 0.0)
    prev = np.maximum(t0 - 1, 0)
    e_prev = wrap(data.q_ref[prev, ep] - data.q[prev, ep])
    return Windows(
        data.q[t0, ep], data.qd[t0, ep], u_past, e_prev, data.u[steps, ep], data.q_ref[steps, ep], data.q[steps + 1, ep]
    )


def rollout_windows(params: HydraulicParams, windows: Windows, gains: PDGains | None = None) -> np.ndarray:
    """Simulate every window from its logged state; return q (H, W, 4) rad.

    Args:
        params: simulator parameters.
        windows: the windows.
        gains: None to replay the logged PWM (open loop); a PD law to track the logged ``q_ref`` (closed loop).
    """
    state: HydraulicState = initial_state(windows.q0, params, windows.qd0, windows.u_past)
    e_prev = windows.e_prev
    out = np.empty_like(windows.q)
    for k in range(len(windows.u)):
        if gains is None:
            u = windows.u[k]
        else:
            e = wrap(windows.q_ref[k] - state.q)
            u, e_prev = gains.command(e, e_prev), e
        state = step(state, u, params)
        out[k] = state.q
    return out


def window_error(params: HydraulicParams, windows: Windows, gains: PDGains | None = None) -> np.ndarray:
    """Per-joint mean |wrap(q_sim − q_log)| over the steps and windows, (4,) rad (see :func:`rollout_windows`).

    Args:
        params: simulator parameters.
        windows: the windows (H steps, W windows).
        gains: None to replay the logged PWM (open loop); a PD law to track the logged ``q_ref`` (closed loop).
    """
    return np.abs(wrap(rollout_windows(params, windows, gains) - windows.q)).mean(axis=(0, 1))


def closed_loop_rollout(system: BatchedSystem, data: Padded) -> np.ndarray:
    """Drive a reference-level system with the logged ``q_ref``, all episodes in one batch.

    Args:
        system: the system (PD law included), reset at each episode's first logged position.
        data: padded logs (N episodes).

    Returns:
        q (T, N, 4) rad: ``q[0]`` the logged start, ``q[t+1]`` the position after ``q_ref[t]``.
    """
    q = np.empty_like(data.q)
    q[0] = data.q[0]
    system.reset(data.q[0])
    for t in range(len(q) - 1):
        q[t + 1] = system.step(data.q_ref[t])[:, :N_JOINTS]
    return q


def tracking_mae(q: np.ndarray, data: Padded) -> np.ndarray:
    """Per-episode, per-joint MAE ``mean_t |wrap(q[t+1] − q_des[t])|`` over the real steps, (N, 4) rad.

    Args:
        q: (T, N, 4) rad, positions (logged or simulated).
        data: the padded logs the positions belong to (for ``q_des`` and the lengths).
    """
    err = np.abs(tracking_error(q, data.q_des))
    mask = data.mask[1:]
    return (err * mask[..., None]).sum(axis=0) / mask.sum(axis=0)[:, None]


def _pack(params: HydraulicParams, names: Sequence[str]) -> np.ndarray:
    return np.concatenate([np.ravel(getattr(params, name)) for name in names])


def _unpack(x: np.ndarray, params: HydraulicParams, names: Sequence[str]) -> HydraulicParams:
    changes: dict[str, Any] = {}
    i = 0
    for name in names:
        shape = np.shape(getattr(params, name))
        size = int(np.prod(shape))
        value = x[i : i + size].reshape(shape)
        changes[name] = value.tolist()
        i += size
    return params.replace(**changes)


def _joint_of_columns(params: HydraulicParams, names: Sequence[str]) -> np.ndarray:
    """The joint each packed parameter belongs to: the last axis of every fitted field is the joint."""
    cols = [np.broadcast_to(np.arange(N_JOINTS), np.shape(getattr(params, n))).ravel() for n in names]
    return np.concatenate(cols)


@dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`calibrate`."""

    delays: tuple[int, ...] = (2, 3, 4, 5, 6)
    """Candidate transport delays, steps (chosen per joint)."""
    open_horizon: int = 20
    """Steps of the open-loop windows (logged PWM replayed)."""
    closed_horizon: int = 60
    """Steps of the closed-loop windows (logged q_ref tracked by the PD law)."""
    max_windows: int = 2500
    """Windows of each kind at most (evenly strided over the logs)."""
    max_episodes: int = 200
    """Episodes at most in the whole-episode closed-loop stage (evenly strided)."""
    mae_weight: float = 3.0
    """Weight of the per-episode tracking-MAE match against the trajectory error in the whole-episode stage."""
    max_nfev: int = 40
    """Residual evaluations per least-squares stage on simulated windows or episodes."""
    steady_nfev: int = 200
    """Residual evaluations of the static fit on the steady samples (cheap: no simulation)."""
    max_ref_jitter: float = 0.01
    """Episodes whose reference perturbation jitters more than this are left out, rad (see :func:`reference_jitter`)."""

    def __post_init__(self) -> None:
        """Validate the settings; raise EfficientTrackError naming the bad one."""
        if not self.delays or not all(isinstance(d, int) and 0 <= d <= 20 for d in self.delays):
            raise EfficientTrackError(f"fit setting 'delays': needs whole steps 0 … 20, got {self.delays!r}")
        for name in ("open_horizon", "closed_horizon", "max_windows", "max_episodes", "max_nfev", "steady_nfev"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise EfficientTrackError(f"fit setting '{name}': needs a positive integer, got {getattr(self, name)!r}")
        if not self.mae_weight >= 0:
            raise EfficientTrackError(f"fit setting 'mae_weight': needs a number ≥ 0, got {self.mae_weight!r}")
        if not self.max_ref_jitter > 0:
            raise EfficientTrackError(f"fit setting 'max_ref_jitter': needs a number > 0, got {self.max_ref_jitter!r}")


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` found.

    Attributes:
        params: the fitted parameters.
        open_loop_deg: (4,) deg, mean |q error| over the open-loop fitting windows.
        closed_loop_deg: (4,) deg, mean |q error| over the closed-loop fitting windows.
        mae_ratio: (4,) closed-loop PD tracking MAE sim / real on the fitting episodes.
        delay_cost: {delay: (4,) mean squared window error per joint, rad²} of the delay grid.
    """

    params: HydraulicParams
    open_loop_deg: np.ndarray
    closed_loop_deg: np.ndarray
    mae_ratio: np.ndarray
    delay_cost: dict[int, np.ndarray]


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
    jitter = np.array([reference_jitter(r) for r in records])
    kept = [r for r, j in zip(records, jitter, strict=True) if low <= j <= high]
    if not kept:
        raise EfficientTrackError(
            f"{option}: no episode's reference jitter lies in [{low:g}, {high:g}] rad "
            f"(the logs' range: {jitter.min():.4g} … {jitter.max():.4g} rad)"
        )
    return kept


class Steady(NamedTuple):
    """Logged steps at which every valve command has been held long enough for the joint to settle.

    Attributes:
        u: (S, 4) PWM, the command reaching each valve (``u[t − delay]``).
        q: (S, 4) rad, positions at t.
        qd: (S, 4) rad/s, velocities at t.
        qd_next: (S, 4) rad/s, velocities at t + 1.
        mask: (S, 4) True where joint j is settled at that step.
    """

    u: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qd_next: np.ndarray
    mask: np.ndarray


def steady_samples(
    data: Padded,
    delay: Sequence[int],
    hold: int = 5,
    tol: float = 40.0,
    min_count: int = 200,
    saturation: tuple[Sequence[float], Sequence[float]] | None = None,
) -> Steady:
    """The steps where a joint's delayed command stayed within ``tol`` PWM for ``hold`` steps and its speed settled.

    Args:
        data: padded logs (T steps, N episodes).
        delay: (4,) transport delay of each joint, steps.
        hold: steps the delayed command must have been held.
        tol: largest spread of the held command, PWM.
        min_count: a joint with fewer settled steps keeps none: a static fit on a handful of steps would
            bend the whole speed map to them (logs of a noisy-reference PD run hold hardly any command).
        saturation: (negative, positive) PWM magnitudes (4,) each at which the valves are fully open; commands
            beyond them count as held at full opening (a PD law at full speed wavers between 800 and 1000).
    """
    delay = np.asarray(delay)
    first = int(delay.max()) + hold
    t = np.arange(first, len(data.q) - 1)
    rows = t[None, :, None] - delay[None, None, :] - np.arange(hold)[:, None, None]  # (hold, len(t), 4)
    lagged = data.u[rows, :, np.arange(N_JOINTS)].transpose(0, 1, 3, 2)  # (hold, len(t), N, 4)
    opening = lagged if saturation is None else np.clip(lagged, -np.asarray(saturation[0]), np.asarray(saturation[1]))
    held = (opening.max(axis=0) - opening.min(axis=0)) <= tol
    settled = np.abs(data.qd[t + 1] - data.qd[t - 1]) <= 0.1 * np.abs(data.qd[t]) + 0.02
    mask = held & settled & data.mask[t + 1][..., None]
    mask &= mask.sum(axis=(0, 1)) >= min_count
    keep = mask.any(axis=-1)  # the steps at which at least one joint is settled
    return Steady(lagged[0][keep], data.q[t][keep], data.qd[t][keep], data.qd[t + 1][keep], mask[keep])


def _bin_weights(steady: Steady, width: float = 100.0, floor: int = 30) -> np.ndarray:
    """Residual weights (S, 4) that give every joint, direction and ``width``-PWM band of the held command equal weight.

    A PD law holds its commands near the dead zone most of the time; weighted per step, the static fit would
    neglect the fast, rare full-PWM moves (on the XE75 it left the bucket dumping at full PWM a third too
    fast). A band with fewer than ``floor`` steps weighs less, in proportion.
    """
    bands_per_direction = int(U_MAX // width) + 1
    band = np.minimum(np.abs(steady.u) // width, bands_per_direction - 1).astype(np.intp)
    code = np.where(steady.u > 0, band + bands_per_direction, bands_per_direction - 1 - band)  # 0 … 2·bands − 1
    joint = np.broadcast_to(np.arange(N_JOINTS), code.shape)
    counts = np.zeros((N_JOINTS, 2 * bands_per_direction))
    np.add.at(counts, (joint[steady.mask], code[steady.mask]), 1.0)
    bands = np.maximum((counts > 0).sum(axis=1), 1)
    return steady.mask / np.sqrt(np.maximum(counts[joint, code], floor) * bands)


def _linkage_guess(params: HydraulicParams, steady: Steady) -> HydraulicParams:
    """Start values of the linkage factor from a log-quadratic regression of logged over modelled steady speed.

    Started without a linkage, the local fit on the XE75 logs left it at zero (it stops after a few steps),
    so the factor ``exp(c + speed_q·r + speed_q2·r²)`` is first fitted in closed form to the ratio of the logged
    speed to the model's without a linkage, on the steady samples where both move the same way; ``exp(c)``
    goes into the speeds at full PWM.
    """
    plain = params.replace(speed_q=[0.0] * N_JOINTS, speed_q2=[0.0] * N_JOINTS)
    v_model = requested_velocity(steady.u, steady.q, steady.qd, plain)
    r = steady.q - plain.arrays.q_mid
    ok = steady.mask & (np.abs(steady.qd_next) > 0.05) & (np.abs(v_model) > 0.05) & (steady.qd_next * v_model > 0)
    coef = np.zeros((3, N_JOINTS))
    for j in np.flatnonzero(ok.sum(axis=0) >= 30):  # a regression per joint (4 at most)
        sel = ok[:, j]
        design = np.stack([np.ones(sel.sum()), r[sel, j], r[sel, j] ** 2], axis=1)
        coef[:, j] = np.linalg.lstsq(design, np.log(steady.qd_next[sel, j] / v_model[sel, j]), rcond=None)[0]
    lo, hi = BOUNDS["speed_q"], BOUNDS["speed_q2"]
    return plain.replace(
        speed_q=np.clip(coef[1], *lo).tolist(),
        speed_q2=np.clip(coef[2], *hi).tolist(),
        v_max_pos=(np.asarray(plain.v_max_pos) * np.exp(coef[0])).tolist(),
        v_max_neg=(np.asarray(plain.v_max_neg) * np.exp(coef[0])).tolist(),
    )


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


def _strided_windows(data: Padded, horizon: int, max_windows: int) -> Windows:
    usable = int(np.maximum(data.lengths - horizon - 1, 0).sum())
    return make_windows(data, horizon, stride=max(1, -(-usable // max_windows)))


def _least_squares(
    residual: Callable[[HydraulicParams], np.ndarray], params: HydraulicParams, names: Sequence[str], max_nfev: int
) -> HydraulicParams:
    """Fit the fields ``names`` within :data:`BOUNDS`; ``residual`` returns (R, 4) (one column per joint).

    Every fitted field is per joint (its last axis). The finite-difference Jacobian takes a joint's
    residuals to depend on that joint's parameters only and perturbs all joints at once. That is
    exact without pump coupling and an approximation with it: the pump couples the joints' motions.
    """
    x0 = _pack(params, names)
    lower = np.concatenate([np.full(np.size(getattr(params, n)), BOUNDS[n][0]) for n in names])
    upper = np.concatenate([np.full(np.size(getattr(params, n)), BOUNDS[n][1]) for n in names])
    x0 = np.clip(x0, lower + 1e-9 * (upper - lower), upper - 1e-9 * (upper - lower))
    rows = residual(params).size
    row_joint = np.tile(np.arange(N_JOINTS), rows // N_JOINTS)
    r_idx, c_idx = np.nonzero(row_joint[:, None] == _joint_of_columns(params, names)[None, :])
    sparsity = scipy.sparse.csr_matrix((np.ones(len(r_idx)), (r_idx, c_idx)), shape=(rows, len(x0)))
    result = least_squares(
        lambda x: residual(_unpack(x, params, names)).ravel(),
        x0,
        bounds=(lower, upper),
        jac_sparsity=sparsity,
        tr_solver="lsmr",
        x_scale="jac",
        diff_step=1e-3,
        max_nfev=max_nfev,
    )
    return _unpack(result.x, params, names)


def _simulate_episodes(params: HydraulicParams, data: Padded, gains: PDGains) -> np.ndarray:
    """Closed-loop positions (T, N, 4) rad of the logged episodes under ``gains`` (as :class:`ClosedLoop` runs them)."""
    state = initial_state(data.q[0], params)
    q = np.empty_like(data.q)
    q[0] = data.q[0]
    e_prev = wrap(data.q_ref[0] - data.q[0])
    for t in range(len(q) - 1):
        e = wrap(data.q_ref[t] - state.q)
        state = step(state, gains.command(e, e_prev), params)
        e_prev, q[t + 1] = e, state.q
    return q


def calibrate(
    records: Sequence[EpisodeRecord],
    start: HydraulicParams | None = None,
    config: FitConfig | None = None,
    gains: PDGains = XE75_PD,
    progress: Callable[[str], None] | None = None,
) -> CalibrationResult:
    """Fit the simulator to logs of a machine under its PD law.

    1. For each candidate delay: the valve-to-speed map ``STEADY_FIELDS`` on the steady samples
       (the linkage started by :func:`_linkage_guess`, the acceleration limit at :func:`logged_accel`),
       then ``JOINT_FIELDS`` by least squares on open-loop and closed-loop windows.
    2. Each joint keeps its best delay and the parameters fitted with it.
    3. Whole episodes in closed loop (logged q_ref, PD law): ``JOINT_FIELDS`` again, on the
       trajectory error plus ``mae_weight`` × the per-episode tracking-MAE mismatch.
    4. The sensor-noise levels (:func:`estimate_sensor_noise`; used only with ``sensor_noise=True``).

    Only the episodes whose reference jitter (:func:`reference_jitter`) is at most
    ``config.max_ref_jitter`` are used.

    Args:
        records: logs with the PWM ``u`` (the fit windows are cut from them).
        start: initial parameters (the shipped preset by default; joint limits, payload and noise are kept).
        config: fit settings.
        gains: the machine's PD law.
        progress: called with a line of text after each stage.

    Returns:
        The fitted parameters and their errors on the fitting logs.
    """
    cfg = config or FitConfig()
    report = progress or (lambda line: None)
    if start is None:
        start = xe75_params()
    total = len(records)
    records = select_by_jitter(records, high=cfg.max_ref_jitter, option="fit setting 'max_ref_jitter'")
    report(f"fitting on {len(records)} of {total} episodes (reference jitter ≤ {cfg.max_ref_jitter} rad)")
    data = pad(records)
    start = start.replace(accel_max=np.minimum(start.accel_max, logged_accel(data, start.dt)).tolist())
    open_w = _strided_windows(data, cfg.open_horizon, cfg.max_windows)
    closed_w = _strided_windows(data, cfg.closed_horizon, cfg.max_windows)
    weight_open = np.sqrt(closed_w.q.size / open_w.q.size)

    def window_residual(params: HydraulicParams) -> np.ndarray:
        r_open = wrap(rollout_windows(params, open_w) - open_w.q).reshape(-1, N_JOINTS) * weight_open
        r_closed = wrap(rollout_windows(params, closed_w, gains) - closed_w.q).reshape(-1, N_JOINTS)
        return np.concatenate([r_open, r_closed])

    # 1: the parameters for each delay
    fits: dict[int, HydraulicParams] = {}
    delay_cost: dict[int, np.ndarray] = {}
    for d in cfg.delays:
        steady = steady_samples(data, [d] * N_JOINTS, saturation=(start.pwm_sat_neg, start.pwm_sat_pos))
        scale = _bin_weights(steady)

        def steady_residual(params: HydraulicParams, s: Steady = steady, w: np.ndarray = scale) -> np.ndarray:
            return (requested_velocity(s.u, s.q, s.qd, params) - s.qd_next) * w

        guess = _linkage_guess(start.replace(delay=[d] * N_JOINTS), steady)
        fit = _least_squares(steady_residual, guess, STEADY_FIELDS, cfg.steady_nfev)
        rms = np.sqrt((steady_residual(fit) ** 2).sum(axis=0))
        report(f"delay {d}: steady rms speed error (rad/s) {np.round(rms, 4).tolist()}")
        fits[d] = _least_squares(window_residual, fit, JOINT_FIELDS, cfg.max_nfev)
        delay_cost[d] = (window_residual(fits[d]) ** 2).mean(axis=0)
        report(f"delay {d}: rms window error (deg) {np.round(np.degrees(np.sqrt(delay_cost[d])), 3).tolist()}")
    # 2: each joint keeps its best delay (and the parameters fitted with it)
    best = [min(cfg.delays, key=lambda d, j=j: delay_cost[d][j]) for j in range(N_JOINTS)]
    merged: dict[str, Any] = {"delay": best}
    for name in JOINT_FIELDS:
        value = np.array(getattr(fits[best[0]], name), dtype=np.float64)
        for j, d in enumerate(best):
            value[..., j] = np.asarray(getattr(fits[d], name))[..., j]
        merged[name] = value.tolist()
    params = start.replace(**merged)
    report(f"delays {best}")
    # 3: whole episodes in closed loop
    keep = np.arange(0, len(records), max(1, -(-len(records) // cfg.max_episodes)))
    episodes = pad([records[i] for i in keep])
    mask = episodes.mask[..., None]
    real_mae = tracking_mae(episodes.q, episodes)

    def episode_residual(params: HydraulicParams) -> np.ndarray:
        q = _simulate_episodes(params, episodes, gains)
        r_traj = (wrap(q - episodes.q) * mask).reshape(-1, N_JOINTS) / np.sqrt(mask.sum())
        r_mae = (tracking_mae(q, episodes) - real_mae) * cfg.mae_weight / np.sqrt(len(keep))
        return np.concatenate([r_traj, r_mae])

    params = _least_squares(episode_residual, params, JOINT_FIELDS, cfg.max_nfev)
    noise_q, noise_qd = estimate_sensor_noise(data, start.dt)
    params = params.replace(noise_q=noise_q.tolist(), noise_qd=noise_qd.tolist())
    ratio = tracking_mae(_simulate_episodes(params, episodes, gains), episodes).mean(axis=0) / real_mae.mean(axis=0)
    report(f"whole episodes: PD tracking MAE ratio sim/real {np.round(ratio, 3).tolist()}")
    return CalibrationResult(
        params=params,
        open_loop_deg=np.degrees(window_error(params, open_w)),
        closed_loop_deg=np.degrees(window_error(params, closed_w, gains)),
        mae_ratio=ratio,
        delay_cost=delay_cost,
    )


class Fidelity(NamedTuple):
    """How closely a simulator reproduces a machine's logs (see the module docstring).

    Attributes:
        real_mae_deg: (4,) deg, PD tracking MAE per joint of the logs.
        sim_mae_deg: (4,) deg, the same for the simulator driven with the logged q_ref.
        ratio: (4,) sim / real.
        mpe20_deg: (4,) deg, open-loop 20-step position error per joint, or None without a plant.
        travel_ratio20: (4,) real / simulated joint travel over the open-loop windows, or None without a plant
            (NaN for a joint the simulator never moves).
        q_sim: (T, N, 4) rad, the simulated closed-loop positions (padded like ``data``).
        data: the padded logs.
    """

    real_mae_deg: np.ndarray
    sim_mae_deg: np.ndarray
    ratio: np.ndarray
    mpe20_deg: np.ndarray | None
    travel_ratio20: np.ndarray | None
    q_sim: np.ndarray
    data: Padded

    def to_json(self, decimals: int = 4) -> dict[str, Any]:
        """The one-line JSON report: ``{"closed_loop": {...}, "open_loop": {"mpe20_deg": [4], "travel_ratio20": [4]}}``.

        The open-loop lists are null without a plant; a NaN value (a joint the simulator never moves) is null.

        Args:
            decimals: digits after the decimal point each value (deg, or the unitless ratio) is rounded to.
        """

        def r(x: np.ndarray | None) -> list[float | None] | None:
            return None if x is None else [round(float(v), decimals) if np.isfinite(v) else None for v in x]

        return {
            "closed_loop": {"real_mae_deg": r(self.real_mae_deg), "sim_mae_deg": r(self.sim_mae_deg), "ratio": r(self.ratio)},
            "open_loop": {"mpe20_deg": r(self.mpe20_deg), "travel_ratio20": r(self.travel_ratio20)},
        }


def _accepts_history(plant: Any) -> bool:
    try:
        names = inspect.signature(plant.reset).parameters
    except (TypeError, ValueError):
        return False
    return "qd0" in names and "u_past" in names and bool(getattr(plant, "batched", False))


def open_loop_replay(plant: BatchedSystem, data: Padded, horizon: int = 20, stride: int = 10) -> tuple[np.ndarray, Windows]:
    """Replay the logged PWM from every ``stride``-th step (definition in the module docstring).

    Args:
        plant: the PWM-level plant (checked view; the raw plant is used for history-aware resets).
        data: padded logs with the PWM ``u``.
        horizon: steps replayed from each start.
        stride: distance between window starts, steps.

    Returns:
        The simulated positions q (H, W, 4) rad, and the windows they replay (logged positions ``windows.q``).
    """
    w = make_windows(data, horizon, stride=stride)
    raw = plant.system
    if _accepts_history(raw):
        raw.reset(w.q0, qd0=w.qd0, u_past=w.u_past)
        return np.stack([np.asarray(raw.step(u), dtype=np.float64)[:, :N_JOINTS] for u in w.u]), w
    chunk = plant.max_batch or len(w.q0)
    parts = []
    for i in range(0, len(w.q0), chunk):
        part = slice(i, i + chunk)
        plant.reset(w.q0[part])
        parts.append(np.stack([plant.step(u[part])[:, :N_JOINTS] for u in w.u]))
    return np.concatenate(parts, axis=1), w


def open_loop_mpe(q_sim: np.ndarray, windows: Windows) -> np.ndarray:
    """Open-loop position error per joint, mean over the steps and windows, (4,) rad.

    Args:
        q_sim: (H, W, 4) rad, simulated positions from :func:`open_loop_replay`.
        windows: the windows replayed (W of them).
    """
    return np.abs(wrap(q_sim - windows.q)).mean(axis=(0, 1))


def travel_ratio(q_sim: np.ndarray, windows: Windows) -> np.ndarray:
    """Real over simulated joint travel at the windows' end, (4,), NaN for a joint the simulation never moves.

    Args:
        q_sim: (H, W, 4) rad, simulated positions from :func:`open_loop_replay`.
        windows: the windows replayed (W of them).
    """
    real = wrap(windows.q[-1] - windows.q0)
    sim = wrap(q_sim[-1] - windows.q0)
    power = (sim * sim).sum(axis=0)
    return np.divide((real * sim).sum(axis=0), power, out=np.full(N_JOINTS, np.nan), where=power > 0)


def fidelity(
    records: Sequence[EpisodeRecord], system: BatchedSystem, plant: BatchedSystem | None = None, stride: int = 10
) -> Fidelity:
    """Closed-loop PD tracking MAE of a system vs the logs, and the plant's open-loop 20-step error and travel.

    Args:
        records: logs of the real machine under its PD law (``u`` needed for the open loop).
        system: the reference-level system (PD law included).
        plant: its PWM-level plant, for the open-loop figures (skipped when None).
        stride: distance between the open-loop window starts, steps.

    Returns:
        The comparison; angles in degrees.
    """
    data = pad(records)
    if system.max_batch is None:
        q_sim = closed_loop_rollout(system, data)
    else:  # an unbatched system runs one episode at a time
        q_sim = np.empty_like(data.q)
        for i, record in enumerate(records):
            q_i = closed_loop_rollout(system, pad([record]))[:, 0]
            q_sim[: len(q_i), i], q_sim[len(q_i) :, i] = q_i, q_i[-1]
    real = np.degrees(tracking_mae(data.q, data).mean(axis=0))
    sim = np.degrees(tracking_mae(q_sim, data).mean(axis=0))
    mpe = travel = None
    if plant is not None:
        if any(r.u is None for r in records):
            raise EfficientTrackError("open-loop fidelity needs logs with the PWM command 'u'")
        q_open, windows = open_loop_replay(plant, data, stride=stride)
        mpe = np.degrees(open_loop_mpe(q_open, windows))
        travel = travel_ratio(q_open, windows)
    return Fidelity(real, sim, sim / np.maximum(real, 1e-12), mpe, travel, q_sim, data)


def _significant(value: Any, digits: int = 6) -> Any:
    """Round floats (also inside lists) to ``digits`` significant digits for a readable preset."""
    if isinstance(value, list):
        return [_significant(v, digits) for v in value]
    return float(f"{value:.{digits}g}") if isinstance(value, float) else value


def save_params(params: HydraulicParams, path: str | Path) -> Path:
    """Write a preset as small reviewable JSON, one parameter per line, floats to 6 significant digits, atomically.

    Args:
        params: the simulator parameters to write (every field, as :meth:`HydraulicParams.to_dict` gives them).
        path: destination JSON file; parent folders are created.

    Returns:
        The destination path.
    """
    values = {key: _significant(value) for key, value in params.to_dict().items()}
    lines = ",\n".join(f"  {json.dumps(key)}: {json.dumps(value)}" for key, value in values.items())
    return atomic_write(path, lambda f: f.write("{\n" + lines + "\n}\n"), mode="w")
