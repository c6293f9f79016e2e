"""Fit the hydraulic simulator to a machine's logs (PWM → motion).

Calibration (:func:`calibrate`) first fits the valve-to-speed map to the logged steps at which a command has
been held until the joint settled (:func:`steady_samples`; a static fit, cheap and well posed, that weighs
every band of held PWM alike: :func:`_bin_weights`), then minimizes multi-step position errors with
``scipy.optimize.least_squares``: windows are cut from the logs (:func:`~efficienttrack.systems.fit.logs.make_windows`),
the simulator is started in each window's logged state and driven either with the logged PWM (open loop) or
by the PD law along the logged ``q_ref`` (closed loop) (:func:`~efficienttrack.systems.fit.simulate.rollout_windows`);
the residual is ``wrap(q_sim − q_log)`` over every step of every window. Integer delays are chosen per joint on
a grid. A last stage runs whole episodes in closed loop and also matches each episode's PD tracking MAE.
Episodes with a strongly perturbed reference are left out (:func:`~efficienttrack.systems.fit.logs.reference_jitter`).
The shipped ``xe75`` preset was fitted this way on ``pd_noise_train`` (its 200 passes with σ ≤ 0.008 rad).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write
from efficienttrack.core.joints import N_JOINTS
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.systems.fit.logs import (
    Padded,
    Windows,
    estimate_sensor_noise,
    logged_accel,
    make_windows,
    pad,
    select_by_jitter,
    tracking_mae,
    window_error,
)
from efficienttrack.systems.fit.simulate import rollout_windows, simulate_episodes
from efficienttrack.systems.hydraulic import U_MAX, HydraulicParams, requested_velocity, xe75_params
from efficienttrack.systems.pd import XE75_PD, PDGains

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
    delays = np.asarray(delay)
    first = int(delays.max()) + hold
    t = np.arange(first, len(data.q) - 1)
    rows = t[None, :, None] - delays[None, None, :] - np.arange(hold)[:, None, None]  # (hold, len(t), 4)
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
    import scipy.sparse  # here, not at the top: the CLI reads FitConfig's defaults at start-up, scipy costs ~0.5 s
    from scipy.optimize import least_squares

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
    best = [min(cfg.delays, key=lambda d: delay_cost[d][j]) for j in range(N_JOINTS)]
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
        q = simulate_episodes(params, episodes, gains)
        r_traj = (wrap(q - episodes.q) * mask).reshape(-1, N_JOINTS) / np.sqrt(mask.sum())
        r_mae = (tracking_mae(q, episodes) - real_mae) * cfg.mae_weight / np.sqrt(len(keep))
        return np.concatenate([r_traj, r_mae])

    params = _least_squares(episode_residual, params, JOINT_FIELDS, cfg.max_nfev)
    noise_q, noise_qd = estimate_sensor_noise(data, start.dt)
    params = params.replace(noise_q=noise_q.tolist(), noise_qd=noise_qd.tolist())
    ratio = tracking_mae(simulate_episodes(params, episodes, gains), episodes).mean(axis=0) / real_mae.mean(axis=0)
    report(f"whole episodes: PD tracking MAE ratio sim/real {np.round(ratio, 3).tolist()}")
    return CalibrationResult(
        params=params,
        open_loop_deg=np.degrees(window_error(rollout_windows(params, open_w), open_w)),
        closed_loop_deg=np.degrees(window_error(rollout_windows(params, closed_w, gains), closed_w)),
        mae_ratio=ratio,
        delay_cost=delay_cost,
    )


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
