"""A seeded generator of operator-like loading cycles (reference trajectories, see :mod:`efficienttrack.data.references`).

The generator draws operator-like loading cycles in the XE75's joint space. Like the recorded
references, a cycle starts and ends at the dump pose above the truck, so the return swing to
the pile opens the cycle together with the bucket positioning:

1. *position*: swing to the pile, boom down, arm out (bucket held);
2. *load*: bucket curl in two strokes while the arm comes in;
3. *transfer*: boom up and swing back to the truck;
4. *dump*: bucket open, starting just before the swing arrives;
5. *settle*: a last arm correction, then a short hold.

Every joint moves in strokes like a lever pulse: the joint velocity ramps up with a smoothstep,
holds, and ramps down with a smoothstep, so positions are C² and speeds and accelerations stay
bounded. Waypoints, stroke speeds, ramp times and pauses are drawn uniformly from the ranges of
a :class:`CycleConfig`; the ``xe75`` preset's ranges were chosen from statistics of the 40
recorded XE75 references (per-joint range, peak speed, peak acceleration, duration; see
:func:`reference_stats`), no recorded array is embedded.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.configfile import check_seed
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, SWING
from efficienttrack.data.references import Reference

Range = tuple[float, float]


@dataclass(frozen=True)
class CycleConfig:
    """Ranges of the loading-cycle generator; every value is drawn uniformly from its (low, high).

    Angles in rad, speeds in rad/s (the plateau speed of one stroke), times in s.
    """

    truck_boom: Range = (-0.33, -0.05)
    """Boom angle at the truck (start and end of the cycle; boom up is the smaller angle)."""
    truck_arm: Range = (-0.42, 0.36)
    """Arm angle at the truck (start and end of the cycle)."""
    truck_bucket: Range = (-0.20, 0.45)
    """Bucket angle at the start of the cycle (bucket open)."""
    truck_swing: Range = (0.40, 1.62)
    """Swing angle over the truck."""
    swing_out: Range = (0.85, 1.60)
    """Swing travel from the truck to the pile (towards smaller angles)."""
    swing_back_offset: Range = (-0.12, 0.12)
    """Swing angle at the end of the cycle minus the one at its start."""
    pile_boom: Range = (0.32, 0.46)
    """Boom angle at the pile (boom down)."""
    pile_arm: Range = (-0.98, -0.45)
    """Arm angle at the pile (arm out)."""
    load_arm: Range = (-0.50, -0.05)
    """Arm angle after loading (arm in)."""
    bucket_full: Range = (2.10, 2.215)
    """Bucket angle when curled full."""
    curl_split: Range = (0.25, 0.65)
    """Fraction of the curl (and of the arm-in stroke) done by the first stroke."""
    dump_bucket: Range = (-0.34, 0.60)
    """Bucket angle after dumping."""
    swing_out_speed: Range = (0.42, 0.80)
    """Swing speed towards the pile."""
    swing_back_speed: Range = (0.20, 0.45)
    """Swing speed back to the truck."""
    boom_down_speed: Range = (0.22, 0.36)
    """Boom speed when lowering to the pile."""
    boom_up_speed: Range = (0.06, 0.18)
    """Boom speed when raising for the transfer."""
    arm_out_speed: Range = (0.38, 0.80)
    """Arm speed when reaching out at the pile."""
    arm_in_speed: Range = (0.10, 0.40)
    """Arm speed while loading and settling."""
    curl_speed: Range = (0.40, 1.40)
    """Bucket speed while curling."""
    dump_speed: Range = (1.00, 2.20)
    """Bucket speed while dumping."""
    ramp_time: Range = (0.06, 0.30)
    """Quick ramp of a boom, arm or bucket stroke: time for its velocity to go from zero to the plateau or
    back (smoothstep). Each stroke has one quick and one slow ramp, the order drawn at random."""
    slow_ramp_time: Range = (0.30, 1.60)
    """Slow ramp of a boom, arm or bucket stroke."""
    swing_ramp_time: Range = (0.10, 0.45)
    """Quick ramp of a swing stroke (the slewing upper structure is heavier)."""
    swing_slow_ramp_time: Range = (0.50, 2.00)
    """Slow ramp of a swing stroke."""
    start_hold: Range = (0.40, 0.80)
    """Still time before the first stroke."""
    reach_delay: Range = (1.00, 3.00)
    """Delay of the boom-down and arm-out strokes after the swing starts."""
    pause: Range = (0.20, 1.00)
    """Pause between phases."""
    curl_pause: Range = (0.30, 2.00)
    """Pause between the two curl strokes."""
    dump_lead: Range = (0.00, 1.20)
    """How long before the transfer ends the dump starts, and before the dump ends the settling arm stroke starts."""
    end_hold: Range = (0.30, 1.50)
    """Still time after the last stroke."""
    duration: Range = (15.0, 25.0)
    """Accepted cycle durations (T − 1)·dt; cycles outside are drawn again."""

    def __post_init__(self) -> None:
        """Check that every field is a finite (low, high) pair with low ≤ high."""
        for f in fields(self):
            value = getattr(self, f.name)
            numbers = (
                isinstance(value, tuple)
                and len(value) == 2
                and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)
            )
            if not (numbers and np.isfinite(value).all() and value[0] <= value[1]):
                raise EfficientTrackError(f"CycleConfig.{f.name}: expected a finite (low, high) pair, got {value!r}")
        for name in (
            "duration",
            *(f.name for f in fields(self) if f.name.endswith("ramp_time")),
            *(f.name for f in fields(self) if f.name.endswith("_speed")),
        ):
            if getattr(self, name)[0] <= 0:
                raise EfficientTrackError(f"CycleConfig.{name}: must be positive, got {getattr(self, name)!r}")


CYCLE_PRESETS: dict[str, CycleConfig] = {"xe75": CycleConfig()}
"""Named generator settings; ``xe75`` resembles the recorded XE75 loading cycles."""
_CHUNK = 256
"""Cycles synthesized at once by :func:`generate_references` (bounds memory)."""


class _Strokes:
    """Stroke table of m cycles being drawn; each stroke moves one joint in all m cycles."""

    def __init__(self, rng: np.random.Generator, cfg: CycleConfig, m: int) -> None:
        self.rng, self.cfg, self.m = rng, cfg, m
        self.joints: list[int] = []
        self.rows: list[np.ndarray] = []

    def draw(self, name: str) -> np.ndarray:
        """(m,) uniform draws from the config range ``name``."""
        low, high = getattr(self.cfg, name)
        return self.rng.uniform(low, high, self.m)

    def add(self, joint: int, start: np.ndarray, delta: np.ndarray, speed: str) -> np.ndarray:
        """Add one stroke of ``delta`` (m,) rad from time ``start`` (m,) s; return its end time (m,) s."""
        prefix = "swing_" if joint == 3 else ""
        quick, slow = self.draw(f"{prefix}ramp_time"), self.draw(f"{prefix}slow_ramp_time")
        quick_first = self.rng.random(self.m) < 0.5
        up, down = np.where(quick_first, quick, slow), np.where(quick_first, slow, quick)
        duration = np.maximum(np.abs(delta) / self.draw(speed) + (up + down) / 2, up + down)
        self.joints.append(joint)
        self.rows.append(np.stack([start, duration, delta, up, down], axis=1))
        return start + duration


class _Cycles(NamedTuple):
    """m drawn cycles made of K strokes each."""

    q0: np.ndarray
    """(m, 4) rad, start pose."""
    joints: np.ndarray
    """(K,) int, the joint each stroke moves."""
    strokes: np.ndarray
    """(m, K, 5) per stroke: start s, duration s, displacement rad, ramp-up s, ramp-down s."""
    end: np.ndarray
    """(m,) s, time of the last sample."""


def _draw_cycles(rng: np.random.Generator, cfg: CycleConfig, m: int) -> _Cycles:
    """Draw m cycles: waypoints, stroke timing and speeds, phase by phase."""
    s = _Strokes(rng, cfg, m)
    q0 = np.stack([s.draw("truck_boom"), s.draw("truck_arm"), s.draw("truck_bucket"), s.draw("truck_swing")], axis=1)
    boom, arm, bucket, swing = q0.T
    pile_swing, pile_boom, pile_arm = swing - s.draw("swing_out"), s.draw("pile_boom"), s.draw("pile_arm")
    # position: swing to the pile, boom down, arm out
    t = s.draw("start_hold")
    end_swing = s.add(3, t, pile_swing - swing, "swing_out_speed")
    end_boom = s.add(0, t + s.draw("reach_delay"), pile_boom - boom, "boom_down_speed")
    end_arm = s.add(1, t + s.draw("reach_delay"), pile_arm - arm, "arm_out_speed")
    # load: two curl strokes while the arm comes in
    t = np.maximum(end_boom, end_arm) + s.draw("pause")
    full, load_arm, split = s.draw("bucket_full"), s.draw("load_arm"), s.draw("curl_split")
    mid = bucket + split * (full - bucket)
    end_curl = s.add(2, t, mid - bucket, "curl_speed")
    end_arm = s.add(1, t + s.draw("pause"), split * (load_arm - pile_arm), "arm_in_speed")
    end_curl = s.add(2, end_curl + s.draw("curl_pause"), full - mid, "curl_speed")
    t = np.maximum(end_arm, end_curl - s.draw("curl_pause"))
    end_arm = s.add(1, t, (1 - split) * (load_arm - pile_arm), "arm_in_speed")
    # transfer: boom up, swing back to the truck
    t = np.maximum(end_curl, end_arm) + s.draw("pause")
    end_boom = s.add(0, t, s.draw("truck_boom") - pile_boom, "boom_up_speed")
    t = np.maximum(t + s.draw("pause"), end_swing)
    end_swing = s.add(3, t, swing + s.draw("swing_back_offset") - pile_swing, "swing_back_speed")
    # dump: bucket open shortly before the swing arrives
    t = np.maximum(np.maximum(end_boom, end_swing) - s.draw("dump_lead"), end_curl)
    end_dump = s.add(2, t, s.draw("dump_bucket") - full, "dump_speed")
    # settle: last arm correction
    end_arm = s.add(1, np.maximum(end_dump - s.draw("dump_lead"), end_arm), s.draw("truck_arm") - load_arm, "arm_in_speed")
    end = np.maximum.reduce([end_boom, end_swing, end_dump, end_arm]) + s.draw("end_hold")
    return _Cycles(q0, np.array(s.joints), np.stack(s.rows, axis=1), end)


def _synthesize(q0: np.ndarray, joints: np.ndarray, strokes: np.ndarray, steps: int) -> np.ndarray:
    """Positions (m, steps, 4) rad: q0 (m, 4) plus the integral of each stroke's velocity (see _Cycles)."""
    t = np.arange(steps - 1) * DT + DT / 2  # midpoints of the steps
    start, duration, delta, up, down = (x[..., None] for x in np.moveaxis(strokes, 2, 0))
    rise = np.clip((t - start) / up, 0.0, 1.0)
    fall = np.clip((start + duration - t) / down, 0.0, 1.0)
    shape = rise * rise * (3 - 2 * rise) * fall * fall * (3 - 2 * fall)  # (m, K, steps-1) velocity shape
    step = delta * shape / shape.sum(axis=2, keepdims=True)  # exact displacement per stroke
    dq = np.einsum("mkt,kj->mtj", step, np.eye(4)[joints])
    return np.concatenate([q0[:, None, :], q0[:, None, :] + np.cumsum(dq, axis=1)], axis=1)


