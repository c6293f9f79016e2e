"""Guard limits as ros2_control's (and MoveIt's) ``joint_limits.yaml``: read where a limits file is read, and written.

A ``joint_limits.yaml`` holds a ``joint_limits`` mapping of joint name → ``has_position_limits``, ``min_position``,
``max_position``, ``has_velocity_limits``, ``max_velocity`` (and acceleration, jerk, effort limits, which the guard
does not use). Its joints are matched to ours by name: a key that is ``boom``, ``arm``, ``bucket`` or ``swing``, or
holds exactly one of these words between underscores, dots, dashes or slashes (``boom_joint``, ``xe75/swing``); a
joint that names none of them (a blade, a track) is left alone. The guard's own fields that the format lacks
(``max_adjust``, ``max_adjust_rate``, ``stale_steps``, ``accept_implausible``) may sit beside ``joint_limits`` at the
top level; MoveIt's scaling factors there are left alone too.

Mapping (rad, rad/s): ``min_position``/``max_position`` → ``q_min``/``q_max`` (no position limits: ±2π, for the swing
±π, its unlimited range; ``angle_wraparound: true`` marks a swing without limits); ``max_velocity`` → ``max_speed``
(no velocity limits: the guard's default).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import JOINT_NAMES, MAX_ABS_ANGLE, SWING

KEY = "joint_limits"
"""The top-level key that makes a limits file a ros2_control ``joint_limits.yaml``."""
GUARD_FIELDS = ("max_adjust", "max_adjust_rate", "stale_steps", "accept_implausible")
"""Top-level keys of the guard's own, which the format lacks, allowed beside :data:`KEY`."""
IGNORED_TOP = ("default_velocity_scaling_factor", "default_acceleration_scaling_factor")
"""MoveIt's top-level keys, not the guard's business."""
JOINT_KEYS = (
    "has_position_limits", "min_position", "max_position", "has_velocity_limits", "max_velocity",
    "has_acceleration_limits", "max_acceleration", "has_deceleration_limits", "max_deceleration", "has_jerk_limits",
    "max_jerk", "has_effort_limits", "max_effort", "angle_wraparound", "has_soft_limits", "k_position", "k_velocity",
    "soft_lower_limit", "soft_upper_limit",
)  # fmt: skip
"""The per-joint keys ros2_control's ``joint_limits`` package and MoveIt read; any other is refused as a typo."""


def is_ros2(data: Any) -> bool:
    """Whether a limits file's mapping is a ros2_control ``joint_limits.yaml`` (it has a top-level ``joint_limits``).

    Args:
        data: the file's contents, as read.
    """
    return isinstance(data, dict) and KEY in data


def _ours(name: str) -> int | None:
    """The index of our joint that a ros2 joint name names, None when it names none; ambiguous names are refused."""
    words = set(re.split(r"[_./\-]", str(name).lower()))
    found = [j for j, joint in enumerate(JOINT_NAMES) if joint in words]
    if len(found) > 1:
        raise EfficientTrackError(f"joint '{name}' names {' and '.join(JOINT_NAMES[j] for j in found)}: name one joint")
    return found[0] if found else None


def _number(joint: dict, key: str, where: str) -> float:
    value = joint.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise EfficientTrackError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _flag(joint: dict, key: str, where: str) -> bool:
    value = joint.get(key, False)
    if not isinstance(value, bool):
        raise EfficientTrackError(f"{where}: {key} must be true or false, got {value!r}")
    return value


