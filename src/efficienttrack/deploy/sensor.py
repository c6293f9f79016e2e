"""Judging a machine's readings: a reading no machine could give is a sensor fault, and a sensor fault stops the run.

A dropped, late or non-finite sample clears by itself: the loop sends the raw reference for that tick and goes on. A
finite reading that is physically impossible does not clear, and acting on it steers the machine by a wrong
position, so :class:`~efficienttrack.deploy.loop.Loop` ends the run on it (docs/loop.md). A reading is a fault when

- a joint reads beyond its joint limits by more than ``margin`` (the swing only where its limits are not the full
  circle);
- a joint's velocity exceeds the limits' ``max_speed`` (faster than the machine can move);
- a joint moved, since the previous finite reading, by more than its velocities allow: the change lies outside
  ``[min(q̇_prev, q̇) · Δt, max(q̇_prev, q̇) · Δt]`` widened by ``tolerance`` (Δt from the stamps). The interval holds
  any integration of a velocity that moves monotonically within the period, so a velocity-driven simulator, whose
  velocity jumps, passes too. A reading stamped no later than the previous one is not judged on its motion (a
  repeated or a late sample: the loop's staleness watchdogs judge those).

On the real XE75's 640 logged episodes (../shared/data/xe75) no reading is a fault at the defaults: the largest
excess over that interval is 0.069 rad (bucket), the largest reading beyond the limits 0.019 rad, the fastest joint
2.8 rad/s against its 10.8 (tests/test_sensor.py).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.joints import JOINT_NAMES, SWING
from efficienttrack.systems.limits import GuardLimits

SENSOR_MARGIN = 0.1
"""rad, how far beyond its joint limits a joint may read before it is a sensor fault."""
SENSOR_TOLERANCE = 0.15
"""rad, how far a joint's change between two readings may lie outside what its velocities allow."""
KINDS = ("position", "speed", "motion")
"""What a fault breaks: the joint limits, the top speed, or the agreement of position and velocity."""


class SensorFault(NamedTuple):
    """The first impossible value in a run of readings.

    Attributes:
        reading: the reading it is in (0-based, of those judged).
        joint: 0 … 3 (boom, arm, bucket, swing).
        kind: one of :data:`KINDS`.
        value: rad (position, motion: the change since the previous reading) or rad/s (speed).
        limit: the bound it broke, same unit (for motion: the change the velocities allow, nearest end).
    """

    reading: int
    joint: int
    kind: str
    value: float
    limit: float

    def describe(self) -> str:
        """One line naming the joint, the value and the limit."""
        joint = JOINT_NAMES[self.joint]
        if self.kind == "position":
            return f"{joint} reads {self.value:.3f} rad, beyond its joint limit {self.limit:.3f} rad"
        if self.kind == "speed":
            return f"{joint} reads {self.value:.3f} rad/s, faster than its top speed {self.limit:.3f} rad/s"
        return f"{joint} moved {self.value:.3f} rad in one reading, where its velocities allow {self.limit:.3f} rad"


def motion_excess(previous: np.ndarray, obs: np.ndarray, gap: np.ndarray | float) -> np.ndarray:
    """How far each joint's change between two readings lies outside what their velocities allow over ``gap``.

    Args:
        previous: (N, 8) [rad, rad/s], the earlier readings ``(q, q̇)``.
        obs: (N, 8) [rad, rad/s], the later ones.
        gap: (N,) or a number, s between them (> 0).

    Returns:
        (N, 4) rad: the change's distance outside ``[min(q̇_prev, q̇) · gap, max(q̇_prev, q̇) · gap]`` (≤ 0 inside; the
        swing's change wrapped).
    """
    moved = obs[:, :4] - previous[:, :4]
    moved[:, SWING] = wrap(moved[:, SWING])
    gap = np.reshape(gap, (-1, 1))
    low, high = np.minimum(previous[:, 4:], obs[:, 4:]) * gap, np.maximum(previous[:, 4:], obs[:, 4:]) * gap
    return np.maximum(low - moved, moved - high)


def first_sensor_fault(
    obs: np.ndarray,
    stamps: np.ndarray,
    limits: GuardLimits,
    margin: float = SENSOR_MARGIN,
    tolerance: float = SENSOR_TOLERANCE,
) -> SensorFault | None:
    """The first sensor fault in consecutive finite readings (module docstring), or None.

    Args:
        obs: (T, 8) [rad, rad/s], finite readings ``(q, q̇)`` in time order.
        stamps: (T,) s, when each was measured.
        limits: the machine's limits (``q_min``, ``q_max``, ``max_speed``).
        margin: rad beyond the joint limits still taken as a reading.
        tolerance: rad by which a change may exceed what the velocities allow.

    Returns:
        The earliest fault (a reading's position and speed are judged before its motion), or None.
    """
    obs = np.asarray(obs, dtype=np.float64).reshape(-1, 8)
    q, qd = obs[:, :4], obs[:, 4:]
    q_min, q_max = np.asarray(limits.q_min), np.asarray(limits.q_max)
    position = q.copy()
    position[:, SWING] = wrap(position[:, SWING])
    below, above = q_min - margin - position, position - q_max - margin
    if limits.q_min[SWING] <= -math.pi and limits.q_max[SWING] >= math.pi:
        below[:, SWING] = above[:, SWING] = -np.inf
    speed = np.abs(qd) - np.asarray(limits.max_speed)
    gap = np.diff(np.asarray(stamps, dtype=np.float64))
    excess = motion_excess(obs[:-1], obs[1:], np.maximum(gap, 0.0))
    motion = np.full_like(q, -np.inf)
    motion[1:] = np.where(gap[:, None] > 0, excess - tolerance, -np.inf)
    broken = np.stack([np.maximum(below, above), speed, motion], axis=1) > 0  # (T, 3 kinds, 4 joints)
    if not broken.any():
        return None
    index, kind, joint = (int(i) for i in np.argwhere(broken)[0])
    if kind == 0:
        value = float(position[index, joint])
        limit = float(q_min[joint] if below[index, joint] > 0 else q_max[joint])
    elif kind == 1:
        value, limit = float(qd[index, joint]), float(limits.max_speed[joint])
    else:
        moved = q[index, joint] - q[index - 1, joint]
        value = float(wrap(moved) if joint == SWING else moved)
        pair = qd[index - 1 : index + 1, joint] * gap[index - 1]
        limit = float(pair.max() if value > pair.max() else pair.min())
    return SensorFault(index, joint, KINDS[kind], value, limit)
