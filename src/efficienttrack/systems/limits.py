"""What the runtime guard may send to a machine: joint limits, adjustment bounds and plausible motion, per joint.

The limits belong to the machine, never to a policy checkpoint: they come from the system (a ``limits``
attribute; the built-in ``xe75`` derives them from its simulator's parameters), or from a limits file the user
gives (``--limits FILE``, YAML or JSON; fields it leaves out keep the system's values), or a shipped preset named
instead of a file (``--limits xe75``: :data:`LIMITS_PRESETS`). A checkpoint's ``max_adjust`` can only make the
adjustment bound tighter (:meth:`GuardLimits.adjust_bound`). ``efficienttrack limits --from-logs`` proposes a file from
a machine's own logs (:mod:`efficienttrack.systems.limits_from_logs`); the schema is in docs/reference.md, "Limits files".

A system that says nothing gets :data:`DEFAULT_LIMITS`: no joint limits beyond the ±2π sanity bound, the XE75's
adjustment bounds, and a generous plausible speed.

Joint order boom, arm, bucket, swing; rad. The swing wraps at ±π: its limits are compared with the wrapped angle,
so ``[-π, π]`` means unlimited.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.configfile import read_mapping_file
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import JOINT_NAMES, MAX_ABS_ANGLE, MAX_ABS_VELOCITY, N_JOINTS, SWING
from efficienttrack.core.settings import settings_from_dict
from efficienttrack.systems.ros2_limits import from_ros2, is_ros2

XE75_MAX_ADJUST = (0.15, 0.30, 0.40, 0.40)
"""Per-joint adjustment bound of the real XE75 deployment (boom, arm, bucket, swing), rad."""

LIMITS_PRESETS = ("xe75",)
"""Limits files shipped with the package, named instead of a file (``--limits xe75``): ``presets/<name>_limits.json``."""

Vec4 = tuple[float, ...]


def limits_preset_path(name: str) -> Path:
    """Path of the shipped limits file of preset ``name`` (a name in :data:`LIMITS_PRESETS`).

    Args:
        name: the preset, e.g. ``"xe75"``.
    """
    return Path(str(resources.files("efficienttrack.systems") / "presets" / f"{name}_limits.json"))


def resolve_limits_path(spec: str | Path) -> Path:
    """The limits file ``spec`` names: a shipped preset (``xe75``; a preset name wins over a file of that name), else a file.

    Args:
        spec: a preset name of :data:`LIMITS_PRESETS` or the path of a YAML/JSON limits file.

    Returns:
        The file's path.

    Raises:
        EfficientTrackError: ``spec`` is neither a preset nor an existing path.
    """
    if str(spec) in LIMITS_PRESETS:
        return limits_preset_path(str(spec))
    path = Path(spec)
    if not path.exists():
        raise EfficientTrackError(
            f"limits '{spec}': neither a limits preset ({', '.join(LIMITS_PRESETS)}) nor an existing YAML/JSON file"
        )
    return path


ACCEPT_IMPLAUSIBLE = "accept_implausible"
"""A limits file's own switch (not a guard field): ``true`` keeps values :meth:`GuardLimits.implausible` doubts."""