MAX_REFERENCES = 10_000
"""Most references one call draws (about 160 MB at 25 s each): checked before any work, so that a typo in ``--n``
cannot fill the memory or the disk."""


def generate_references(n: int, seed: int, config: CycleConfig | str = "xe75") -> list[Reference]:
    """Draw ``n`` operator-like loading cycles, reproducible by seed.

    Each cycle (positioning, loading, transfer, dump, settle; see the module docstring) is
    built from smooth strokes between drawn waypoints and lasts ``config.duration`` (15–25 s
    for ``xe75``). The same (n, seed, config) always gives the same references; the first k of
    n references depend on n, so split one generated set rather than generating twice.

    Args:
        n: number of references (≥ 1).
        seed: seed of ``np.random.default_rng``.
        config: generator ranges, or the name of one of ``CYCLE_PRESETS``.

    Returns:
        n references named ``ref_01`` … (zero-padded to the width of n, at least 2 digits),
        each q (T, 4) rad at 20 Hz.

    Raises:
        EfficientTrackError: n outside 1 … :data:`MAX_REFERENCES`, a bad seed, an unknown preset name, or a config
            whose cycles almost never fit its duration range.
    """
    if not 1 <= n <= MAX_REFERENCES:
        raise EfficientTrackError(f"n: need 1 to {MAX_REFERENCES:,} references, got {n}")
    check_seed(seed, "seed")
    if isinstance(config, str) and config not in CYCLE_PRESETS:
        raise EfficientTrackError(f"cycle preset '{config}': unknown (known: {', '.join(CYCLE_PRESETS)})")
    cfg = CYCLE_PRESETS[config] if isinstance(config, str) else config
    rng = np.random.default_rng(seed)
    kept: list[_Cycles] = []
    for _ in range(50):  # rejection rounds: redraw the cycles whose duration falls outside the range
        missing = n - sum(len(c.end) for c in kept)
        if missing == 0:
            break
        cycles = _draw_cycles(rng, cfg, 2 * missing + 8)
        duration = np.round(cycles.end / DT) * DT
        ok = np.flatnonzero((duration >= cfg.duration[0]) & (duration <= cfg.duration[1]))[:missing]
        kept.append(_Cycles(cycles.q0[ok], cycles.joints, cycles.strokes[ok], cycles.end[ok]))
    else:
        raise EfficientTrackError(f"CycleConfig.duration {cfg.duration}: drawn cycles almost never fit this range")
    q0, strokes = (np.concatenate([getattr(c, f) for c in kept]) for f in ("q0", "strokes"))
    steps = np.round(np.concatenate([c.end for c in kept]) / DT).astype(int) + 1
    width = max(2, len(str(n)))
    refs: list[Reference] = []
    for lo in range(0, n, _CHUNK):  # bounded memory: (chunk, K, T) velocity shapes
        q = _synthesize(q0[lo : lo + _CHUNK], kept[0].joints, strokes[lo : lo + _CHUNK], int(steps[lo : lo + _CHUNK].max()))
        refs += [Reference(f"ref_{lo + i + 1:0{width}d}", qi[: steps[lo + i]]) for i, qi in enumerate(q)]
    return refs


