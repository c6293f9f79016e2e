"""A fixed-rate loop for real machines: a runtime at 20 Hz on absolute deadlines, against a machine adapter, with watchdogs.

:class:`Loop` runs a runtime (:class:`~efficienttrack.deploy.runtime.Runtime`, or anything with its ``start`` / ``step`` /
``stop``) against a :class:`Machine` adapter along one reference::

    with TickLog("ref_00.jsonl") as log:
        result = Loop(Runtime(policy, limits=limits), MyMachine(...), limits, log=log, shadow=True).run(ref.q, ref.name)

Tick k has the deadline ``start + k·dt`` (never ``previous + dt``: the loop does not drift), reads the machine,
asks the runtime for the reference of step k+1 and sends it. What it sends is decided in this order:

1. **stop** (the raw reference ``q*_{k+1}`` is sent once more, then the run ends): the tick is the
   ``stop_after``-th overrun in a row; the last good reading is older than ``stop_stale_ticks``; the machine's
   ``read`` raised or gave a malformed reading; the runtime raised; Ctrl-C, SIGTERM or SIGHUP
   (:mod:`~efficienttrack.core.stop_signals`). A **sensor fault** (a finite reading no machine could give:
   :mod:`~efficienttrack.deploy.sensor`) stops the run too, but holds: the reference sent last tick is sent again,
   for the machine's controller would steer the raw one by the faulty reading. A ``send`` that raises or reports a
   malformed reference ends the run at once (nothing more can be sent);
2. **a = 0** (the raw reference) for this tick: the first tick (every run starts with a = 0); shadow mode; the
   ``hold_after``-th overrun in a row or later; a reading older than ``stale_ticks`` (or missing: a dropped
   sample or a non-finite one; the runtime gets a NaN observation and falls back on its own too);
3. otherwise the runtime's adjustment, its change per tick limited to the machine's ``max_adjust_rate`` from what
   was really sent last tick, and ramped down to 0 over the last ticks (every run ends with a = 0).

A tick **overruns** when the previous tick's work ended after this tick's deadline; when whole periods were
missed, the loop skips to the current period (the reference follows the clock) and counts the skipped ticks.

Every tick writes one line to a :class:`TickLog` (JSONL, flushed per line, fsynced every ``fsync_every`` lines and at
the end), and the run ends with a summary line (``"event": "end"``); a log without one was cut by a crash. The
fields are listed in ``docs/loop.md``.

The clock is injectable (:class:`Clock`): :data:`MONOTONIC` (``time.monotonic``) for a machine, or
:class:`~efficienttrack.deploy.machine.SimulatedClock` to run a simulator as fast as it computes (a test's fake clock too).
The machine side (the :class:`Machine` protocol, its simulated twins) is :mod:`efficienttrack.deploy.machine`.
:mod:`efficienttrack.deploy.deployment` runs the loop over a folder of references against a simulator or a user's adapter.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, SWING
from efficienttrack.core.stop_signals import interrupt_name, stop_signals_as_interrupt
from efficienttrack.deploy.episodes import Driver, Guard, Sent
from efficienttrack.deploy.machine import MONOTONIC, Clock, Machine, Reading
from efficienttrack.deploy.sensor import SENSOR_MARGIN, SENSOR_TOLERANCE, first_sensor_fault
from efficienttrack.systems.limits import GuardLimits

STOP_REASONS = ("overruns", "stale_sensor", "sensor_fault", "read_error", "send_error", "runtime_error", "interrupted")
"""Why a run can end before its reference does (``done``: it ran to the end)."""


class LoopRuntime(Driver, Protocol):
    """What the loop runs: the episodes' :class:`~efficienttrack.deploy.episodes.Driver`, for one machine (N = 1).

    It adds how many desired positions ``step`` needs and a ``stop`` at the end: the interface of
    :class:`~efficienttrack.deploy.runtime.Runtime`.

    A runtime that also has ``sent_instead(q_ref)`` ((1, 4) rad) is told when the loop sent another reference
    than the one ``step`` returned (shadow mode, a hold, the rate limit, a machine that clamps), so that the
    reference history its policy sees next holds what was really sent.
    """

    future_length: int
    """F, the desired positions ``step`` needs."""

    def stop(self) -> None:
        """End."""
        ...


@dataclass(frozen=True)
class LoopConfig:
    """Timing, watchdogs and logging of :class:`Loop`."""

    dt: float = DT
    """Control period, s (20 Hz)."""
    hold_after: int = 3
    """Overruns in a row from which the raw reference is sent (a = 0) until a tick is on time again."""
    stop_after: int = 10
    """Overruns in a row at which the run stops."""
    stale_ticks: float = 2.0
    """A reading older than this many periods (or none) sends the raw reference for that tick."""
    stop_stale_ticks: float = 10.0
    """The last good reading older than this many periods stops the run."""
    start_tolerance: float = 0.1
    """rad, largest distance per joint between the machine and the reference's first position at the start."""
    sensor_margin: float = SENSOR_MARGIN
    """rad, how far beyond the joint limits a joint may read before the reading is a sensor fault (stop)."""
    sensor_tolerance: float = SENSOR_TOLERANCE
    """rad, how far a joint's change between readings may exceed what its velocities allow before it is a sensor fault."""
    fsync_every: int = 20
    """Log lines between two fsyncs (each line is flushed)."""

    def __post_init__(self) -> None:
        """Refuse settings that cannot work: a non-positive period, stop before hold, stop-stale below stale."""
        if not (isinstance(self.dt, int | float) and math.isfinite(self.dt) and self.dt > 0):
            raise EfficientTrackError(f"loop: dt must be a positive number of seconds, got {self.dt!r}")
        for name in ("hold_after", "stop_after", "fsync_every"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise EfficientTrackError(f"loop: {name} must be an integer ≥ 1, got {value!r}")
        if self.stop_after < self.hold_after:
            raise EfficientTrackError(f"loop: stop_after ({self.stop_after}) must be ≥ hold_after ({self.hold_after})")
        if not (math.isfinite(self.stale_ticks) and 0 < self.stale_ticks <= self.stop_stale_ticks < math.inf):
            raise EfficientTrackError(
                f"loop: needs 0 < stale_ticks ≤ stop_stale_ticks, finite, got {self.stale_ticks!r}, {self.stop_stale_ticks!r}"
            )
        for name in ("start_tolerance", "sensor_margin", "sensor_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise EfficientTrackError(f"loop: {name} must be a positive number of rad, got {value!r}")


class TickLog:
    """A crash-safe JSONL log: one line per tick, flushed at once, fsynced every ``fsync_every`` lines and at close.

    Opened by ``with`` (no file I/O before); an existing file is refused, not overwritten, and one closed without a line
    (a run that never started) is removed. Non-finite numbers are written as ``null`` (JSON has no NaN).

    Args:
        path: the ``.jsonl`` file to create.
        fsync_every: lines between two fsyncs.
    """

    def __init__(self, path: str | Path, fsync_every: int = LoopConfig.fsync_every) -> None:
        self.path = Path(path)
        self.fsync_every = fsync_every
        self._file: IO[str] | None = None
        self._unsynced = 0
        self.lines = 0
        """Lines written so far."""

    def __enter__(self) -> TickLog:
        """Create the file (refused when it exists)."""
        try:
            self._file = open(self.path, "x", encoding="utf-8")  # noqa: SIM115 (closed in __exit__)
        except FileExistsError:
            raise EfficientTrackError(f"{self.path}: the log exists already; nothing was sent (use another log)") from None
        except OSError as exc:
            raise EfficientTrackError(f"{self.path}: cannot create the log ({exc.strerror}); nothing was sent") from exc
        return self

    def __exit__(self, *exc: object) -> None:
        """Flush, fsync and close; remove the file when it holds no line."""
        if self._file is not None:
            self._sync()
            self._file.close()
            self._file = None
            if not self.lines:
                self.path.unlink(missing_ok=True)

    def write(self, entry: dict[str, Any]) -> None:
        """Append one line.

        Args:
            entry: JSON-serializable data (numpy arrays and numbers allowed).
        """
        if self._file is None:
            raise EfficientTrackError(f"{self.path}: the log is not open")
        self._file.write(json.dumps(_jsonable(entry), allow_nan=False) + "\n")
        self._file.flush()
        self.lines += 1
        self._unsynced += 1
        if self._unsynced >= self.fsync_every:
            self._sync()

    def _sync(self) -> None:
        assert self._file is not None  # called while the log is open
        self._file.flush()
        os.fsync(self._file.fileno())
        self._unsynced = 0


def set_aside(log: Path) -> Path | None:
    """Move an earlier try's tick log out of the way of a new run: to the first free ``<name>.stopped-<n>.jsonl``.

    A run that a watchdog stopped is run again from its start; its log is kept, under a name that says so.

    Args:
        log: ``<folder>/<name>.jsonl``, the log the new run will write.

    Returns:
        Where the earlier log now is, or None when there was none.
    """
    if not log.exists():
        return None
    n = 1
    while (aside := log.with_name(f"{log.stem}.stopped-{n}.jsonl")).exists():
        n += 1
    os.replace(log, aside)
    return aside


def _jsonable(value: Any) -> Any:
    """``value`` with arrays as lists and NaN/±inf as None."""
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return value


@dataclass
class LoopResult:
    """What one run did.

    Attributes:
        name: the reference's name.
        reason: ``done``, or why it stopped early (one of :data:`STOP_REASONS`).
        ticks: ticks run (each sent one reference).
        error: the error that stopped it, as text, or None.
        counts: event → ticks it happened at (``overrun``, ``missed``, ``hold``, ``stale``, ``dropped``, ``fallback``, …).
        lateness: (ticks,) s, how late each tick started after its deadline.
        compute: (ticks,) s, the runtime's ``step`` time per tick.
    """

    name: str
    reason: str = "done"
    ticks: int = 0
    error: str | None = None
    counts: dict[str, int] = field(default_factory=dict)
    lateness: list[float] = field(default_factory=list)
    compute: list[float] = field(default_factory=list)

    @property
    def stopped(self) -> bool:
        """True when the run ended before its reference did."""
        return self.reason != "done"

    def summary(self) -> dict[str, Any]:
        """JSON form: reason, ticks, counts, lateness p50/p99/max and compute p50/p99/max (ms)."""
        late, comp = np.asarray(self.lateness) * 1e3, np.asarray(self.compute) * 1e3
        stats = {}
        for key, values in (("lateness_ms", late), ("compute_ms", comp)):
            if len(values):
                p50, p99 = np.percentile(values, [50, 99])
                stats[key] = {"p50": float(p50), "p99": float(p99), "max": float(values.max())}
        return {"name": self.name, "reason": self.reason, "ticks": self.ticks, "error": self.error, **self.counts, **stats}


class NotAtStart(EfficientTrackError):
    """The loop refused to start: the machine stands too far from the reference's first position (nothing was sent).

    Args:
        message: what the loop says.
        position: (4,) rad, where the machine stood (kept as :attr:`position`).
    """

    def __init__(self, message: str, position: np.ndarray) -> None:
        super().__init__(message)
        self.position = position


class _Stop(Exception):
    """A watchdog or a fault ends the run (``reason``, one of :data:`STOP_REASONS`)."""

    def __init__(self, reason: str, error: str | None = None) -> None:
        super().__init__(reason)
        self.reason, self.error = reason, error


class Loop:
    """The runtime at a fixed rate against one machine, along one reference at a time (:meth:`run`).

    Args:
        runtime: the runtime (:class:`~efficienttrack.deploy.runtime.Runtime` or one with its interface,
            see :class:`LoopRuntime`).
        machine: the machine adapter (:class:`Machine`); each :meth:`run` opens and closes it.
        limits: the machine's limits: the joint limits every reference sent is clamped to, and ``max_adjust_rate``,
            the largest change per tick of the adjustment really sent.
        cfg: timing, watchdogs and logging.
        clock: :data:`MONOTONIC` on a machine; a simulated or a test's fake clock otherwise.
        log: the open per-tick log, or None (no log).
        shadow: compute and log the adjustment, send the raw reference.
    """

    def __init__(
        self,
        runtime: LoopRuntime,
        machine: Machine,
        limits: GuardLimits,
        cfg: LoopConfig | None = None,
        clock: Clock = MONOTONIC,
        log: TickLog | None = None,
        shadow: bool = False,
    ) -> None:
        self.runtime, self.machine, self.limits = runtime, machine, limits
        self.cfg = LoopConfig() if cfg is None else cfg
        self.clock, self.log, self.shadow = clock, log, shadow
        self._rate = np.asarray(limits.max_adjust_rate, dtype=np.float64)
        self._good: Reading | None = None  # the newest finite reading
        self._a_sent = np.zeros(4)  # the adjustment really sent last tick
        self._q_sent: np.ndarray | None = None  # the reference really sent last tick

    def run(self, q_des: np.ndarray, name: str = "reference") -> LoopResult:
        """Track one reference: tick k sends the reference of step k+1, for k = 0 … L − 2.

        Args:
            q_des: (L, 4) rad, desired positions ``q*_0 … q*_{L−1}``, L ≥ 2, inside the joint limits.
            name: the reference's name, for the log and errors.

        Returns:
            What the run did; a watchdog's stop is a result (``reason``), not an exception.

        Raises:
            EfficientTrackError: a reference outside the joint limits, or a start that is unsafe (no fresh finite
                reading, the machine farther than ``start_tolerance`` from ``q*_0``): nothing was sent.
        """
        q_des = np.asarray(q_des, dtype=np.float64)
        if q_des.ndim != 2 or q_des.shape[1] != 4 or len(q_des) < 2:
            raise EfficientTrackError(f"loop '{name}': q_des must have shape (L, 4) with L ≥ 2, got {q_des.shape}")
        self.limits.check_reference(q_des, name)
        future = max(int(self.runtime.future_length), 1)
        padded = np.concatenate([q_des, np.repeat(q_des[-1:], future, axis=0)])
        last = len(q_des) - 2  # the last tick
        result = LoopResult(name=name)
        dt = self.cfg.dt
        with stop_signals_as_interrupt(), self.machine:
            self._good = self._start(q_des[0], name)
            self.runtime.start(self._good.obs[None])
            self._a_sent, self._q_sent = np.zeros(4), None
            t0 = self.clock.now()
            k, in_row, previous_end = 0, 0, t0
            try:
                while k <= last:
                    # wait for the deadline; skip whole periods already lost (the reference follows the clock)
                    now = self.clock.now()
                    if now < t0 + k * dt:
                        self.clock.sleep(t0 + k * dt - now)
                    start = self.clock.now()
                    missed = min(max(int((start - t0) // dt) - k, 0), last - k)
                    k += missed
                    deadline = t0 + k * dt
                    overrun = k > 0 and (previous_end > deadline or missed > 0)
                    in_row = in_row + 1 if overrun else 0
                    events = ["start"] if k == 0 else []
                    if overrun:
                        events.append("overrun")
                    if in_row >= self.cfg.hold_after:
                        events.append("hold")
                    stop = _Stop("overruns", f"{in_row} overruns in a row") if in_row >= self.cfg.stop_after else None
                    entry = self._tick(k, start, padded[k + 1 : k + 1 + future], last - k, events, stop)
                    previous_end = self.clock.now()
                    entry.update(tick=k, t=deadline - t0, lateness=start - deadline, work=previous_end - start, missed=missed)
                    result.ticks += 1
                    result.lateness.append(start - deadline)
                    result.compute.append(entry["compute"])
                    for event in events + ["missed_ticks"] * missed:
                        result.counts[event] = result.counts.get(event, 0) + 1
                    stop = entry.pop("stop")
                    self._write(**entry)
                    if stop is not None:
                        raise stop
                    k += 1
            except _Stop as stop:
                result.reason, result.error = stop.reason, stop.error
            except KeyboardInterrupt as interrupt:  # Ctrl-C, or SIGTERM / SIGHUP (stop_signals)
                result.reason, result.error = "interrupted", interrupt_name(interrupt)
                self._send_raw_quietly(q_des[min(k, last) + 1])
            finally:
                self.runtime.stop()
                self._write(event="end", **result.summary())
        return result

    def _tick(
        self, k: int, start: float, q_des_future: np.ndarray, ticks_left: int, events: list[str], stop: _Stop | None
    ) -> dict[str, Any]:
        """Tick k's read, compute and send (``events`` gets this tick's events); its log entry, with ``stop`` to raise.

        Args:
            k: the tick.
            start: when it started, s on the clock.
            q_des_future: (F, 4) rad, ``q*_{k+1} … q*_{k+F}``.
            ticks_left: ticks after this one.
            events: the loop's events of this tick so far (``hold`` sends the raw reference).
            stop: the stop already decided (the raw reference is sent, then the run ends), or None.
        """
        cfg = self.cfg
        # read: a dropped, non-finite or old sample sends the raw reference; a fault or a long silence stops
        obs = np.full(8, np.nan)
        try:
            reading = self._good if k == 0 else self.machine.read()
            reading = None if reading is None else _checked_reading(reading)
        except Exception as exc:
            reading = None
            stop = stop or _Stop("read_error", f"{type(exc).__name__}: {exc}")
        assert self._good is not None  # run reads the first good reading before the first tick
        fault = None
        if reading is None:
            events.append("dropped")
        elif not np.all(np.isfinite(reading.obs)):
            events.append("nonfinite")
        elif k > 0 and (fault := self._sensor_fault(self._good, reading)) is not None:
            events.append("sensor_fault")
            stop = stop or _Stop("sensor_fault", f"tick {k}: {fault}")
        else:
            obs, self._good = reading.obs, reading
        age = start - self._good.stamp
        if age > cfg.stop_stale_ticks * cfg.dt:
            stop = stop or _Stop("stale_sensor", f"last good reading {age * 1e3:.0f} ms old")
        elif age > cfg.stale_ticks * cfg.dt:
            events.append("stale")
        # compute
        before = self.clock.now()
        sent: Sent | None = None
        try:
            sent = self.runtime.step(obs[None], q_des_future[None])
        except Exception as exc:  # a runtime that raises: the raw reference, then stop
            stop = stop or _Stop("runtime_error", f"{type(exc).__name__}: {exc}")
        compute = self.clock.now() - before
        a = np.zeros(4) if sent is None else np.asarray(sent.adjustment, dtype=np.float64)[0]
        guard = [] if sent is None or sent.guard is None else _guard_names(int(sent.guard[0]))
        if sent is not None and bool(sent.fallback[0]):
            events.append("fallback")
        if self.shadow:
            events.append("shadow")
        # send: the raw reference, or the adjustment limited in rate and ramped down at the end
        q_raw = q_des_future[0]
        raw = stop is not None or bool({"start", "shadow", "hold", "dropped", "nonfinite", "stale"} & set(events))
        a_target = np.zeros(4) if raw else a
        a_send = self._limit(a_target, self._a_sent, ticks_left)
        if np.any(a_send != a_target):
            events.append("ramped")
        q_send = self.limits.clamp(q_raw + a_send)
        if fault is not None and self._q_sent is not None:
            q_send = self._q_sent  # hold: the machine's controller would steer to q_raw by the faulty reading
        self._a_sent = np.zeros(4)  # if the send fails, nothing adjusted was sent
        q_taken = self._send(q_send)
        self._q_sent = q_taken
        self._a_sent = q_taken - q_raw
        self._a_sent[SWING] = wrap(self._a_sent[SWING])
        if np.any(q_taken != q_send):
            events.append("send_changed")
        sent_instead: Callable[[np.ndarray], None] | None = getattr(self.runtime, "sent_instead", None)
        if sent is not None and sent_instead is not None and np.any(q_taken != np.asarray(sent.q_ref)[0]):
            sent_instead(q_taken[None])
        return dict(
            compute=compute,
            age=age,
            events=events,
            guard=guard,
            obs=obs,
            q_des=q_raw,
            a=a,
            a_sent=self._a_sent,
            q_ref=q_taken,
            stop=stop,
        )

    def _start(self, q0: np.ndarray, name: str) -> Reading:
        """The first reading, checked safe to start from: present, finite, fresh, near ``q*_0``; else nothing is sent."""
        try:
            reading = self.machine.read()
            reading = None if reading is None else _checked_reading(reading)
        except Exception as exc:
            raise EfficientTrackError(
                f"loop '{name}': the machine's first read failed ({type(exc).__name__}: {exc}); nothing was sent"
            ) from exc
        if reading is None or not np.all(np.isfinite(reading.obs)):
            raise EfficientTrackError(f"loop '{name}': no finite first reading from the machine; nothing was sent")
        fault = first_sensor_fault(reading.obs, np.array([reading.stamp]), self.limits, self.cfg.sensor_margin)
        if fault is not None:
            raise EfficientTrackError(
                f"loop '{name}': sensor fault in the first reading: {fault.describe()}; nothing was sent"
            )
        age = self.clock.now() - reading.stamp
        if age > self.cfg.stale_ticks * self.cfg.dt:
            raise EfficientTrackError(
                f"loop '{name}': the machine's first reading is {age * 1e3:.0f} ms old (stale); nothing was sent"
            )
        gap = np.abs(reading.obs[:4] - q0)
        gap[SWING] = abs(wrap(gap[SWING]))
        if np.any(gap > self.cfg.start_tolerance):
            j = int(np.argmax(gap))
            raise NotAtStart(
                f"loop '{name}': the machine is {gap[j]:.3f} rad from the reference's first position "
                f"(joint {j}, tolerance {self.cfg.start_tolerance} rad); move it to the start first, or let it approach "
                "(--between-episodes approach); nothing was sent",
                reading.obs[:4].copy(),
            )
        return reading

    def _sensor_fault(self, previous: Reading, reading: Reading) -> str | None:
        """What makes ``reading`` impossible after ``previous`` (:mod:`~efficienttrack.deploy.sensor`), or None."""
        obs, stamps = np.stack([previous.obs, reading.obs]), np.array([previous.stamp, reading.stamp])
        fault = first_sensor_fault(obs, stamps, self.limits, self.cfg.sensor_margin, self.cfg.sensor_tolerance)
        return None if fault is None else fault.describe()

    def _limit(self, a_target: np.ndarray, a_last: np.ndarray, ticks_left: int) -> np.ndarray:
        """The adjustment to send: a = 0 at once, else at most ``rate`` from the last one sent and ``rate·ticks_left``."""
        if not np.any(a_target):
            return np.zeros(4)
        bound = self._rate * ticks_left
        return np.clip(self.limits.rate_limit(a_target, a_last), -bound, bound)

    def _send(self, q_ref: np.ndarray) -> np.ndarray:
        """Send ``q_ref`` (4,) rad; the machine's answer, checked; a fault stops the run (nothing more is sent)."""
        try:
            taken = np.asarray(self.machine.send(q_ref.copy()), dtype=np.float64)
        except Exception as exc:
            raise _Stop("send_error", f"{type(exc).__name__}: {exc}") from exc
        if taken.shape != (4,) or not np.all(np.isfinite(taken)):
            raise _Stop("send_error", f"the machine reported sending {taken!r}, not 4 finite positions")
        return taken

    def _send_raw_quietly(self, q_raw: np.ndarray) -> None:
        """After Ctrl-C: one last raw reference, if the machine takes it."""
        try:
            self.machine.send(np.array(q_raw, dtype=np.float64))
        except Exception:  # the run is ending anyway; closing the machine follows
            return

    def _write(self, **entry: Any) -> None:
        if self.log is not None:
            self.log.write(entry)


def _checked_reading(reading: Any) -> Reading:
    """A machine's reading as a :class:`Reading` with obs (8,); malformed ones raise (an adapter fault)."""
    if not isinstance(reading, tuple) or len(reading) != 2:
        raise EfficientTrackError(f"read() must return Reading(obs, stamp) or None, got {type(reading).__name__}")
    obs = np.asarray(reading[0], dtype=np.float64).reshape(-1)
    stamp = float(reading[1])
    if obs.shape != (8,) or not math.isfinite(stamp):
        raise EfficientTrackError(f"read() gave obs of {obs.size} values and stamp {stamp}; needs 8 values and a finite stamp")
    return Reading(obs, stamp)


def _guard_names(bits: int) -> list[str]:
    """The runtime guard's reasons in one step's bits, lower case."""
    return [str(flag.name).lower() for flag in Guard if bits & flag.value]
