"""Guard limits proposed from a machine's own recorded episodes (``efficienttrack limits --from-logs``).

Every rule works on all the logs' samples at once (joint order boom, arm, bucket, swing; rad, rad/s):

- **q_min / q_max**: the lowest and highest position seen in ``q``, ``q_ref`` and ``q_des`` (where the machine was,
  and what it was sent and asked for), widened by ``margin`` (default :data:`DEFAULT_MARGIN`) and kept within ±2π.
  The swing is compared wrapped to (−π, π], as the guard compares it; it stays unlimited (``[-π, π]``) when the logs
  cross ±π (a range on the wrapped angle cannot hold a path through ±π), or when the widened range leaves less than
  ``margin`` of the circle unvisited (it covers nearly the full circle).
- **max_speed**: ``speed_factor`` (default :data:`DEFAULT_SPEED_FACTOR`, as the built-in ``xe75`` takes twice its
  top speed) times the top speed seen, the larger of the sensors' ``|qd|`` and the move between two samples
  ``|Δq| / DT``: the guard takes an observation that moved more than ``max_speed · DT`` for a sensor fault, and the
  logged moves include the sampling jitter.
- **max_adjust**: kept (the XE75 deployment's bound by default): a safety choice the logs cannot show, as the logs'
  ``q_ref − q_des`` is whatever noise or policy ran; lowered to half the proposed range where that is smaller (what
  :meth:`~efficienttrack.systems.limits.GuardLimits.implausible` doubts). The largest ``|q_ref − q_des|`` seen is
  reported.
- **max_adjust_rate**: ``max_adjust / 2`` per control period, the package's rule; the largest step change of
  ``q_ref − q_des`` seen is reported.
- **stale_steps**: twice (the longest run of steps whose observation, all 8 channels of ``q`` and ``qd``, repeats the
  previous one bit for bit, + 1), at least 2: noisy sensors never repeat exactly, so a longer run than the logs ever
  show means a stale sensor.

**Isolated spikes are dropped first**: a sample of one channel (a joint of ``q``, ``q_ref``, ``q_des`` or ``qd``) that
leaves both its neighbours and comes back, sticking out beyond their span by more than :data:`SPIKE_HEIGHT` (0.5 rad,
3 rad/s for ``qd``), is a glitch, not motion; the whole sample is left out of every rule and reported with its episode
and time. On the real XE75's 640 episodes the highest such excursion is 0.08 rad (the noisy references' ``q_ref``),
0.02 rad for ``q`` and 0.37 rad/s for ``qd``: none is dropped.

**Jumps no machine makes refuse the proposal**: a glitch longer than one sample, or a sensor offset, is no spike but
moves a joint faster than its logged motion ever does. Where one move between two samples (of ``q``, ``q_ref`` or
``q_des``) or one ``|qd|`` is more than :data:`JUMP_FACTOR` times the 90th percentile of that channel's logged values
(a percentile a glitch of up to a tenth of the samples does not move) and above :data:`JUMP_FLOOR`, no limits are
proposed: the error names the episode, time, channel and joint, so that the log can be cut or mended. On the real
XE75's 640 episodes the largest such ratio is 6.8 (the arm's ``q_ref``), 8.6 on the episodes of
``policy_round1_train`` alone.

Proposed values are rounded outward to :data:`DECIMALS` decimals (never tighter than the rule, but for float round-off
within :data:`ROUNDING_SLACK`, and none with a zero margin). The proposal returns one line per field saying what was
seen and which margin or factor made the value.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np
import yaml

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write
from efficienttrack.core.joints import DT, JOINT_NAMES, MAX_ABS_ANGLE, MAX_ABS_VELOCITY, N_JOINTS, SWING
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.systems.limits import XE75_MAX_ADJUST, GuardLimits
from efficienttrack.systems.ros2_limits import to_ros2

DEFAULT_MARGIN = 0.05
"""Widening of the observed joint range on each side, rad (about 2.9°)."""
MAX_MARGIN = math.pi
"""Largest margin accepted, rad: a margin beyond π rad (180°) is taken for degrees."""
DEFAULT_SPEED_FACTOR = 2.0
"""``max_speed`` over the top speed seen (the built-in ``xe75`` also takes twice its top speed as plausible)."""
MAX_SPEED_FACTOR = 100.0
"""Largest speed factor accepted."""
STALE_FACTOR = 2
"""``stale_steps`` over (the longest run of repeated observations seen + 1)."""
DECIMALS = 4
"""Decimals of the proposed values (rad, rad/s): 1e-4 rad is 0.006°."""
ROUNDING_SLACK = 1e-10
"""rad (rad/s): how far a proposed value may fall inside its rule through float round-off (none with a zero margin)."""
POSITION_FIELDS = ("q", "q_ref", "q_des")
"""The record fields whose positions the joint range must hold."""
SPIKE_HEIGHT = {"q": 0.5, "q_ref": 0.5, "q_des": 0.5, "qd": 3.0}
"""rad (rad/s for ``qd``): how far one sample may stick out beyond both neighbours' span before it is a glitch."""
SHOWN_SPIKES = 5
"""Dropped spikes named one by one in the report; the rest are counted."""
JUMP_FACTOR = 20.0
"""A move (or ``|qd|``) more than this many times its channel's 90th percentile is a jump no machine makes."""
JUMP_FLOOR = 1.0
"""rad/s: below this speed a move is never taken for a jump (a joint that hardly moved has a tiny percentile)."""


