"""The two interfaces every machine or simulator is seen through, and how to load one by name.

``Plant`` (PWM level)
    ``dt`` control period in s (0.05 for the XE75); ``reset(q0) -> obs``; ``step(u) -> obs``.
``ClosedLoopSystem`` (reference level)
    ``dt``; ``reset(q0) -> obs``; ``step(q_ref_next) -> obs``. A plant wrapped with its position
    controller, or a real machine whose own controller takes position references.

Channels (joint order boom, arm, bucket, swing everywhere):

======== ============ ========================== ======================================
name     shape        unit                       meaning
======== ============ ========================== ======================================
q0       (4,)/(N, 4)  rad                        initial joint positions for ``reset``
u        (4,)/(N, 4)  PWM, −1000 … 1000          valve command (``Plant.step``)
q_ref    (4,)/(N, 4)  rad                        position reference for the next step
obs      (8,)/(N, 8)  [q rad, q̇ rad/s]           observation after reset / the step
======== ============ ========================== ======================================

Batch semantics: a system that sets the attribute ``batched = True`` accepts ``(N, 4)`` inputs
and returns ``(N, 8)`` observations for any N it was reset with. Without it, the system takes
single ``(4,)`` arrays only (a real machine is N = 1); the package then runs it one episode at a
time. A closed-loop system may expose ``last_command`` (the PWM it applied in the last step,
``(4,)``/``(N, 4)``); it is recorded when present. It may expose ``limits`` (a
:class:`~efficienttrack.systems.limits.GuardLimits` or a mapping of its fields): the joint limits and adjustment
bounds the runtime guard enforces; without it the guard uses
:data:`~efficienttrack.systems.limits.DEFAULT_LIMITS`. A batched system may offer
``reset_machines(index (K,), q0 (K, 4)) -> obs (K, 8)``: reset some machines while the others keep
their state; the vector environment (:mod:`efficienttrack.envs`) needs it to start one sub-environment's
next episode while the others run on (the built-in simulator and PD loop have it).

Loading a system by name or import path: :mod:`efficienttrack.systems.spec`.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import N_JOINTS, OBS_DIM
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits


@runtime_checkable
class Plant(Protocol):
    """PWM-level machine or simulator: ``reset(q0) -> obs``, ``step(u) -> obs``."""

    dt: float

    def reset(self, q0: np.ndarray) -> np.ndarray:
        """Put the machine at ``q0`` (4,)/(N, 4) rad at rest; return obs (8,)/(N, 8)."""
        ...

    def step(self, u: np.ndarray) -> np.ndarray:
        """Apply PWM ``u`` (4,)/(N, 4) for one period ``dt``; return the next obs (8,)/(N, 8)."""
        ...


@runtime_checkable
class ClosedLoopSystem(Protocol):
    """Reference-level system: ``reset(q0) -> obs``, ``step(q_ref_next) -> obs``."""

    dt: float

    def reset(self, q0: np.ndarray) -> np.ndarray:
        """Put the machine at ``q0`` (4,)/(N, 4) rad at rest; return obs (8,)/(N, 8)."""
        ...

    def step(self, q_ref: np.ndarray) -> np.ndarray:
        """Track ``q_ref`` (4,)/(N, 4) rad for one period ``dt``; return the next obs (8,)/(N, 8)."""
        ...


class BatchedSystem:
    """A uniform, checked, batched view of any Plant or ClosedLoopSystem.

    Inputs and outputs are always ``(N, 4)`` / ``(N, 8)`` float64. An unbatched system is
    driven with N = 1 (``max_batch`` is 1). Every observation is checked for shape and
    finiteness, so a misbehaving user system fails with a message naming it instead of
    producing silently wrong numbers downstream.

    Args:
        system: the Plant or ClosedLoopSystem to wrap.
        name: how to name it in errors (the spec it was loaded from).
    """

    def __init__(self, system: Any, name: str = "system") -> None:
        self.system = system
        self.name = name
        dt = getattr(system, "dt", None)
        if not isinstance(dt, int | float) or not np.isfinite(dt) or dt <= 0:
            raise EfficientTrackError(f"{name}: attribute 'dt' must be a positive number of seconds, got {dt!r}")
        for method in ("reset", "step"):
            if not callable(getattr(system, method, None)):
                raise EfficientTrackError(f"{name}: has no method '{method}'")
        self.dt = float(dt)
        self.batched = bool(getattr(system, "batched", False))
        self.max_batch: int | None = None if self.batched else 1
        own = getattr(system, "limits", None)
        self.limits = DEFAULT_LIMITS if own is None else GuardLimits.coerce(own, f"{name}: attribute 'limits'")
        """What the runtime guard may send: the system's own ``limits``, a user's limits file (``SystemSpec.limits``),
        or :data:`~efficienttrack.systems.limits.DEFAULT_LIMITS`."""
        self._n = 0

    def reset(self, q0: np.ndarray) -> np.ndarray:
        """Reset N machines; ``q0`` (N, 4) rad → obs (N, 8)."""
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.ndim != 2 or q0.shape[1] != N_JOINTS:
            raise EfficientTrackError(f"{self.name}: reset expects q0 of shape (N, 4), got {q0.shape}")
        self._check_batch(len(q0))
        self._n = len(q0)
        return self._checked(self.system.reset(q0 if self.batched else q0[0]), "reset")

    @property
    def resets_machines(self) -> bool:
        """Whether some machines can be reset while the others run on (:meth:`reset_machines`)."""
        return self.max_batch == 1 or callable(getattr(self.system, "reset_machines", None))

    def reset_machines(self, index: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Reset the machines ``index`` (K,) at ``q0`` (K, 4) rad, the others keep running → their obs (K, 8).

        All N at once is a plain :meth:`reset`; otherwise the system's own ``reset_machines`` does it.
        """
        index = np.asarray(index, dtype=np.int64)
        q0 = np.asarray(q0, dtype=np.float64)
        if (
            q0.shape != (len(index), N_JOINTS)
            or len(np.unique(index)) != len(index)
            or np.any((index < 0) | (index >= self._n))
        ):
            raise EfficientTrackError(
                f"{self.name}: reset_machines expects distinct indices below N = {self._n} and q0 of shape (K, 4), "
                f"got {index.tolist()} and {q0.shape}"
            )
        if len(index) == self._n:
            return self.reset(q0[np.argsort(index)])[index]
        if not self.resets_machines:
            raise EfficientTrackError(f"{self.name}: cannot reset single machines of a batch (it has no 'reset_machines')")
        obs = self.system.reset_machines(index, q0)
        try:
            obs = np.asarray(obs, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise EfficientTrackError(f"{self.name}: reset_machines returned something that is not a numeric array") from exc
        if obs.shape != (len(index), OBS_DIM) or not np.all(np.isfinite(obs)):
            raise EfficientTrackError(
                f"{self.name}: reset_machines returned obs of shape {obs.shape} (expected ({len(index)}, 8)) "
                "or non-finite values"
            )
        return obs

    def step(self, x: np.ndarray) -> np.ndarray:
        """Step N machines with ``x`` (N, 4) (PWM or q_ref) → obs (N, 8)."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self._n, N_JOINTS):
            raise EfficientTrackError(f"{self.name}: step expects ({self._n}, 4) after reset, got {x.shape}")
        return self._checked(self.system.step(x if self.batched else x[0]), "step")

    @property
    def last_command(self) -> np.ndarray | None:
        """PWM applied in the last step, (N, 4), or None when the system does not expose it."""
        u = getattr(self.system, "last_command", None)
        if u is None:
            return None
        return np.asarray(u, dtype=np.float64).reshape(self._n, N_JOINTS)

    def _check_batch(self, n: int) -> None:
        if n < 1:
            raise EfficientTrackError(f"{self.name}: reset needs at least one machine")
        if self.max_batch is not None and n > self.max_batch:
            raise EfficientTrackError(f"{self.name}: takes single machines only (no 'batched = True'), got N = {n}")

    def _checked(self, obs: Any, what: str) -> np.ndarray:
        try:
            obs = np.asarray(obs, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise EfficientTrackError(f"{self.name}: {what} returned something that is not a numeric array") from exc
        expected = (self._n, OBS_DIM) if self.batched else (OBS_DIM,)
        if obs.shape != expected:
            raise EfficientTrackError(f"{self.name}: {what} returned obs of shape {obs.shape}, expected {expected}")
        if not np.all(np.isfinite(obs)):
            raise EfficientTrackError(f"{self.name}: {what} returned a non-finite observation {obs.tolist()}")
        return obs.reshape(self._n, OBS_DIM)


def machines_to_reset(index: Any, q0: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The arguments of a batched plant's ``reset_machines``, checked and converted.

    Args:
        index: (K,) which machines.
        q0: (K, 4) rad, their start positions.
        name: the plant, for the message.

    Returns:
        ``index`` as (K,) int64 and ``q0`` as (K, 4) float64.
    """
    index = np.asarray(index, dtype=np.int64)
    q0 = np.asarray(q0, dtype=np.float64)
    if q0.shape != (len(index), N_JOINTS):
        raise EfficientTrackError(f"{name}: reset_machines expects q0 of shape ({len(index)}, 4), got {q0.shape}")
    return index, q0


def check_system(system: Any, q0: np.ndarray | None = None, steps: int = 5, name: str = "system") -> None:
    """Check that ``system`` follows the ClosedLoopSystem protocol; raise EfficientTrackError if not.

    Resets it at ``q0`` (4,) rad (zeros by default) and holds that reference for ``steps`` steps,
    checking ``dt``, shapes and finiteness on the way. Run it on your own machine wrapper before
    training on it.

    Args:
        system: the system to check (a ClosedLoopSystem, or one already wrapped in a :class:`BatchedSystem`).
        q0: (4,) rad, the start position and held reference; zeros by default.
        steps: number of steps to run.
        name: how to name the system in errors (unused when ``system`` is already a :class:`BatchedSystem`).
    """
    view = system if isinstance(system, BatchedSystem) else BatchedSystem(system, name=name)
    start = np.zeros((1, N_JOINTS)) if q0 is None else np.asarray(q0, dtype=np.float64).reshape(1, N_JOINTS)
    view.reset(start)
    for _ in range(steps):
        view.step(start)