HOME_SPEED = 0.3
"""rad/s, the peak speed of the joint that moves farthest on a move between home and a cycle (:func:`homed`)."""


def joint_move(q_from: np.ndarray, q_to: np.ndarray, peak_speed: float, dt: float = DT) -> np.ndarray:
    """A move from rest to rest in joint space, a half-cosine speed profile; the swing goes the short way round.

    ``peak_speed`` is reached on the joint that moves farthest; the others move slower, all arriving together.

    Args:
        q_from: (4,) rad, where the move starts (not in the result).
        q_to: (4,) rad, where it ends (the last row).
        peak_speed: rad/s, > 0.
        dt: s, the step.

    Returns:
        (K, 4) rad, K ≥ 1.
    """
    q_from = np.asarray(q_from, dtype=np.float64)
    delta = np.asarray(q_to, dtype=np.float64) - q_from
    delta[SWING] = wrap(delta[SWING])
    steps = max(int(np.ceil(np.abs(delta).max() * np.pi / 2 / (peak_speed * dt))), 1)
    shape = (1 - np.cos(np.pi * np.arange(1, steps + 1) / steps)) / 2
    path = q_from + shape[:, None] * delta
    path[:, SWING] = wrap(path[:, SWING])
    return path


def homed(refs: list[Reference], home: np.ndarray) -> list[Reference]:
    """The references, each led in from ``home`` and back to it, so that every one starts and ends at that pose.

    A machine that ends one episode at home stands near the next one's start, so the approach between episodes is
    short (the xe75 simulator's position controller still stops its swing up to 0.23 rad short of home, beyond the
    loop's 0.1 rad start tolerance, so there it is still needed). Each move is a :func:`joint_move` at
    :data:`HOME_SPEED`.

    Args:
        refs: the references, q (T, 4) rad.
        home: (4,) rad, the pose.

    Returns:
        The references, named as before, q (M + T + N, 4) rad.
    """
    home = np.asarray(home, dtype=np.float64)
    return [
        Reference(ref.name, np.concatenate([home[None], joint_move(home, ref.q[0], HOME_SPEED)[:-1], ref.q,
                                            joint_move(ref.q[-1], home, HOME_SPEED)]))
        for ref in refs
    ]  # fmt: skip