@dataclass(frozen=True)
class LogStats:
    """What the rules read from the logs, per joint (boom, arm, bucket, swing).

    Attributes:
        episodes: number of episodes.
        steps: number of samples (Σ T).
        lowest: (4,) rad, lowest position in ``q``, ``q_ref``, ``q_des`` (the swing wrapped to (−π, π]).
        highest: (4,) rad, highest such position.
        swing_crosses: whether the swing passed ±π between two samples of ``q``, ``q_ref`` or ``q_des``.
        top_qd: (4,) rad/s, largest ``|qd|``.
        top_move: (4,) rad/s, largest ``|q[t] − q[t−1]| / DT`` within an episode (the swing's difference wrapped).
        top_adjust: (4,) rad, largest ``|q_ref − q_des|``.
        top_adjust_step: (4,) rad, largest ``|Δ(q_ref − q_des)|`` from one step to the next within an episode.
        longest_repeat: longest run of steps whose observation (``q``, ``qd``) equals the previous one bit for bit.
        spikes: the isolated spikes left out of every rule, each ``"<episode> at <t> s: <field> <joint> <value>"``.
        jumps: the moves no machine makes (module docstring), each ``"<episode> at <t> s: <field> <joint> moved at
            <speed> rad/s, <ratio>× its 90th percentile"``.
    """

    episodes: int
    steps: int
    lowest: np.ndarray
    highest: np.ndarray
    swing_crosses: bool
    top_qd: np.ndarray
    top_move: np.ndarray
    top_adjust: np.ndarray
    top_adjust_step: np.ndarray
    longest_repeat: int
    spikes: tuple[str, ...] = ()
    jumps: tuple[str, ...] = ()


def jumps(speeds: np.ndarray, names: np.ndarray, times: np.ndarray, field: str) -> list[str]:
    """The speeds of one channel that are jumps no machine makes (module docstring), described.

    Args:
        speeds: (M, 4) rad/s, the channel's moves ``|Δq| / DT`` (or ``|qd|``), spikes and episode seams left out.
        names: (M,) the episode of each.
        times: (M,) s, the time of each (the later sample of a move).
        field: the channel's name, for the description.

    Returns:
        One description per jump, in sample order.
    """
    if not len(speeds):
        return []
    usual = np.quantile(speeds, 0.9, axis=0, method="lower")  # (4,)
    out = (speeds > JUMP_FACTOR * usual) & (speeds > JUMP_FLOOR)
    return [
        f"{names[i]} at {times[i]:.2f} s: {field} {JOINT_NAMES[j]} moved at {speeds[i, j]:.3f} rad/s, "
        f"{speeds[i, j] / usual[j] if usual[j] > 0 else math.inf:.0f}× its 90th percentile {usual[j]:.3f} rad/s"
        for i, j in np.argwhere(out)
    ]


