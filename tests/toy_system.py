"""A small external closed-loop system for tests: loadable as ``tests.toy_system:make``.

Each joint follows its reference with a first-order lag, ``q[t+1] = q[t] + k·(q_ref[t] − q[t])``,
so PD-like tracking of a moving reference lags behind by ``v·(1 − k)/k`` for a reference moving
``v`` rad per step. The adjustment that removes the lag exactly is
``a = (1/k − 1)·(q*[t+1] − q[t])``: a policy has something real to learn. With ``delay = d`` the reference
acts d steps late (``q_ref[t − d]`` in place of ``q_ref[t]``; the start position before the first d steps).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from efficienttrack.data.references import Reference
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.config import PRESETS


class LagSystem:
    """Reference-level first-order lag, optionally batched.

    Args:
        gain: fraction k of the remaining error closed per step, in (0, 1].
        batched: accept (N, 4) inputs (True) or single (4,) arrays only (False).
        dt: control period, s.
        delay: steps d ≥ 0 by which the reference acts late.
    """

    def __init__(self, gain: float = 0.4, batched: bool = True, dt: float = 0.05, delay: int = 0) -> None:
        self.k = float(gain)
        self.batched = bool(batched)
        self.dt = float(dt)
        self.delay = int(delay)
        self.last_command: np.ndarray | None = None
        self._q: np.ndarray | None = None
        self._pending: list[np.ndarray] = []

    def reset(self, q0):
        self._q = np.array(q0, dtype=np.float64)
        self._pending = [self._q.copy() for _ in range(self.delay)]
        self.last_command = None
        return np.concatenate([self._q, np.zeros_like(self._q)], axis=-1)

    def step(self, q_ref):
        q_ref = np.asarray(q_ref, dtype=np.float64)
        assert q_ref.shape == self._q.shape, (q_ref.shape, self._q.shape)
        self._pending.append(q_ref)
        dq = self.k * (self._pending.pop(0) - self._q)
        self.last_command = 1000.0 * dq
        self._q = self._q + dq
        return np.concatenate([self._q, dq / self.dt], axis=-1)


def make(gain: float = 0.4, batched: bool = True, delay: int = 0) -> LagSystem:
    """Build the toy system (the ``module:callable`` entry point)."""
    return LagSystem(gain=gain, batched=batched, delay=delay)


DIE_ONCE = "EFFICIENTTRACK_TEST_DIE_ONCE"
"""Environment variable naming a marker file: the first process to open :func:`make_dying` while it exists removes it
and dies at once, as a worker killed by the kernel would (spawned workers inherit the variable)."""


def make_dying() -> LagSystem:
    """The toy system, or the death of the opening process when the :data:`DIE_ONCE` marker is there to take."""
    import os

    marker = os.environ.get(DIE_ONCE)
    if marker:
        try:
            os.unlink(marker)
        except FileNotFoundError:
            pass
        else:
            os._exit(1)
    return make()


def sine_refs(lengths: list[int], seed: int = 0) -> list[Reference]:
    """Smooth multi-sine references of the given lengths (20 Hz, amplitudes 0.2–0.5 rad), named ref_00, ref_01, …"""
    rng = np.random.default_rng(seed)
    refs = []
    for i, n in enumerate(lengths):
        t = np.arange(n) * 0.05
        amp, freq, phase = rng.uniform(0.2, 0.5, 4), rng.uniform(0.1, 0.4, 4), rng.uniform(0, 6, 4)
        refs.append(Reference(f"ref_{i:02d}", amp * np.sin(2 * np.pi * freq * t[:, None] + phase)))
    return refs


class IntegratorPlant:
    """PWM-level toy plant, batched: ``q̇ = 1e-3·direction·u`` rad/s (XE75 sign convention), for ``--plant`` tests."""

    dt = 0.05
    batched = True
    direction = np.array([-1.0, -1.0, -1.0, 1.0])

    def reset(self, q0):
        self._q = np.array(q0, dtype=np.float64)
        return np.concatenate([self._q, np.zeros_like(self._q)], axis=-1)

    def step(self, u):
        qd = 1e-3 * self.direction * np.asarray(u, dtype=np.float64)
        self._q = self._q + qd * self.dt
        return np.concatenate([self._q, qd], axis=-1)


def make_plant() -> IntegratorPlant:
    """Build the toy plant (the ``module:callable`` entry point for ``--plant``)."""
    return IntegratorPlant()


TOY = SystemSpec(system="toy_system:make")
"""This module's system, as a run names it."""
TINY = PRESETS["tiny"]
TOY_CFG = replace(
    TINY,
    device="cpu",
    collect=replace(TINY.collect, passes=6),
    model=replace(TINY.model, steps=100),
    policy=replace(TINY.policy, steps=100),
)
"""The tiny preset with more data and short trainings: ~3 s on one core. Its policy leaves under 0.3 × PD's tracking
error (the toy runs check 0.5 ×) at every seed tried; 300 steps each reached 0.23 × in twice the time."""


def toy_split() -> tuple[list[Reference], list[Reference]]:
    """Four training and two test references for the toy runs."""
    refs = sine_refs([80, 70, 90, 75, 85, 60], seed=4)
    return refs[:4], refs[4:]