@dataclass(frozen=True)
class ReferenceStats:
    """Statistics of a set of references (rad, rad/s, rad/s², s; joints boom, arm, bucket, swing).

    Attributes:
        n: number of references.
        duration: median duration (T − 1)·dt, s.
        duration_range: (shortest, longest) duration, s.
        q_min: (4,) rad, smallest angle of the set per joint.
        q_max: (4,) rad, largest angle of the set per joint.
        span: (4,) rad, median over references of max − min per joint.
        peak_speed: (4,) rad/s, median over references of max |Δq|/dt per joint.
        peak_accel: (4,) rad/s², median over references of max |Δ²q|/dt² per joint.
    """

    n: int
    duration: float
    duration_range: tuple[float, float]
    q_min: np.ndarray
    q_max: np.ndarray
    span: np.ndarray
    peak_speed: np.ndarray
    peak_accel: np.ndarray


def reference_stats(refs: list[Reference]) -> ReferenceStats:
    """Compute the statistics the generator is compared on (see :class:`ReferenceStats`).

    Args:
        refs: at least one reference, each q (T, 4) rad with T ≥ 3.

    Returns:
        The set's statistics.
    """
    if not refs or min(len(r) for r in refs) < 3:
        raise EfficientTrackError("reference_stats: needs at least one reference, each with ≥ 3 samples")
    steps = max(len(r) for r in refs)
    q = np.full((len(refs), steps, 4), np.nan)
    for i, ref in enumerate(refs):  # pad to a common length
        q[i, : len(ref)] = ref.q
    durations = np.array([r.duration for r in refs])
    step = wrap(np.diff(q, axis=1))
    speed = np.nanmax(np.abs(step), axis=1) / DT
    accel = np.nanmax(np.abs(np.diff(step, axis=1)), axis=1) / DT**2
    return ReferenceStats(
        n=len(refs),
        duration=float(np.median(durations)),
        duration_range=(float(durations.min()), float(durations.max())),
        q_min=np.nanmin(q, axis=(0, 1)),
        q_max=np.nanmax(q, axis=(0, 1)),
        span=np.median(np.nanmax(q, axis=1) - np.nanmin(q, axis=1), axis=0),
        peak_speed=np.median(speed, axis=0),
        peak_accel=np.median(accel, axis=0),
    )
