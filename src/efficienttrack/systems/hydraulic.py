"""The built-in hydraulic excavator simulator (PWM level), vectorized over N machines.

Per joint j (boom, arm, bucket, swing) and step t, with the PWM u[t] clipped to ±1000:

1. **Transport delay**: the valve sees the command of ``delay[j]`` steps ago, ``u_d = u[t − delay]``.
2. **Spool lag**: the valve spool follows ``u_d`` with time constant ``tau_spool`` (in PWM units, ``s``), so a
   one-step PWM spike opens the valve only a little while a held command opens it fully.
3. **Dead zone, flow curve, saturation**: the valve opening is
   ``x = flow(clip((|s| − dz) / (sat − dz), 0, 1))``, a piecewise-linear flow characteristic
   ``flow`` (0 at 0, 1 at 1, ``flow_curve`` at the evenly spaced knots between). The dead zone ``dz`` and the
   saturation ``sat`` depend on the direction (``pwm_sat_pos``/``pwm_sat_neg``: a cylinder may reach its
   full speed earlier one way); the dead zone shifts linearly with the joint angle (``dead_zone_q``) and is
   larger for a joint at rest (``dead_zone_rest``, breakaway, fading out up to ``rest_speed``).
4. **Direction asymmetry, gravity and payload**: the requested speed is
   ``v_max_pos·(1 + payload_pos·payload)·x`` for s > 0 and ``v_max_neg·(1 + payload_neg·payload)·x``
   for s < 0 (boom raising and lowering differ, and a loaded bucket slows the raising), times the
   linkage factor ``exp(speed_q·r + speed_q2·r²)`` of the angle r from the middle of the joint range:
   a cylinder turns its joint through a linkage whose lever arm changes with the angle (at a held
   full PWM the XE75's bucket moves about twice as fast near 1.8 rad as near 0.2 rad).
5. **Pump sharing**: the joints share the pump, so every open valve lowers the supply to the others
   (and, through its own pressure drop, to itself): joint j's requested speed is divided by
   ``1 + Σ_i pump_coupling[i][j]·x[i]``.
6. **Actuator lag**: the joint velocity follows the requested velocity with time constant ``tau``
   when speeding up and ``tau_brake`` when slowing down or reversing, changing by at most
   ``accel_max·dt`` per step (the relief pressure limits the torque on a heavy link).
7. **Integration and limits**: ``q += dt·q̇``; boom, arm and bucket stop at ``[q_min, q_max]``;
   the swing wraps at ±π.

Sign convention (as the real XE75): a positive PWM moves boom, arm and bucket towards smaller
angles and the swing towards larger angles. The observation is ``(q, q̇)`` (8,)/(N, 8), plus
optional Gaussian sensor noise drawn from a seeded generator.

The physics is the pure function :func:`step` on a :class:`HydraulicState` with a frozen
:class:`HydraulicParams`; :class:`HydraulicExcavator` is the thin stateful Plant on top.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.configfile import check_seed, read_mapping_file
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, N_JOINTS, SWING
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits
from efficienttrack.systems.pd import XE75_PD, ClosedLoop
from efficienttrack.systems.protocol import machines_to_reset

U_MAX = 1000.0
DIRECTION = np.array([-1.0, -1.0, -1.0, 1.0])
"""Sign of the joint velocity for a positive PWM (boom, arm, bucket, swing)."""

_JOINT_INDEX = np.arange(N_JOINTS)

Vec4 = tuple[float, float, float, float]


@dataclass(frozen=True)
class HydraulicParams:
    """Parameters of the hydraulic excavator model; per-joint tuples are (boom, arm, bucket, swing)."""

    delay: tuple[int, int, int, int] = (4, 4, 4, 4)
    """Hydraulic transport delay, whole control steps from the command to the valve."""
    tau_spool: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Time constant of the valve spool following the delayed command (0: the spool follows at once), s."""
    tau: Vec4 = (0.10, 0.10, 0.10, 0.10)
    """Time constant of the first-order actuator lag while speeding up, s."""
    tau_brake: Vec4 = (0.10, 0.10, 0.10, 0.10)
    """Time constant of the actuator lag while slowing down or reversing (the closing valve brakes), s."""
    accel_max: Vec4 = (1000.0, 1000.0, 1000.0, 1000.0)
    """Largest joint acceleration or deceleration (torque limited by the relief valves), rad/s²."""
    dead_zone_pos: Vec4 = (480.0, 470.0, 500.0, 450.0)
    """Valve dead zone for positive PWM at angle 0, PWM."""
    dead_zone_neg: Vec4 = (480.0, 470.0, 480.0, 450.0)
    """Valve dead zone for negative PWM at angle 0, PWM."""
    dead_zone_q: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Change of both dead zones per rad of joint angle (state-dependent dead zone), PWM/rad."""
    dead_zone_rest: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Extra dead zone of a joint at rest (breakaway), fading out linearly up to ``rest_speed``, PWM."""
    rest_speed: Vec4 = (0.05, 0.05, 0.05, 0.05)
    """Joint speed from which the extra rest dead zone is gone, rad/s."""
    pwm_sat_pos: Vec4 = (1000.0, 1000.0, 1000.0, 1000.0)
    """Positive PWM at which the valve is fully open (flow saturation), PWM."""
    pwm_sat_neg: Vec4 = (1000.0, 1000.0, 1000.0, 1000.0)
    """Negative PWM magnitude at which the valve is fully open (flow saturation), PWM."""
    flow_curve: tuple[Vec4, ...] = ((0.2,) * 4, (0.4,) * 4, (0.6,) * 4, (0.8,) * 4)
    """Valve opening 0..1 at the evenly spaced interior knots of the normalized PWM beyond the dead zone (rows: knots)."""
    v_max_pos: Vec4 = (0.10, 0.40, 1.80, 0.25)
    """Joint speed at full positive PWM with no load and no pump sharing, rad/s (saturation)."""
    v_max_neg: Vec4 = (0.20, 0.30, 0.90, 0.25)
    """Joint speed at full negative PWM with no load and no pump sharing, rad/s (saturation)."""
    speed_q: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Linkage: change of the log joint speed per rad from the middle of the joint range, 1/rad."""
    speed_q2: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Linkage: second-order term of the log joint speed in the angle from the middle of the range, 1/rad²."""
    payload_pos: Vec4 = (-0.30, -0.10, -0.05, 0.0)
    """Relative change of the positive-PWM speed per unit payload (boom raising is negative)."""
    payload_neg: Vec4 = (0.10, 0.05, 0.0, 0.0)
    """Relative change of the negative-PWM speed per unit payload (boom lowering is positive)."""
    pump_coupling: tuple[Vec4, Vec4, Vec4, Vec4] = (
        (0.0, 0.3, 0.3, 0.3),
        (0.3, 0.0, 0.3, 0.3),
        (0.3, 0.3, 0.0, 0.3),
        (0.3, 0.3, 0.3, 0.0),
    )
    """Slow-down of joint j (column) per unit valve opening of joint i (row) through the shared pump."""
    q_min: Vec4 = (-0.60, -1.20, -0.60, -math.pi)
    """Lower joint limits, rad (the swing is not limited: it wraps at ±π)."""
    q_max: Vec4 = (0.70, 0.60, 2.50, math.pi)
    """Upper joint limits, rad (the swing is not limited: it wraps at ±π)."""
    noise_q: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Standard deviation of the position sensor noise, rad (used when sensor noise is on)."""
    noise_qd: Vec4 = (0.0, 0.0, 0.0, 0.0)
    """Standard deviation of the velocity sensor noise, rad/s (used when sensor noise is on)."""
    payload: float = 0.0
    """Bucket load fraction, 0 (empty) … 1 (full)."""
    dt: float = DT
    """Control period, s."""

    def __post_init__(self) -> None:
        """Validate every field: per-joint tuples of 4 finite numbers, sensible ranges."""
        rows = {"flow_curve": len(self.flow_curve) if isinstance(self.flow_curve, tuple) else 0, "pump_coupling": N_JOINTS}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in rows:
                if not value or not all(isinstance(row, tuple) and len(row) == N_JOINTS for row in value):
                    raise EfficientTrackError(f"hydraulic parameter '{f.name}': needs rows of 4 numbers, got {value!r}")
                value = tuple(v for row in value for v in row)
            if isinstance(value, tuple):
                if len(value) != N_JOINTS * rows.get(f.name, 1) or not all(
                    isinstance(v, int | float) and math.isfinite(v) for v in value
                ):
                    raise EfficientTrackError(f"hydraulic parameter '{f.name}': needs 4 finite numbers, got {value!r}")
            elif not isinstance(value, int | float) or not math.isfinite(value):
                raise EfficientTrackError(f"hydraulic parameter '{f.name}': needs a finite number, got {value!r}")
        checks = {
            "delay": all(int(d) == d and 0 <= d <= 20 for d in self.delay),
            "tau_spool": all(t >= 0 for t in self.tau_spool),
            "tau": all(t >= 0 for t in self.tau),
            "tau_brake": all(t >= 0 for t in self.tau_brake),
            "accel_max": all(a > 0 for a in self.accel_max),
            "dead_zone_pos": all(0 <= d < U_MAX for d in self.dead_zone_pos),
            "dead_zone_neg": all(0 <= d < U_MAX for d in self.dead_zone_neg),
            "flow_curve": all(0.0 <= v <= 2.0 for row in self.flow_curve for v in row),
            "dead_zone_rest": all(d >= 0 for d in self.dead_zone_rest),
            "rest_speed": all(v > 0 for v in self.rest_speed),
            "pwm_sat_pos": all(0 < s <= U_MAX for s in self.pwm_sat_pos),
            "pwm_sat_neg": all(0 < s <= U_MAX for s in self.pwm_sat_neg),
            "v_max_pos": all(v >= 0 for v in self.v_max_pos),
            "v_max_neg": all(v >= 0 for v in self.v_max_neg),
            "pump_coupling": all(c >= 0 for row in self.pump_coupling for c in row),
            "q_max": all(lo < hi for lo, hi in zip(self.q_min, self.q_max, strict=True)),
            "noise_q": all(s >= 0 for s in self.noise_q),
            "noise_qd": all(s >= 0 for s in self.noise_qd),
            "payload": 0.0 <= self.payload <= 1.0,
            "dt": self.dt > 0,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise EfficientTrackError(f"hydraulic parameters out of range: {', '.join(bad)}")

    @cached_property
    def arrays(self) -> _Arrays:
        """The parameters as numpy arrays, shaped for the vectorized step (computed once)."""
        a = {f.name: np.asarray(getattr(self, f.name), dtype=np.float64) for f in fields(self)}
        load = self.payload
        v_pos = DIRECTION * a["v_max_pos"] * np.maximum(1.0 + a["payload_pos"] * load, 0.0)
        v_neg = -DIRECTION * a["v_max_neg"] * np.maximum(1.0 + a["payload_neg"] * load, 0.0)
        return _Arrays(
            delay=np.asarray(self.delay, dtype=np.intp),
            beta=1.0 - np.exp(-self.dt / np.maximum(a["tau_spool"], 1e-9)),
            q_mid=np.where(np.arange(N_JOINTS) == SWING, 0.0, (a["q_min"] + a["q_max"]) / 2),
            speed_q=a["speed_q"],
            speed_q2=a["speed_q2"],
            alpha=1.0 - np.exp(-self.dt / np.maximum(a["tau"], 1e-9)),
            alpha_brake_minus_accel=np.exp(-self.dt / np.maximum(a["tau"], 1e-9))
            - np.exp(-self.dt / np.maximum(a["tau_brake"], 1e-9)),
            dv_max=a["accel_max"] * self.dt,
            dv_min=-a["accel_max"] * self.dt,
            dz_pos=a["dead_zone_pos"],
            dz_neg=a["dead_zone_neg"],
            dz_q=a["dead_zone_q"],
            dz_rest=a["dead_zone_rest"],
            inv_rest_speed=1.0 / a["rest_speed"],
            sat_pos=a["pwm_sat_pos"],
            sat_neg=a["pwm_sat_neg"],
            flow_table=np.concatenate([np.zeros((1, N_JOINTS)), a["flow_curve"], np.ones((1, N_JOINTS))]),
            v_pos=v_pos,
            v_neg=v_neg,
            pump_coupling=a["pump_coupling"],
            q_min=np.where(np.arange(N_JOINTS) == SWING, -np.inf, a["q_min"]),
            q_max=np.where(np.arange(N_JOINTS) == SWING, np.inf, a["q_max"]),
            noise=np.concatenate([a["noise_q"], a["noise_qd"]]),
            dt=float(self.dt),
        )

    @property
    def top_speed(self) -> np.ndarray:
        """(4,) rad/s, the fastest each joint can move: full valve, no pump sharing, the linkage's fastest angle."""
        p = self.arrays
        r = np.linspace(np.asarray(self.q_min) - p.q_mid, np.asarray(self.q_max) - p.q_mid, 101)
        linkage = np.exp((p.speed_q + p.speed_q2 * r) * r).max(axis=0)
        return np.maximum(np.abs(p.v_pos), np.abs(p.v_neg)) * p.flow_table.max(axis=0) * linkage

    def guard_limits(self) -> GuardLimits:
        """The limits of the runtime guard for this machine: its joint range, and twice its top speed as plausible.

        Boom, arm and bucket may be sent references within ``[q_min, q_max]``; the swing is unlimited (it wraps).
        The adjustment bounds are the package's (:data:`~efficienttrack.systems.limits.XE75_MAX_ADJUST`).
        """
        swing = np.arange(N_JOINTS) == SWING
        return DEFAULT_LIMITS.replace(
            q_min=tuple(float(v) for v in np.where(swing, -math.pi, self.q_min)),
            q_max=tuple(float(v) for v in np.where(swing, math.pi, self.q_max)),
            max_speed=tuple(float(v) for v in 2.0 * self.top_speed),
        )

    @property
    def max_delay(self) -> int:
        """Longest transport delay over the joints, steps."""
        return int(max(self.delay))

    def replace(self, **changes: Any) -> HydraulicParams:
        """A copy with some fields changed (lists become tuples); unknown names raise EfficientTrackError.

        Args:
            **changes: field name → new value (units as in the field's docstring).
        """
        names = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise EfficientTrackError(f"unknown hydraulic parameter(s): {', '.join(unknown)}")
        values = self.to_dict()
        values.update(changes)
        return HydraulicParams.from_dict(values)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable fields (tuples as lists)."""
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, values: dict[str, Any], source: str = "hydraulic parameters") -> HydraulicParams:
        """Build from a dict of fields (lists for per-joint values); raise EfficientTrackError on bad input.

        Args:
            values: field name → value, e.g. as read from a JSON preset; fields left out keep their defaults.
            source: where ``values`` came from, named in error messages.
        """
        if not isinstance(values, dict):
            raise EfficientTrackError(f"{source}: expected a JSON object of parameters")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise EfficientTrackError(f"{source}: unknown parameter(s) {', '.join(unknown)}")
        kwargs: dict[str, Any] = {}
        for key, value in values.items():
            if key in ("flow_curve", "pump_coupling") and isinstance(value, list):
                value = tuple(tuple(row) if isinstance(row, list) else row for row in value)
            elif isinstance(value, list):
                value = tuple(int(v) if key == "delay" and float(v).is_integer() else v for v in value)
            kwargs[key] = value
        try:
            return cls(**kwargs)
        except EfficientTrackError as exc:
            raise EfficientTrackError(f"{source}: {exc}") from exc

    @classmethod
    def load(cls, path: str | Path) -> HydraulicParams:
        """Read a JSON preset file: every field of this class (as written by ``efficienttrack sim calibrate``).

        Args:
            path: the JSON preset file; it must give every field.
        """
        path = Path(path)
        values = read_mapping_file(path)  # size-capped, duplicated keys refused
        missing = [f.name for f in fields(cls) if isinstance(values, dict) and f.name not in values]
        if missing:
            raise EfficientTrackError(f"{path}: simulator preset lacks parameter(s) {', '.join(missing)}")
        return cls.from_dict(values, source=str(path))


class _Arrays(NamedTuple):
    """Derived numpy views of :class:`HydraulicParams` used by :func:`step`."""

    delay: np.ndarray
    beta: np.ndarray
    q_mid: np.ndarray
    speed_q: np.ndarray
    speed_q2: np.ndarray
    alpha: np.ndarray
    alpha_brake_minus_accel: np.ndarray
    dv_max: np.ndarray
    dv_min: np.ndarray
    dz_pos: np.ndarray
    dz_neg: np.ndarray
    dz_q: np.ndarray
    dz_rest: np.ndarray
    inv_rest_speed: np.ndarray
    sat_pos: np.ndarray
    sat_neg: np.ndarray
    flow_table: np.ndarray
    v_pos: np.ndarray
    v_neg: np.ndarray
    pump_coupling: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    noise: np.ndarray
    dt: float


class HydraulicState(NamedTuple):
    """State of N simulated machines.

    Attributes:
        q: (N, 4) rad, joint positions.
        qd: (N, 4) rad/s, joint velocities.
        u_hist: (N, D, 4) PWM, the last D commands, newest first (D = max delay + 1).
        spool: (N, 4) PWM, the valve spool position (the delayed command after the spool lag).
    """

    q: np.ndarray
    qd: np.ndarray
    u_hist: np.ndarray
    spool: np.ndarray


def initial_state(
    q0: np.ndarray, params: HydraulicParams, qd0: np.ndarray | None = None, u_past: np.ndarray | None = None
) -> HydraulicState:
    """State of N machines at ``q0`` (N, 4) rad; at rest with empty delay lines unless told otherwise.

    Args:
        q0: (N, 4) rad, joint positions.
        params: model parameters (sets the delay-line length).
        qd0: (N, 4) rad/s, joint velocities; zeros by default.
        u_past: (K, N, 4) PWM, the last K commands in time order (the last row is the command of the
            step just before); fills the delay line and sets the spool as if they had passed through
            it (older commands count as zero).

    Returns:
        The state.
    """
    q0 = np.array(q0, dtype=np.float64)
    n = len(q0)
    qd = np.zeros((n, N_JOINTS)) if qd0 is None else np.array(qd0, dtype=np.float64).reshape(n, N_JOINTS)
    u_hist = np.zeros((n, params.max_delay + 1, N_JOINTS))
    spool = np.zeros((n, N_JOINTS))
    if u_past is not None:
        recent = np.clip(np.asarray(u_past, dtype=np.float64).reshape(-1, n, N_JOINTS), -U_MAX, U_MAX)[::-1]
        k = min(len(recent), params.max_delay + 1)
        u_hist[:, :k] = recent[:k].transpose(1, 0, 2)
        # the spool has filtered the delayed commands: weight beta·(1 − beta)^age of each, newest first
        p = params.arrays
        age = np.arange(len(recent))[:, None] - p.delay[None, :]
        weights = np.where(age >= 0, p.beta * (1.0 - p.beta) ** np.maximum(age, 0), 0.0)
        spool = np.einsum("knj,kj->nj", recent, weights)
    return HydraulicState(q=q0, qd=qd, u_hist=u_hist, spool=spool)


def requested_velocity(spool: np.ndarray, q: np.ndarray, qd: np.ndarray, params: HydraulicParams) -> np.ndarray:
    """The joint velocity the valves ask for (steps 3–5 of the model: the speed the joint settles at), (N, 4) rad/s.

    Args:
        spool: (N, 4) PWM, the valve spool positions.
        q: (N, 4) rad, joint positions (state-dependent dead zone, linkage).
        qd: (N, 4) rad/s, joint velocities (the extra dead zone at rest).
        params: model parameters.
    """
    p = params.arrays
    # valve: direction- and state-dependent dead zone, flow curve, saturation
    pos = spool > 0.0
    dz = np.where(pos, p.dz_pos, p.dz_neg) + p.dz_q * q
    dz += p.dz_rest * np.maximum(1.0 - np.abs(qd) * p.inv_rest_speed, 0.0)
    sat = np.where(pos, p.sat_pos, p.sat_neg)
    x = (np.abs(spool) - dz) / np.maximum(sat - dz, 1.0)
    x = np.minimum(np.maximum(x, 0.0), 1.0) * (len(p.flow_table) - 1)
    i = np.minimum(x.astype(np.intp), len(p.flow_table) - 2)
    lo = p.flow_table[i, _JOINT_INDEX]
    opening = lo + (x - i) * (p.flow_table[i + 1, _JOINT_INDEX] - lo)
    # pump sharing
    share = 1.0 / (1.0 + np.einsum("ni,ij->nj", opening, p.pump_coupling))  # not @: BLAS sums differ with N
    # direction asymmetry / payload, linkage
    r = q - p.q_mid
    linkage = np.exp((p.speed_q + p.speed_q2 * r) * r)
    return np.where(pos, p.v_pos, p.v_neg) * opening * share * linkage


def step(state: HydraulicState, u: np.ndarray, params: HydraulicParams) -> HydraulicState:
    """Advance N machines by one control period.

    Args:
        state: the current state (N machines).
        u: (N, 4) PWM command of this step; clipped to ±1000.
        params: model parameters.

    Returns:
        The next state; ``q`` (N, 4) rad, ``qd`` (N, 4) rad/s.
    """
    p = params.arrays
    u_now = np.minimum(np.maximum(u, -U_MAX), U_MAX)
    u_hist = np.concatenate((u_now[:, None, :], state.u_hist[:, :-1]), axis=1)
    u_d = u_hist[:, p.delay, _JOINT_INDEX]
    spool = state.spool + p.beta * (u_d - state.spool)
    v_cmd = requested_velocity(spool, state.q, state.qd, params)
    # first-order lag (faster when braking), acceleration limit
    dv = v_cmd - state.qd
    change = (p.alpha + (dv * state.qd < 0.0) * p.alpha_brake_minus_accel) * dv
    qd = state.qd + np.minimum(np.maximum(change, p.dv_min), p.dv_max)
    q, qd = within_limits(state.q + p.dt * qd, qd, params)
    return HydraulicState(q=q, qd=qd, u_hist=u_hist, spool=spool)


def within_limits(q: np.ndarray, qd: np.ndarray, params: HydraulicParams) -> tuple[np.ndarray, np.ndarray]:
    """Joints stopped at their limits (swing unlimited, wrapped to (−π, π]): the machine cannot be elsewhere.

    Args:
        q: (N, 4) rad, joint positions.
        qd: (N, 4) rad/s, joint velocities.
        params: model parameters (``q_min``, ``q_max``).

    Returns:
        ``q`` clamped into the limits, and ``qd`` with 0 where a joint was stopped.
    """
    p = params.arrays
    q_lim = np.minimum(np.maximum(q, p.q_min), p.q_max)
    qd = qd * (q_lim == q)
    q_lim[:, SWING] = wrap(q_lim[:, SWING])
    return q_lim, qd


def observe(state: HydraulicState, params: HydraulicParams, rng: np.random.Generator | None = None) -> np.ndarray:
    """Observation (N, 8) = [q rad, q̇ rad/s], with sensor noise when ``rng`` is given.

    Args:
        state: the state of N machines (``q`` (N, 4) rad, ``qd`` (N, 4) rad/s).
        params: model parameters (the noise std ``noise_q`` rad / ``noise_qd`` rad/s).
        rng: generator of the sensor noise; None for noise-free observations.

    Returns:
        (N, 8) [rad, rad/s], ``[q, qd]``.
    """
    obs = np.concatenate((state.q, state.qd), axis=1)
    if rng is not None:
        obs += rng.standard_normal(obs.shape) * params.arrays.noise
    return obs


class HydraulicExcavator:
    """The hydraulic excavator simulator as a batched Plant (see the module docstring for the model).

    ====== ============ ===================== ==========================================
    name   shape        unit / limits         meaning
    ====== ============ ===================== ==========================================
    q0     (4,)/(N, 4)  rad                   ``reset``: positions; at rest, empty delay lines
    u      (4,)/(N, 4)  PWM, clipped ±1000    ``step``: valve commands
    obs    (8,)/(N, 8)  [q rad, q̇ rad/s]      q within [q_min, q_max] (swing in (−π, π])
    ====== ============ ===================== ==========================================

    ``dt`` = ``params.dt`` (0.05 s). ``reset`` clamps a start outside ``[q_min, q_max]`` into the limits (and wraps
    the swing), as ``step`` would at once: the simulated machine cannot stand beyond its end stops, and logs of the
    real machine read slightly past the fitted limits (the bucket at −0.519 rad against −0.50), so refusing them would
    refuse real windows. References outside the limits are refused before anything runs (``runtime.track``).
    ``limits`` are the runtime guard's (:meth:`HydraulicParams.guard_limits`). ``reset`` optionally takes the logged
    velocity ``qd0`` and the last commands ``u_past`` (K, 4)/(K, N, 4), time order, to start in a logged state. Output rank
    follows the ``q0`` given to ``reset``. Version 3 (the model of this module docstring; version 2 had no
    linkage factor and no acceleration limit, version 1 also no spool lag, one saturation per joint and a pump
    limit instead of the pump coupling).

    Args:
        params: model parameters.
        sensor_noise: add Gaussian noise of std ``params.noise_q`` / ``noise_qd`` to the observations.
        seed: seed of the noise generator (re-seeded at construction only).
    """

    batched = True

    def __init__(self, params: HydraulicParams, sensor_noise: bool = False, seed: int = 0) -> None:
        check_seed(seed, "hydraulic simulator: option 'seed'")
        self.params = params
        self.dt = params.dt
        self.sensor_noise = bool(sensor_noise)
        self._rng = np.random.default_rng(seed)
        self.state: HydraulicState | None = None
        self._single = False

    @property
    def limits(self) -> GuardLimits:
        """What the runtime guard may send this machine (:meth:`HydraulicParams.guard_limits`)."""
        return self.params.guard_limits()

    def reset(self, q0: np.ndarray, qd0: np.ndarray | None = None, u_past: np.ndarray | None = None) -> np.ndarray:
        """Machines at ``q0`` (4,)/(N, 4) rad; return obs (8,)/(N, 8).

        At rest with empty delay lines by default; ``qd0`` (4,)/(N, 4) rad/s and ``u_past``
        (K, 4)/(K, N, 4) PWM (the last K commands, time order) start them in a logged state instead.
        """
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape[-1:] != (N_JOINTS,) or q0.ndim not in (1, 2):
            raise EfficientTrackError(f"hydraulic simulator: reset expects q0 of shape (4,) or (N, 4), got {q0.shape}")
        self._single = q0.ndim == 1
        n = 1 if self._single else len(q0)
        if qd0 is not None and np.size(qd0) != n * N_JOINTS:
            raise EfficientTrackError(f"hydraulic simulator: qd0 must match q0 {q0.shape}, got {np.shape(qd0)}")
        if u_past is not None and np.size(u_past) % (n * N_JOINTS):
            raise EfficientTrackError(f"hydraulic simulator: u_past must be (K, {n}, 4), got {np.shape(u_past)}")
        state = initial_state(q0.reshape(n, N_JOINTS), self.params, qd0, u_past)
        q, qd = within_limits(state.q, state.qd, self.params)
        self.state = state._replace(q=q, qd=qd)
        return self._obs()

    def reset_machines(self, index: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Reset some of the N machines at rest at ``q0``; the others keep their state (a vector env's autoreset).

        Args:
            index: (K,) int, which machines (of a batched reset).
            q0: (K, 4) rad, their start positions.

        Returns:
            (K, 8) [rad, rad/s], their observations.
        """
        if self.state is None or self._single:
            raise EfficientTrackError("hydraulic simulator: reset_machines needs a batched reset (N, 4) first")
        index, q0 = machines_to_reset(index, q0, "hydraulic simulator")
        fresh = initial_state(q0, self.params)
        q, qd = within_limits(fresh.q, fresh.qd, self.params)
        fresh = fresh._replace(q=q, qd=qd)
        merged = []
        for old, new in zip(self.state, fresh, strict=True):
            field = old.copy()
            field[index] = new
            merged.append(field)
        self.state = HydraulicState(*merged)
        return observe(fresh, self.params, self._rng if self.sensor_noise else None)

    def step(self, u: np.ndarray) -> np.ndarray:
        """Apply PWM ``u`` (4,)/(N, 4) for one period; return obs (8,)/(N, 8)."""
        if self.state is None:
            raise EfficientTrackError("hydraulic simulator: step called before reset")
        u = np.asarray(u, dtype=np.float64)
        if u.ndim == 1:
            u = u[None]
        if u.shape != self.state.q.shape:
            raise EfficientTrackError(f"hydraulic simulator: step expects PWM of shape {self.state.q.shape}, got {u.shape}")
        self.state = step(self.state, u, self.params)
        return self._obs()

    def _obs(self) -> np.ndarray:
        assert self.state is not None  # called by reset and step, after they set the state
        obs = observe(self.state, self.params, self._rng if self.sensor_noise else None)
        return obs[0] if self._single else obs