def from_ros2(data: dict[str, Any], source: str) -> dict[str, Any]:
    """The guard's fields a ``joint_limits.yaml`` gives (the module docstring's mapping), with its guard-only fields.

    Args:
        data: the file's mapping (:func:`is_ros2`).
        source: the file, named in errors.

    Returns:
        ``{"q_min", "q_max", "max_speed": 4-lists}`` plus the top-level guard fields the file gives (unchecked: the
        caller validates them as any limits file's).

    Raises:
        EfficientTrackError: a joint of ours missing or given twice, an unknown key, or a value of the wrong type.
    """
    unknown = sorted(str(k) for k in data if k not in (KEY, *GUARD_FIELDS, *IGNORED_TOP))
    if unknown:
        raise EfficientTrackError(
            f"{source}: unknown top-level key(s) {', '.join(unknown)} beside {KEY}; allowed: {', '.join(GUARD_FIELDS)}"
        )
    joints = data[KEY]
    if not isinstance(joints, dict):
        raise EfficientTrackError(f"{source}: {KEY} must map joint names to their limits, got {type(joints).__name__}")
    found: dict[int, tuple[str, dict]] = {}
    for name, joint in joints.items():
        where = f"{source}: {KEY}.{name}"
        try:
            j = _ours(name)
        except EfficientTrackError as exc:
            raise EfficientTrackError(f"{source}: {exc}") from None
        if j is None:
            continue
        if j in found:
            raise EfficientTrackError(f"{source}: joints '{found[j][0]}' and '{name}' both name the {JOINT_NAMES[j]}")
        if not isinstance(joint, dict):
            raise EfficientTrackError(f"{where}: expected a mapping of limits, got {type(joint).__name__}")
        bad = sorted(str(k) for k in joint if k not in JOINT_KEYS)
        if bad:
            raise EfficientTrackError(
                f"{where}: unknown key(s) {', '.join(bad)}; ros2_control reads {', '.join(JOINT_KEYS[:5])}…"
            )
        found[j] = (str(name), joint)
    missing = [JOINT_NAMES[j] for j in range(len(JOINT_NAMES)) if j not in found]
    if missing:
        raise EfficientTrackError(
            f"{source}: no joint of {KEY} names the {', '.join(missing)} (joints: {', '.join(map(str, joints))}); name each "
            "boom, arm, bucket, swing, or with one of these words (boom_joint)"
        )
    q_min, q_max, speed = [], [], []
    for j in range(len(JOINT_NAMES)):
        name, joint = found[j]
        where = f"{source}: {KEY}.{name}"
        unlimited = math.pi if j == SWING else MAX_ABS_ANGLE
        if _flag(joint, "has_position_limits", where) and not _flag(joint, "angle_wraparound", where):
            q_min.append(_number(joint, "min_position", where))
            q_max.append(_number(joint, "max_position", where))
        else:
            q_min.append(-unlimited)
            q_max.append(unlimited)
        speed.append(_number(joint, "max_velocity", where) if _flag(joint, "has_velocity_limits", where) else None)
    fields: dict[str, Any] = {"q_min": q_min, "q_max": q_max}
    if all(v is not None for v in speed):
        fields["max_speed"] = speed
    elif any(v is not None for v in speed):
        without = ", ".join(JOINT_NAMES[j] for j, v in enumerate(speed) if v is None)
        raise EfficientTrackError(
            f"{source}: velocity limits on some of our joints only ({without} without): the guard checks every joint's "
            "speed; give has_velocity_limits and max_velocity to all four"
        )
    return fields | {k: data[k] for k in GUARD_FIELDS if k in data}


def to_ros2(fields: dict[str, Any], names: Sequence[str] = JOINT_NAMES) -> dict[str, Any]:
    """A ``joint_limits.yaml`` mapping of the guard's limits: position and velocity per joint, the guard's own fields beside.

    Args:
        fields: the limits' fields (:meth:`~efficienttrack.systems.limits.GuardLimits.to_dict`).
        names: the machine's joint names in our order (boom, arm, bucket, swing); each must name its joint
            (module docstring), so that the file reads back.

    Returns:
        The mapping, for YAML.
    """
    if len(names) != len(JOINT_NAMES) or any(_ours(name) != j for j, name in enumerate(names)):
        raise EfficientTrackError(
            f"joint names {', '.join(map(str, names))}: give four, naming boom, arm, bucket and swing in this order "
            "(e.g. boom_joint,arm_joint,bucket_joint,swing_joint)"
        )
    joints = {}
    for j, name in enumerate(names):
        lo, hi = fields["q_min"][j], fields["q_max"][j]
        wraps = j == SWING and lo <= -math.pi and hi >= math.pi
        joint: dict[str, Any] = {"has_position_limits": not wraps}
        if wraps:
            joint["angle_wraparound"] = True
        else:
            joint |= {"min_position": lo, "max_position": hi}
        joint |= {"has_velocity_limits": True, "max_velocity": fields["max_speed"][j], "has_acceleration_limits": False}
        joints[name] = joint
    return {KEY: joints} | {k: fields[k] for k in GUARD_FIELDS if k in fields}