def isolated_spikes(records: Sequence[EpisodeRecord]) -> tuple[np.ndarray, list[str]]:
    """The samples to leave out: one channel jumps away from both neighbours and back (module docstring).

    Args:
        records: the episodes.

    Returns:
        (Σ T,) bool, the samples of all episodes end to end that hold a spike, and one description per spike.
    """
    spiky, found = [], []
    for record in records:
        hit = np.zeros(len(record), dtype=bool)
        for name, height in SPIKE_HEIGHT.items():
            x = getattr(record, name)
            before, after, span = x[1:-1] - x[:-2], x[2:] - x[1:-1], x[2:] - x[:-2]
            if name != "qd":  # angles: the swing's differences wrapped
                for diff in (before, after, span):
                    diff[:, SWING] = wrap(diff[:, SWING])
            span = np.abs(span)
            out = (np.sign(before) * np.sign(after) < 0) & (np.minimum(np.abs(before), np.abs(after)) - span > height)
            for t, j in np.argwhere(out):
                found.append(f"{record.meta.get('name', '?')} at {record.t[t + 1]:.2f} s: {name} "
                             f"{JOINT_NAMES[j]} {x[t + 1, j]:.3f}")  # fmt: skip
            hit[1:-1] |= out.any(axis=1)
        spiky.append(hit)
    return np.concatenate(spiky), found


def log_stats(records: Sequence[EpisodeRecord]) -> LogStats:
    """The statistics the rules read, over all samples of all episodes at once.

    Args:
        records: the episodes (validated records: ``q``, ``qd``, ``q_ref``, ``q_des`` of shape (T, 4), T ≥ 2).

    Returns:
        The :class:`LogStats`.
    """
    if not records:
        raise EfficientTrackError("limits: no episodes to propose limits from")
    lengths = np.array([len(r) for r in records])
    # (3, N, 4) positions of all episodes end to end; differences across two episodes' seam are masked out
    positions = np.stack([np.concatenate([getattr(r, name) for r in records]) for name in POSITION_FIELDS])
    qd = np.concatenate([r.qd for r in records])
    within = np.ones(len(qd) - 1, dtype=bool)  # (N−1,) True where samples t−1 and t belong to one episode
    within[np.cumsum(lengths)[:-1] - 1] = False
    spiky, spikes = isolated_spikes(records)
    kept = ~spiky
    within &= kept[1:] & kept[:-1]  # no move or step change to or from a spike
    positions[..., SWING] = wrap(positions[..., SWING])
    step = np.diff(positions, axis=1)  # (3, N−1, 4)
    crosses = np.abs(step[..., SWING]) > math.pi  # wrapped angles jump by ~2π where the swing passed ±π
    speeds = np.abs(step) / DT  # (3, N−1, 4) rad/s, the moves of q, q_ref, q_des; the swing's the short way round
    speeds[..., SWING] = np.abs(wrap(step[..., SWING])) / DT
    adjust = positions[1] - positions[2]
    adjust[:, SWING] = wrap(adjust[:, SWING])
    adjust_step = np.abs(np.diff(adjust, axis=0))
    adjust_step[:, SWING] = np.abs(wrap(np.diff(adjust[:, SWING])))
    names = np.concatenate([np.full(len(r), str(r.meta.get("name", "?"))) for r in records])
    times = np.concatenate([r.t for r in records])
    jumped = [line for k, name in enumerate(POSITION_FIELDS)
              for line in jumps(speeds[k][within], names[1:][within], times[1:][within], name)]  # fmt: skip
    jumped += jumps(np.abs(qd[kept]), names[kept], times[kept], "qd")
    obs = np.concatenate([np.concatenate([r.q for r in records]), qd], axis=1)
    repeats = np.all(obs[1:] == obs[:-1], axis=1) & within
    edges = np.diff(np.concatenate([[0], repeats.astype(np.int8), [0]]))  # +1 where a run starts, −1 after it ends
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    return LogStats(
        episodes=len(records),
        steps=int(lengths.sum()),
        lowest=positions[:, kept].min(axis=(0, 1)),
        highest=positions[:, kept].max(axis=(0, 1)),
        swing_crosses=bool(np.any(crosses & within)),
        top_qd=np.abs(qd[kept]).max(axis=0),
        top_move=np.max(speeds[0][within], axis=0, initial=0.0),
        top_adjust=np.abs(adjust[kept]).max(axis=0),
        top_adjust_step=np.max(adjust_step[within], axis=0, initial=0.0),
        longest_repeat=int(runs.max(initial=0)),
        spikes=tuple(spikes),
        jumps=tuple(jumped),
    )