@dataclass(frozen=True)
class GuardLimits:
    """The limits the runtime guard enforces on every reference it sends (per joint: boom, arm, bucket, swing)."""

    q_min: Vec4 = (-MAX_ABS_ANGLE, -MAX_ABS_ANGLE, -MAX_ABS_ANGLE, -math.pi)
    """(4,) rad, lowest position reference the machine may be sent (the swing's is compared wrapped to (−π, π])."""
    q_max: Vec4 = (MAX_ABS_ANGLE, MAX_ABS_ANGLE, MAX_ABS_ANGLE, math.pi)
    """(4,) rad, highest position reference the machine may be sent (the swing's is compared wrapped to (−π, π])."""
    max_adjust: Vec4 = XE75_MAX_ADJUST
    """(4,) rad, bound of the policy's adjustment |a|; a larger output falls back to the raw reference."""
    max_adjust_rate: Vec4 = tuple(b / 2 for b in XE75_MAX_ADJUST)
    """(4,) rad per control period, largest change of the adjustment from one step to the next (limited, not refused)."""
    max_speed: Vec4 = (2 * math.pi,) * N_JOINTS
    """(4,) rad/s, faster than the machine can move: an observation that moved more than ``max_speed · dt`` since the
    last one is a sensor fault (or dropped samples), and that step falls back to the raw reference."""
    stale_steps: int | None = None
    """Steps in a row whose observation repeats the previous one bit for bit, from which the sensor counts as stale and
    the step falls back (≥ 2: the first step may repeat the start observation); None: not checked (a noise-free
    simulator at rest repeats itself exactly; set it for a real machine's noisy sensors)."""

    def __post_init__(self) -> None:
        """Validate every field: 4 finite numbers each, ``q_min < q_max`` within ±2π, positive bounds."""
        for name in ("q_min", "q_max", "max_adjust", "max_adjust_rate", "max_speed"):
            value = getattr(self, name)
            if (
                not isinstance(value, tuple)
                or len(value) != N_JOINTS
                or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)
            ):
                raise EfficientTrackError(
                    f"limits field '{name}': needs 4 finite numbers (boom, arm, bucket, swing), got {value!r}"
                )
            if name != "q_min" and name != "q_max" and not all(v > 0 for v in value):
                raise EfficientTrackError(f"limits field '{name}': needs 4 positive numbers, got {value!r}")
        for j, joint in enumerate(JOINT_NAMES):
            lo, hi = self.q_min[j], self.q_max[j]
            if not -MAX_ABS_ANGLE <= lo < hi <= MAX_ABS_ANGLE:
                raise EfficientTrackError(
                    f"limits fields 'q_min'/'q_max': {joint} needs −2π ≤ q_min < q_max ≤ 2π rad, got [{lo}, {hi}]"
                )
        if self.stale_steps is not None and (
            not isinstance(self.stale_steps, int) or isinstance(self.stale_steps, bool) or self.stale_steps < 2
        ):
            raise EfficientTrackError(f"limits field 'stale_steps': needs an integer ≥ 2 or null, got {self.stale_steps!r}")

    @classmethod
    def load(cls, path: str | Path, base: GuardLimits | None = None) -> GuardLimits:
        """Read a limits file (a YAML or JSON mapping of this class's fields); fields it leaves out keep ``base``'s.

        A ros2_control ``joint_limits.yaml`` is read too (:mod:`~efficienttrack.systems.ros2_limits`).

        Args:
            path: the file, or a shipped preset's name (``xe75``, :data:`LIMITS_PRESETS`).
            base: the limits the file amends (the system's own); :data:`DEFAULT_LIMITS` when None.

        Returns:
            The validated limits.
        """
        path = resolve_limits_path(path)
        data = read_mapping_file(path)
        if not isinstance(data, dict):
            raise EfficientTrackError(f"{path}: expected a mapping of limits fields, got {type(data).__name__}")
        if is_ros2(data):  # a ros2_control joint_limits.yaml
            data = from_ros2(data, str(path))
        accepted = data.pop(ACCEPT_IMPLAUSIBLE, False)
        if not isinstance(accepted, bool):
            raise EfficientTrackError(f"{path}: {ACCEPT_IMPLAUSIBLE} must be true or false, got {accepted!r}")
        merged = {**(base or DEFAULT_LIMITS).to_dict(), **data}
        try:
            limits = settings_from_dict(cls, merged, str(path))
        except EfficientTrackError as exc:
            message = str(exc)
            raise EfficientTrackError(message if message.startswith(str(path)) else f"{path}: {message}") from exc
        doubts = limits.implausible()
        if doubts and not accepted:
            raise EfficientTrackError(
                f"{path}: {'; '.join(doubts)}: a typo or not radians? If the machine really allows it, add "
                f"'{ACCEPT_IMPLAUSIBLE}: true' to the file"
            )
        return limits

    def implausible(self) -> list[str]:
        """What in these limits is no excavator's: an adjustment over half a joint's range, or a speed no record may hold.

        The speed bound is :data:`~efficienttrack.core.joints.MAX_ABS_VELOCITY`, beyond which records are refused.

        Returns:
            One line per doubt, empty when none.
        """
        joints = zip(JOINT_NAMES, self.max_adjust, self.q_min, self.q_max, self.max_speed, strict=True)
        doubts = []
        for joint, bound, lo, hi, speed in joints:
            if bound > (hi - lo) / 2:
                doubts.append(f"max_adjust of the {joint}, {bound} rad, is more than half its range [{lo}, {hi}]")
            if speed > MAX_ABS_VELOCITY:
                doubts.append(f"max_speed of the {joint}, {speed} rad/s, is beyond any excavator's {MAX_ABS_VELOCITY:g} rad/s")
        return doubts

    @classmethod
    def coerce(cls, value: Any, source: str) -> GuardLimits:
        """A system's ``limits`` attribute as :class:`GuardLimits`: already one, or a mapping of its fields.

        Args:
            value: the attribute.
            source: how to name it in errors.

        Returns:
            The validated limits.
        """
        if isinstance(value, GuardLimits):
            return value
        if isinstance(value, dict):
            return settings_from_dict(cls, {**DEFAULT_LIMITS.to_dict(), **value}, source)
        raise EfficientTrackError(f"{source}: expected GuardLimits or a mapping of its fields, got {type(value).__name__}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable fields (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def replace(self, **changes: Any) -> GuardLimits:
        """A copy with some fields changed (validated again).

        Args:
            **changes: field name → new value.
        """
        return replace(self, **changes)

    def adjust_bound(self, policy_max_adjust: Any = None) -> np.ndarray:
        """(4,) rad, the adjustment bound the guard enforces: the machine's, tightened (never widened) by a policy's.

        Args:
            policy_max_adjust: (4,) rad, the bound stored in a policy checkpoint, or None.
        """
        bound = np.asarray(self.max_adjust, dtype=np.float64)
        if policy_max_adjust is None:
            return bound
        return np.minimum(bound, np.asarray(policy_max_adjust, dtype=np.float64))

    def rate_limit(self, a: np.ndarray, a_last: np.ndarray) -> np.ndarray:
        """An adjustment whose change from the last one sent is at most ``max_adjust_rate`` per joint.

        The runtime guard and the fixed-rate loop both limit the adjustment this way (each from what it sent last).

        Args:
            a: (..., 4) rad, the adjustment wanted.
            a_last: (..., 4) rad, the adjustment sent the step before.

        Returns:
            (..., 4) rad.
        """
        rate = np.asarray(self.max_adjust_rate, dtype=np.float64)
        return np.clip(a, a_last - rate, a_last + rate)

    def clamp(self, q: np.ndarray) -> np.ndarray:
        """Positions clamped into the joint limits; the swing only where its wrapped angle is outside them.

        Args:
            q: (..., 4) rad.

        Returns:
            (..., 4) rad, equal to ``q`` wherever it was inside the limits.
        """
        q = np.asarray(q, dtype=np.float64)
        out = np.clip(q, self.q_min, self.q_max)
        swing = wrap(q[..., SWING])
        out[..., SWING] = np.where(
            (swing < self.q_min[SWING]) | (swing > self.q_max[SWING]),
            np.clip(swing, self.q_min[SWING], self.q_max[SWING]),
            q[..., SWING],
        )
        return out

    def outside(self, q: np.ndarray) -> np.ndarray:
        """Where positions are outside the joint limits (or not finite).

        Args:
            q: (..., 4) rad.

        Returns:
            (..., 4) bool.
        """
        q = np.asarray(q, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return ~np.isfinite(q) | (self.clamp(q) != q)

    def check_reference(self, q: np.ndarray, name: str) -> None:
        """Refuse a reference that leaves the joint limits anywhere, naming it, the joint, the step and the value.

        Args:
            q: (L, 4) rad, the desired positions.
            name: the reference's name, for the message.
        """
        q = np.asarray(q, dtype=np.float64)
        bad = self.outside(q)
        if bad.any():
            step, joint = (int(i) for i in np.argwhere(bad)[0])
            raise EfficientTrackError(
                f"reference '{name}': {JOINT_NAMES[joint]} is {q[step, joint]:.4g} rad at step {step}, outside the joint "
                f"limits [{self.q_min[joint]:.4g}, {self.q_max[joint]:.4g}] rad ({int(bad.any(axis=1).sum())} step(s) "
                "outside); nothing was sent"
            )


DEFAULT_LIMITS = GuardLimits()
"""Limits of a system that gives none: ±2π (swing unlimited), the XE75's adjustment bounds, 2π rad/s."""
