"""The machine side of the loop: the :class:`Machine` adapter protocol, the clocks, and simulated machines to rehearse on.

A real machine is one adapter class of the owner's (docs/your-machine.md). Two simulated twins stand in for it:
:class:`SimulatedMachine`, which ``deploy`` and ``collect`` drive when no ``--machine`` is given (a simulator reset at each
reference's start), and :func:`simulated`, a machine for ``--machine efficienttrack.deploy.machine:simulated`` that
behaves as a real one does: it stays where the last episode left it, and injects the faults a real one has on request.
"""

from __future__ import annotations

import time
from typing import NamedTuple, Protocol

import numpy as np

from efficienttrack.core.angles import parse_pose
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import BUILTIN_SYSTEMS, SystemSpec


class Clock(Protocol):
    """Where the loop reads the time and waits: seconds on one monotonic clock shared with the readings' stamps."""

    def now(self) -> float:
        """Seconds on the clock."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait.

        Args:
            seconds: how long, ≥ 0.
        """
        ...


class MonotonicClock:
    """The real clock: ``time.monotonic`` and ``time.sleep``."""

    def now(self) -> float:
        """Seconds of ``time.monotonic``."""
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        """``time.sleep``.

        Args:
            seconds: how long, ≥ 0.
        """
        time.sleep(seconds)


MONOTONIC = MonotonicClock()
"""The clock of a run on a real machine."""


class Reading(NamedTuple):
    """One sample of the machine's sensors.

    Attributes:
        obs: (8,) [rad, rad/s], ``(q, q̇)``, joints boom, arm, bucket, swing.
        stamp: s, when it was measured, on the loop's clock (``time.monotonic`` for :data:`MONOTONIC`).
    """

    obs: np.ndarray
    stamp: float


class Machine(Protocol):
    """A machine adapter: one machine's sensors in, position references out, with a lifecycle.

    ``with machine:`` opens it (connect, or reset a simulator) and closes it however the run ends. ``read``
    returns the newest sample, or None when there is none (a dropped sample); ``send`` hands the position
    controller a reference and returns the reference it really took (a machine that clamps says so).
    """

    def __enter__(self) -> Machine:
        """Open the machine."""
        ...

    def __exit__(self, *exc: object) -> None:
        """Close the machine."""
        ...

    def read(self) -> Reading | None:
        """The newest sample, or None (dropped)."""
        ...

    def send(self, q_ref: np.ndarray) -> np.ndarray:
        """Send a position reference.

        Args:
            q_ref: (4,) rad.

        Returns:
            (4,) rad, the reference the machine really took.
        """
        ...


class SimulatedClock:
    """A clock that only moves when slept on: a simulator runs as fast as it computes.

    Args:
        start: the clock's time at first, s.
    """

    def __init__(self, start: float = 0.0) -> None:
        self.t = float(start)

    def now(self) -> float:
        """The simulated time, s."""
        return self.t

    def sleep(self, seconds: float) -> None:
        """Advance the time by ``seconds`` at once.

        Args:
            seconds: how long, ≥ 0.
        """
        self.t += max(float(seconds), 0.0)


class SimulatedMachine:
    """A closed-loop system (``SystemSpec.open()``, e.g. the built-in ``xe75``) as a :class:`Machine`.

    Opening resets the simulator at ``q0``; ``read`` returns its state stamped with the clock's time; ``send`` steps it
    once (one control period) and returns the reference as given.

    Args:
        system: the checked system (one machine).
        q0: (4,) rad, the start position (the reference's first).
        clock: the loop's clock (for the stamps).
    """

    def __init__(self, system: BatchedSystem, q0: np.ndarray, clock: Clock = MONOTONIC) -> None:
        self.system, self.q0, self.clock = system, np.asarray(q0, dtype=np.float64), clock
        self._obs: np.ndarray | None = None

    def __enter__(self) -> SimulatedMachine:
        """Reset the simulator at ``q0``."""
        self._obs = np.asarray(self.system.reset(self.q0[None]), dtype=np.float64)[0]
        return self

    def __exit__(self, *exc: object) -> None:
        """Nothing to release."""
        self._obs = None

    def read(self) -> Reading | None:
        """The simulator's state, stamped now."""
        return self.state()

    def state(self) -> Reading:
        """The simulator's state, stamped now (:meth:`read` without its faults, in a subclass that has them)."""
        if self._obs is None:
            raise EfficientTrackError(f"{self.system.name}: read before open")
        return Reading(self._obs.copy(), self.clock.now())

    def send(self, q_ref: np.ndarray) -> np.ndarray:
        """One simulator step towards ``q_ref`` (4,) rad; returns it."""
        if self._obs is None:
            raise EfficientTrackError(f"{self.system.name}: send before open")
        self._obs = np.asarray(self.system.step(np.asarray(q_ref, dtype=np.float64)[None]), dtype=np.float64)[0]
        return np.asarray(q_ref, dtype=np.float64)


FAULTS = ("nan", "drop", "stale", "late", "read_error", "send_error")
"""What :func:`simulated` can inject: a NaN reading, no reading, a reading that stops changing (its stamp too), a read
that takes three control periods, a read that raises, a send that raises."""


