"""The paper's own excavator simulator (Zou et al., 2025, Table I), re-implemented from its published facts.

The research repository's simulator maps each joint's PWM straight to a joint velocity, with no delay, no
inertia and no coupling between joints, and integrates it with one explicit Euler step per control period:

- **Boom, arm, bucket**: the speed is ``|v(|u|/100) · P(q)|``, with the logistic valve curve
  ``v(x) = b / (1 + exp(a − c·x)) + d`` and a quintic ``P`` of the joint's own angle, one pair per joint and
  direction. A positive PWM moves the joint towards smaller angles (as on the XE75), and a joint at its end
  stop does not move further in the commanded direction. The valve curves are saturated from about 80 PWM on.
- **Swing**: the PWM is rounded to an integer. A positive PWM up to 51 and a negative one down to −66 do not
  move it (the dead zone); from 77 and from −90 on it turns at ±1 rad/s. In between, the speed is linear in
  the angle and in ``|u|/100``.
- **Integration**: ``q += dt·q̇``; boom, arm and bucket are clipped into ``[q_min, q_max]``, the swing wraps at ±π.
  The observation is ``(q, q̇)`` with ``q̇`` the velocity of the step just taken.

Three options make it a harder machine, to check that a method does not fit this one simulator only (all 0 by default,
the paper's simulator exactly): ``delay`` control periods before a command takes effect, a first-order ``lag`` (time
constant, s) of the joint velocities towards the valve's (inertia), and a ``dead_band`` of PWM that boom, arm and
bucket do not respond to (subtracted from |u|). ``--system paper --system-opt delay=1 --system-opt lag=0.1
--system-opt dead_band=10`` is the variant docs/comparison.md measures as a third plant.

Under :data:`PAPER_PD` (the repository's PD law) on the paper's 8 test references, this gives Table I's PD row
(docs/paper-simulator.md). The repository stores the swing's in-between law as a pickled scikit-learn model,
which we do not load; its coefficients were recovered from the repository's recorded simulator logs, which it
reproduces to their printed precision.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, N_JOINTS, SWING
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.pd import PAPER_PD, ClosedLoop
from efficienttrack.systems.protocol import machines_to_reset

Q_MIN = (-0.4, -1.0, -1.0, -math.pi)
"""(4,) rad, the simulator's lower joint limits (the swing is unlimited and wraps)."""
Q_MAX = (0.8, 1.1, 3.0, math.pi)
"""(4,) rad, the simulator's upper joint limits."""
PWM_PER_UNIT = 100.0
"""The valve curves and the swing law take ``|u| / 100``."""

VALVE = np.array(
    [
        [
            [11.858506809692232, 0.512567730315598, 21.86915957497452, -0.0007917425932205652],
            [8.931731925229315, 0.36658149083455016, 15.700213825626527, -0.002794938954199982],
        ],
        [
            [14.023240203780164, 0.8183660786758581, 25.106667075640413, 0.0016937385965325377],
            [13.301471156931091, 0.6985445420696443, 21.749372501996476, 0.002202294140167611],
        ],
        [
            [14.952651261917973, 1.2749258196268678, 28.417406629267962, -0.0010930530561161407],
            [13.581409898795217, 1.0442331432592302, 25.098200285462813, -0.0013277636870057657],
        ],
    ]
)
"""(3, 2, 4): the logistic valve curve ``(a, b, c, d)`` of boom, arm and bucket, for a positive and a negative PWM."""
JOINT_POLY = np.array(
    [
        [
            [0.22455292, 0.1251744, -0.56642958, 0.62115276, -0.43994377, 0.79004756],
            [0.37712406, 0.79595915, -1.23805643, 0.88716494, -0.62352762, 1.07171297],
        ],
        [
            [0.14598575, 0.67122928, 0.04021848, 0.33858849, 0.09810778, 0.91324457],
            [-0.36816399, 0.499325, -0.04911397, 0.43650892, 0.00799341, 1.07954839],
        ],
        [
            [0.1282508, 0.10203362, -0.36151386, 0.50794024, 0.09358899, 0.98092446],
            [-0.08686432, 0.31000578, -0.21916701, 0.40319928, -0.00116702, 0.99735403],
        ],
    ]
)
"""(3, 2, 6): the quintic ``P(q)`` of boom, arm and bucket (highest power first), for a positive and a negative PWM."""

SWING_DEAD_ZONE = (51.0, 66.0)
"""Rounded swing PWM that does not move it: up to 51 in the positive direction, down to −66 in the negative."""
SWING_SATURATION = (77.0, 90.0)
"""Rounded swing PWM from which it turns at :data:`SWING_TOP_SPEED`: 77 positive, −90 negative."""
SWING_TOP_SPEED = 1.0
"""rad/s, the swing's speed at and beyond the saturation."""
SWING_LAW = np.array(
    [
        [-1.8031877212, 3.4912919977, -0.00084364439102],
        [2.2624153429, -3.3852482496, 0.0020402306792],
    ]
)
"""(2, 3): swing velocity between dead zone and saturation, ``w0 + w1·|u|/100 + w2·q`` rad/s, positive and negative PWM."""