def _down(x: np.ndarray, exact: bool = False) -> np.ndarray:
    """(4,) ``x`` rounded down to :data:`DECIMALS` decimals.

    Never above ``x + ROUNDING_SLACK`` (float round-off in ``lowest − margin`` does not cost a decimal), or, with
    ``exact``, never above ``x`` (a zero margin: the bound may not cut off a sample seen).
    """
    scale = 10.0**DECIMALS
    slack = 0.0 if exact else ROUNDING_SLACK * scale
    out = np.floor(x * scale + slack) / scale
    return np.where(out > x + slack / scale, out - 1 / scale, out)


def _up(x: np.ndarray, exact: bool = False) -> np.ndarray:
    """(4,) ``x`` rounded up to :data:`DECIMALS` decimals, never below ``x − ROUNDING_SLACK`` (``exact``: ``x``)."""
    return -_down(-x, exact)


def _vec(values: np.ndarray | Sequence[float]) -> str:
    """``[a, b, c, d]`` with :data:`DECIMALS` decimals."""
    return "[" + ", ".join(f"{v:.{DECIMALS}f}" for v in values) + "]"


def check_proposal_options(margin: float, speed_factor: float, source: str = "") -> None:
    """Refuse a margin or speed factor the rules cannot use, naming the option.

    Args:
        margin: rad, in [0, :data:`MAX_MARGIN`].
        speed_factor: in [1, :data:`MAX_SPEED_FACTOR`].
        source: prefix of the option names in messages (``"--"`` on the command line).
    """
    name = "--margin" if source == "--" else "margin"
    if not (isinstance(margin, int | float) and math.isfinite(margin) and 0 <= margin <= MAX_MARGIN):
        raise EfficientTrackError(f"{name} {margin}: needs a number of radians in [0, π] (radians, not degrees)")
    name = "--speed-factor" if source == "--" else "speed_factor"
    if not (isinstance(speed_factor, int | float) and math.isfinite(speed_factor) and 1 <= speed_factor <= MAX_SPEED_FACTOR):
        raise EfficientTrackError(f"{name} {speed_factor}: needs a number in [1, {MAX_SPEED_FACTOR:g}]")