class RehearsalMachine(SimulatedMachine):
    """A simulated machine that behaves as a real one: opened many times, it goes on from where it stood.

    Built by :func:`simulated`, which also sets its fault: opening it does not reset the simulator (only its first
    opening does, at ``q0``), and on request it injects one kind of fault (:data:`FAULTS`) from read ``fault_at`` on of
    its ``fault_episode``-th opening (every opening when None).

    Args:
        system: the simulator (one machine).
        q0: (4,) rad, where it stands at first.
        kind: the built-in system it simulates (:func:`simulated`'s ``system``).
    """

    def __init__(self, system: BatchedSystem, q0: np.ndarray, kind: str) -> None:
        super().__init__(system, q0)
        self.kind = kind
        self.fault: str | None = None
        self.fault_at = 0
        self.fault_episode: int | None = None
        self.openings, self.reads = 0, 0
        self._frozen: Reading | None = None

    def __enter__(self) -> RehearsalMachine:
        """Open: reset the simulator at ``q0`` the first time; later, go on from where it stands."""
        if self.openings == 0:
            super().__enter__()
        self.openings, self.reads, self._frozen = self.openings + 1, 0, None
        return self

    def __exit__(self, *exc: object) -> None:
        """Close; the machine stays where it is."""

    def read(self) -> Reading | None:
        """The simulator's state, stamped now, or the fault asked for."""
        k, self.reads = self.reads, self.reads + 1
        if not self._faulty(k):
            return self.state()
        if self.fault == "read_error":
            raise OSError("simulated fault: the sensor bus does not answer")
        if self.fault == "drop":
            return None
        if self.fault == "late":
            self.clock.sleep(3 * self.system.dt)
            return self.state()
        if self.fault == "stale":
            self._frozen = self._frozen or self.state()
            return self._frozen
        reading = self.state()
        reading.obs[2] = np.nan
        return reading

    def send(self, q_ref: np.ndarray) -> np.ndarray:
        """One simulator step towards ``q_ref`` (4,) rad, or the send fault asked for."""
        if self.fault == "send_error" and self._faulty(self.reads - 1):
            raise OSError("simulated fault: the valve driver refused the command")
        return super().send(q_ref)

    def _faulty(self, k: int) -> bool:
        """Whether the fault applies at read ``k`` of this opening."""
        opening = self.fault_episode is None or self.openings == self.fault_episode
        return self.fault is not None and k >= self.fault_at and opening


_MACHINES: dict[str, RehearsalMachine] = {}
"""The simulated machines of this process by name: each stays where its last episode left it."""


def simulated(
    system: str = "xe75",
    start: str | None = None,
    name: str = "default",
    fault: str | None = None,
    fault_at: int = 0,
    fault_episode: int | None = None,
    clock: Clock = MONOTONIC,
) -> RehearsalMachine:
    """A simulated machine to rehearse a real one on: ``--machine efficienttrack.deploy.machine:simulated``.

    Every adapter built with the same ``name`` in one process is the same machine, which stays where the last episode
    left it (as a real one does): the first episode starts at ``start``, each later one where the one before ended, so
    collection and deployment must bring it to each reference's start (``--between-episodes approach``).

    Args:
        system: a built-in system (``xe75``, ``paper``), the machine's physics and position controller.
        start: ``"q_boom,q_arm,q_bucket,q_swing"`` rad, where the machine stands at first (the middle of its joint
            range when None).
        name: which machine of the process (``--machine-opt name=…``): another name is another machine.
        fault: one of :data:`FAULTS` to inject, or None.
        fault_at: the read of an episode from which on the fault is injected (0: the first).
        fault_episode: the opening (from 1, counted per machine: a refused start and an approach count) that gets the
            fault; None: every one.
        clock: the loop's clock (the runner passes it: a simulated one under ``--fast``).

    Raises:
        EfficientTrackError: an unknown system or fault, a fault tick or opening that is no whole number ≥ 0, or a start
            that is not four numbers.
    """
    if fault is not None and fault not in FAULTS:
        raise EfficientTrackError(f"simulated machine: fault '{fault}' is none of {', '.join(FAULTS)}")
    for option, value in (("fault_at", fault_at), ("fault_episode", fault_episode)):
        if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 0):
            raise EfficientTrackError(f"simulated machine: {option} must be a whole number ≥ 0, got {value!r}")
    if system not in BUILTIN_SYSTEMS or system == "learned":
        raise EfficientTrackError(f"simulated machine: system '{system}' is no built-in physical system (xe75, paper)")
    machine = _MACHINES.get(name)
    if machine is None or machine.kind != system:
        physics = SystemSpec(system=system).open()
        lo, hi = np.asarray(physics.limits.q_min), np.asarray(physics.limits.q_max)
        q0 = np.clip((lo + hi) / 2, -1.0, 1.0) if start is None else parse_pose(start, "simulated machine: start")
        machine = _MACHINES[name] = RehearsalMachine(physics, q0, system)
    machine.clock, machine.fault, machine.fault_at, machine.fault_episode = clock, fault, fault_at, fault_episode
    return machine