def preset_path() -> Path:
    """Path of the shipped XE75 preset (fitted to the real machine's logs)."""
    return Path(str(resources.files("efficienttrack.systems") / "presets" / "xe75.json"))


def xe75_params(params_file: str | Path | None = None, payload: float | None = None) -> HydraulicParams:
    """The XE75 parameters: the shipped preset (or ``params_file``), with an optional payload 0..1."""
    params = HydraulicParams.load(preset_path() if params_file is None else params_file)
    return params if payload is None else params.replace(payload=float(payload))


def xe75_plant(
    params_file: str | None = None, payload: float | None = None, sensor_noise: bool = False, seed: int = 0
) -> HydraulicExcavator:
    """The built-in XE75 plant (``load_plant("xe75")``).

    Args:
        params_file: JSON preset to use instead of the shipped one (from ``efficienttrack sim calibrate``).
        payload: bucket load fraction 0..1 (default: the preset's, 0).
        sensor_noise: add the preset's sensor noise to the observations.
        seed: seed of the sensor noise.

    Returns:
        A batched :class:`HydraulicExcavator`.
    """
    return HydraulicExcavator(xe75_params(params_file, payload), sensor_noise=sensor_noise, seed=seed)


def xe75_closed_loop(
    params_file: str | None = None, payload: float | None = None, sensor_noise: bool = False, seed: int = 0
) -> ClosedLoop:
    """The built-in XE75 system (``load_system("xe75")``): :func:`xe75_plant` under the real PD law.

    Args:
        params_file: JSON preset to use instead of the shipped one.
        payload: bucket load fraction 0..1.
        sensor_noise: add the preset's sensor noise to the observations.
        seed: seed of the sensor noise.

    Returns:
        A batched :class:`~efficienttrack.systems.pd.ClosedLoop`.
    """
    return ClosedLoop(xe75_plant(params_file, payload, sensor_noise, seed), XE75_PD)