def propose_limits(
    records: Sequence[EpisodeRecord],
    margin: float = DEFAULT_MARGIN,
    speed_factor: float = DEFAULT_SPEED_FACTOR,
    max_adjust: Sequence[float] = XE75_MAX_ADJUST,
) -> tuple[GuardLimits, list[str]]:
    """Limits for the machine that recorded ``records``, by the rules of this module, and why.

    Args:
        records: the machine's episodes (``q``, ``qd``, ``q_ref``, ``q_des`` of shape (T, 4), rad and rad/s).
        margin: rad, how far the joint range is widened beyond the positions seen, on each side.
        speed_factor: ``max_speed`` over the top speed seen.
        max_adjust: (4,) rad, the adjustment bound to keep (the XE75 deployment's by default).

    Returns:
        The validated limits, and one line per field (and one on the swing) saying what was seen and the margin or
        factor applied, values in rad.

    Raises:
        EfficientTrackError: no episodes, a bad margin or factor, a jump no machine makes (module docstring), or a
            joint that never moved (no range or speed).
    """
    check_proposal_options(margin, speed_factor)
    stats = log_stats(records)
    if stats.jumps:
        shown = "; ".join(stats.jumps[:SHOWN_SPIKES]) + (f"; and {len(stats.jumps) - SHOWN_SPIKES} more"
                                                         if len(stats.jumps) > SHOWN_SPIKES else "")  # fmt: skip
        raise EfficientTrackError(
            f"limits: the logs hold {len(stats.jumps)} jump(s) no machine makes, a glitch longer than one sample or a "
            f"sensor offset: {shown}; cut those episodes or mend the samples, then propose again (a jump would set the "
            "range and speed the guard allows)"
        )
    q_min = np.maximum(_down(stats.lowest - margin, exact=margin == 0), -MAX_ABS_ANGLE)
    q_max = np.minimum(_up(stats.highest + margin, exact=margin == 0), MAX_ABS_ANGLE)
    clipped = [
        JOINT_NAMES[j] for j in range(N_JOINTS) if j != SWING and (q_min[j] == -MAX_ABS_ANGLE or q_max[j] == MAX_ABS_ANGLE)
    ]
    lo, hi = max(float(q_min[SWING]), -math.pi), min(float(q_max[SWING]), math.pi)
    unvisited = 2 * math.pi - (hi - lo)
    seen = f"{stats.lowest[SWING]:.4f} … {stats.highest[SWING]:.4f} rad"
    if stats.swing_crosses:
        swing = (
            f"swing: unlimited [−π, π]: it passed ±π in the logs ({seen} wrapped), which no range of the wrapped angle holds"
        )
        lo, hi = -math.pi, math.pi
    elif unvisited < margin:
        swing = (
            f"swing: unlimited [−π, π]: it covers nearly the full circle ({seen} wrapped; the widened range leaves "
            f"{unvisited:.4f} rad unvisited, less than the margin)"
        )
        lo, hi = -math.pi, math.pi
    else:
        swing = (
            f"swing: limited on its wrapped angle, as the guard compares it: {seen}, never passing ±π; "
            f"{unvisited:.4f} rad of the circle stay forbidden"
        )
    q_min[SWING], q_max[SWING] = lo, hi
    flat = [JOINT_NAMES[j] for j in range(N_JOINTS) if not q_min[j] < q_max[j]]
    if flat:
        raise EfficientTrackError(
            f"limits: the {', '.join(flat)} never moved in the logs and the margin is {margin}: no joint range; "
            "give a margin > 0"
        )
    top = np.maximum(stats.top_qd, stats.top_move)
    still = [JOINT_NAMES[j] for j in range(N_JOINTS) if top[j] == 0]
    if still:
        raise EfficientTrackError(
            f"limits: the {', '.join(still)} never moved in the logs (|qd| and |Δq| are 0 throughout): no max_speed"
        )
    max_speed = np.minimum(_up(speed_factor * top, exact=speed_factor == 1), MAX_ABS_VELOCITY)  # GuardLimits.implausible
    kept = np.asarray(max_adjust, dtype=np.float64)
    bound = np.minimum(kept, (q_max - q_min) / 2)  # no more than half the range (GuardLimits.implausible)
    halved = [JOINT_NAMES[j] for j in range(N_JOINTS) if bound[j] < kept[j]]
    stale = max(2, STALE_FACTOR * (stats.longest_repeat + 1))
    limits = GuardLimits(
        q_min=tuple(float(v) for v in q_min),
        q_max=tuple(float(v) for v in q_max),
        max_adjust=tuple(float(v) for v in bound),
        max_adjust_rate=tuple(float(v) for v in bound / 2),
        max_speed=tuple(float(v) for v in max_speed),
        stale_steps=stale,
    )
    beyond = [JOINT_NAMES[j] for j in range(N_JOINTS) if stats.top_adjust[j] > bound[j]]
    faster = [JOINT_NAMES[j] for j in range(N_JOINTS) if stats.top_adjust_step[j] > limits.max_adjust_rate[j]]
    clip_note = f" (clipped to ±2π at the {', '.join(clipped)})" if clipped else ""
    reasons = [
        f"q_min: {_vec(limits.q_min)} rad = lowest q/q_ref/q_des seen {_vec(stats.lowest)} − margin {margin:g} rad{clip_note}",
        f"q_max: {_vec(limits.q_max)} rad = highest q/q_ref/q_des seen {_vec(stats.highest)} + margin {margin:g} rad"
        f"{clip_note}",
        swing,
        f"max_speed: {_vec(limits.max_speed)} rad/s = factor {speed_factor:g} × top speed seen {_vec(top)} rad/s, the "
        f"larger of |qd| {_vec(stats.top_qd)} and the move |Δq|/{DT:g} s {_vec(stats.top_move)} the guard checks",
        f"max_adjust: {_vec(limits.max_adjust)} rad, kept (the XE75 deployment's bound: a safety choice the logs cannot "
        f"show)"
        + (f", lowered to half the joint's range at the {', '.join(halved)}" if halved else "")
        + f"; largest |q_ref − q_des| seen {_vec(stats.top_adjust)} rad"
        + (f", beyond the bound at the {', '.join(beyond)}" if beyond else ""),
        f"max_adjust_rate: {_vec(limits.max_adjust_rate)} rad per step = max_adjust / 2 (the package's rule); largest "
        f"step change of q_ref − q_des seen {_vec(stats.top_adjust_step)} rad"
        + (f", beyond the rate at the {', '.join(faster)}" if faster else ""),
        f"stale_steps: {stale} = {STALE_FACTOR} × (longest run of bit-identical observations seen, {stats.longest_repeat} "
        "step(s), + 1), at least 2",
    ]
    if stats.spikes:
        shown = "; ".join(stats.spikes[:SHOWN_SPIKES]) + (f"; and {len(stats.spikes) - SHOWN_SPIKES} more"
                                                          if len(stats.spikes) > SHOWN_SPIKES else "")  # fmt: skip
        reasons.insert(0, f"dropped {len(stats.spikes)} isolated spike(s), left out of every rule (a sample that jumps "
                          f"away from both neighbours and back): {shown}")  # fmt: skip
    return limits, reasons


def write_limits(
    limits: GuardLimits, path: str | Path, header: Sequence[str] = (), ros2_names: Sequence[str] | None = None
) -> Path:
    """Write a limits file atomically: YAML with ``header`` as comment lines, or JSON (no comments) for ``.json``.

    Args:
        limits: the limits; every field is written.
        path: the file; ``.json`` gives JSON, anything else YAML.
        header: comment lines for the YAML file (without ``#``).
        ros2_names: write a ros2_control ``joint_limits.yaml`` with these joint names (boom, arm, bucket, swing order;
            :func:`~efficienttrack.systems.ros2_limits.to_ros2`) instead of the guard's own schema.

    Returns:
        The path.
    """
    path = Path(path)
    data = limits.to_dict() if ros2_names is None else to_ros2(limits.to_dict(), ros2_names)
    if path.suffix == ".json":
        text = "{\n" + ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in data.items()) + "\n}\n"
    else:
        body = yaml.safe_dump(data, default_flow_style=None, sort_keys=False, allow_unicode=True, width=1000)
        text = "".join(f"# {line}".rstrip() + "\n" for line in header) + body

    def write(f: IO[str]) -> None:
        f.write(text)

    return atomic_write(path, write, mode="w")