def valve_speed(x: np.ndarray, q: np.ndarray, direction: int) -> np.ndarray:
    """Speed of boom, arm and bucket, ``|v(x)·P(q)|``, for one PWM direction.

    Args:
        x: (N, 3) ``|u| / 100`` of boom, arm, bucket.
        q: (N, 3) rad, their angles.
        direction: 0 for a positive PWM, 1 for a negative one.

    Returns:
        (N, 3) rad/s, ≥ 0.
    """
    a, b, c, d = np.moveaxis(VALVE[:, direction], -1, 0)
    poly = np.zeros_like(q)
    for coefficient in np.moveaxis(JOINT_POLY[:, direction], -1, 0):  # Horner, highest power first
        poly = poly * q + coefficient
    return np.abs((b / (1.0 + np.exp(a - c * x)) + d) * poly)


def swing_velocity(u: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The swing's velocity for its PWM: dead zone, the linear law in between, saturation.

    Args:
        u: (N,) PWM of the swing (rounded here to an integer, half to even, as the original).
        q: (N,) rad, the swing angle.

    Returns:
        (N,) rad/s.
    """
    p = np.round(u)
    x = np.abs(p) / PWM_PER_UNIT
    (w_pos, w_neg) = SWING_LAW
    inner_pos = w_pos[0] + w_pos[1] * x + w_pos[2] * q
    inner_neg = w_neg[0] + w_neg[1] * x + w_neg[2] * q
    positive = np.where(p <= SWING_DEAD_ZONE[0], 0.0, np.where(p >= SWING_SATURATION[0], SWING_TOP_SPEED, inner_pos))
    negative = np.where(-p <= SWING_DEAD_ZONE[1], 0.0, np.where(-p >= SWING_SATURATION[1], -SWING_TOP_SPEED, inner_neg))
    return np.where(p > 0, positive, np.where(p < 0, negative, 0.0))


def joint_velocity(q: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The simulator's joint velocity for PWM ``u`` at positions ``q``.

    Args:
        q: (N, 4) rad.
        u: (N, 4) PWM.

    Returns:
        (N, 4) rad/s.
    """
    q_min, q_max = np.asarray(Q_MIN[:SWING]), np.asarray(Q_MAX[:SWING])
    arm_q, arm_u = q[:, :SWING], u[:, :SWING]
    x = np.abs(arm_u) / PWM_PER_UNIT
    lowering = np.where(arm_q <= q_min, 0.0, -valve_speed(x, arm_q, 0))
    raising = np.where(arm_q >= q_max, 0.0, valve_speed(x, arm_q, 1))
    arm = np.where(arm_u > 0, lowering, np.where(arm_u < 0, raising, 0.0))
    return np.concatenate([arm, swing_velocity(u[:, SWING], q[:, SWING])[:, None]], axis=1)


@functools.cache
def top_speed() -> np.ndarray:
    """(4,) rad/s, the fastest each joint moves anywhere in its range at any PWM (on a grid of 501 angles × 101 PWM).

    The bucket's quintic makes it fast near its limits: 45 rad/s at the top of its range, 11.6 rad/s within the
    references' −0.34 … 2.22 rad.
    """
    q = np.linspace(np.maximum(Q_MIN, -math.pi), np.minimum(Q_MAX, math.pi), 501)  # (501, 4)
    u = np.linspace(-1000, 1000, 101)
    grid_q = np.repeat(q, len(u), axis=0)  # every angle with every PWM: (501 · 101, 4)
    grid_u = np.tile(np.repeat(u[:, None], N_JOINTS, axis=1), (len(q), 1))
    return np.abs(joint_velocity(grid_q, grid_u)).max(axis=0)


class PaperExcavator:
    """The paper's simulator as a batched Plant (see the module docstring for the model).

    ====== ============ ===================== ==========================================
    name   shape        unit                  meaning
    ====== ============ ===================== ==========================================
    q0     (4,)/(N, 4)  rad                   ``reset``: positions, at rest
    u      (4,)/(N, 4)  PWM                   ``step``: valve commands (saturated in effect from about ±80)
    obs    (8,)/(N, 8)  [q rad, q̇ rad/s]      q within [:data:`Q_MIN`, :data:`Q_MAX`] (swing in (−π, π])
    ====== ============ ===================== ==========================================

    ``dt`` is 0.05 s. Output rank follows the ``q0`` given to ``reset``. ``reset`` takes ``q0`` as given (the original
    does not clip it); the first step clips it.

    Args:
        delay: control periods before a command takes effect (the commands before the first are 0), ≥ 0.
        lag: s, time constant of a first-order lag of the joint velocities towards the valve's, ≥ 0 (0: none).
        dead_band: PWM subtracted from |u| of boom, arm and bucket before their valve curves, ≥ 0.
    """

    batched = True
    dt = DT

    def __init__(self, delay: int = 0, lag: float = 0.0, dead_band: float = 0.0) -> None:
        if not (isinstance(delay, int) and not isinstance(delay, bool) and delay >= 0):
            raise EfficientTrackError(f"paper simulator: delay must be a whole number of periods ≥ 0, got {delay!r}")
        for name, value in (("lag", lag), ("dead_band", dead_band)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise EfficientTrackError(f"paper simulator: {name} must be a finite number ≥ 0, got {value!r}")
        self.delay, self.lag, self.dead_band = delay, float(lag), float(dead_band)
        self._follow = 1.0 - math.exp(-self.dt / self.lag) if self.lag > 0 else 1.0
        """Share of the way from the joint velocities to the valve's that one period covers."""
        self.q: np.ndarray | None = None
        self.qd: np.ndarray | None = None
        self._pending: np.ndarray | None = None
        self._single = False

    @property
    def limits(self) -> GuardLimits:
        """What the runtime guard may send: the joint limits, the XE75's adjustment bounds, twice :func:`top_speed`.

        Twice the fastest each joint can move is the plausible speed, as the built-in ``xe75`` takes it.
        """
        return GuardLimits(q_min=Q_MIN, q_max=Q_MAX, max_speed=tuple(float(v) for v in 2.0 * top_speed()))

    def reset(self, q0: np.ndarray) -> np.ndarray:
        """Machines at rest at ``q0`` (4,)/(N, 4) rad; return obs (8,)/(N, 8)."""
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape[-1:] != (N_JOINTS,) or q0.ndim not in (1, 2):
            raise EfficientTrackError(f"paper simulator: reset expects q0 of shape (4,) or (N, 4), got {q0.shape}")
        self._single = q0.ndim == 1
        self.q = q0.reshape(-1, N_JOINTS).copy()
        self.qd = np.zeros_like(self.q)
        self._pending = np.zeros((self.delay, *self.q.shape))
        return self._obs()

    def reset_machines(self, index: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Reset some of the N machines at rest at ``q0``; the others keep their state (a vector env's autoreset).

        Args:
            index: (K,) int, which machines (of a batched reset).
            q0: (K, 4) rad, their start positions.

        Returns:
            (K, 8) [rad, rad/s], their observations.
        """
        if self.q is None or self.qd is None or self._single:
            raise EfficientTrackError("paper simulator: reset_machines needs a batched reset (N, 4) first")
        index, q0 = machines_to_reset(index, q0, "paper simulator")
        self.q, self.qd = self.q.copy(), self.qd.copy()
        self.q[index], self.qd[index] = q0, 0.0
        if self._pending is not None:
            self._pending = self._pending.copy()
            self._pending[:, index] = 0.0
        return np.concatenate([self.q[index], self.qd[index]], axis=1)

    def step(self, u: np.ndarray) -> np.ndarray:
        """Apply PWM ``u`` (4,)/(N, 4) for one period; return obs (8,)/(N, 8)."""
        if self.q is None:
            raise EfficientTrackError("paper simulator: step called before reset")
        u = np.asarray(u, dtype=np.float64).reshape(-1, N_JOINTS)
        if u.shape != self.q.shape:
            raise EfficientTrackError(f"paper simulator: step expects PWM of shape {self.q.shape}, got {u.shape}")
        if self.delay:
            assert self._pending is not None  # made by reset
            self._pending = np.concatenate([self._pending, u[None]])
            u, self._pending = self._pending[0], self._pending[1:]
        if self.dead_band:
            u = u.copy()
            u[:, :SWING] = np.sign(u[:, :SWING]) * np.maximum(np.abs(u[:, :SWING]) - self.dead_band, 0.0)
        valve = joint_velocity(self.q, u)
        self.qd = self.qd + self._follow * (valve - self.qd) if self.lag else valve
        q = self.q + self.dt * self.qd
        q[:, :SWING] = np.clip(q[:, :SWING], Q_MIN[:SWING], Q_MAX[:SWING])
        q[:, SWING] = wrap(q[:, SWING])
        self.q = q
        return self._obs()

    def _obs(self) -> np.ndarray:
        obs = np.concatenate([self.q, self.qd], axis=1)
        return obs[0] if self._single else obs


def paper_plant(delay: int = 0, lag: float = 0.0, dead_band: float = 0.0) -> PaperExcavator:
    """The paper's simulator at PWM level (``load_plant("paper")``, ``--plant paper``).

    Args:
        delay: control periods before a command takes effect (0: the paper's).
        lag: s, velocity lag time constant (0: none, the paper's).
        dead_band: PWM of boom, arm and bucket that does not move them (0: the paper's).
    """
    return PaperExcavator(delay, lag, dead_band)


def paper_closed_loop(delay: int = 0, lag: float = 0.0, dead_band: float = 0.0) -> ClosedLoop:
    """The paper's simulator under its PD law (``load_system("paper")``, ``--system paper``).

    Args:
        delay: control periods before a command takes effect (0: the paper's).
        lag: s, velocity lag time constant (0: none, the paper's).
        dead_band: PWM of boom, arm and bucket that does not move them (0: the paper's).
    """
    return ClosedLoop(PaperExcavator(delay, lag, dead_band), PAPER_PD)
