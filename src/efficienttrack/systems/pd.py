"""The PD position controller of the real XE75 and its composition with a plant.

Per joint, with e[t] = wrap(q_ref[t] − q[t]):

    u[t] = clip(s·(kp·e[t] + kd·(e[t] − e[t−1]) + c·sign(e[t])), −u_max, u_max)

At the first step of an episode the previous error is taken equal to the current one.
Gains of the real machine were fitted on its logs (see the data README): they reproduce the
logged PWM exactly.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.configfile import is_finite_number, read_mapping_file
from efficienttrack.core.errors import EfficientTrackError


@dataclass(frozen=True)
class PDGains:
    """Gains of the per-joint PD law (joint order boom, arm, bucket, swing)."""

    kp: tuple[float, float, float, float]
    """Proportional gain, PWM per rad."""
    kd: tuple[float, float, float, float]
    """Gain on the error difference over one step, PWM per rad."""
    sign: tuple[float, float, float, float]
    """Sign from the error to the PWM: −1 where a positive PWM moves the joint to smaller angles."""
    c: float = 400.0
    """Constant push in the direction of the error, PWM (overcomes the valve dead zone)."""
    u_max: float = 1000.0
    """PWM saturation."""

    def __post_init__(self) -> None:
        """Check every field: kp, kd ≥ 0 and sign ±1, 4 values each (boom, arm, bucket, swing); c ≥ 0; u_max > 0.

        Raises:
            EfficientTrackError: naming the field and the problem (a gain of the wrong type, shape, sign or not finite).
        """
        for name in ("kp", "kd", "sign"):
            values = getattr(self, name)
            if not isinstance(values, tuple | list) or len(values) != 4 or not all(map(is_finite_number, values)):
                raise EfficientTrackError(f"PD gains: field '{name}' needs 4 numbers (boom, arm, bucket, swing): {values!r}")
            object.__setattr__(self, name, tuple(float(v) for v in values))
        for name in ("c", "u_max"):
            if not is_finite_number(getattr(self, name)):
                raise EfficientTrackError(f"PD gains: field '{name}' needs one number, got {getattr(self, name)!r}")
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("kp", "kd"):
            if not all(v >= 0 for v in getattr(self, name)):
                raise EfficientTrackError(f"PD gains: field '{name}' must be ≥ 0 per joint, got {getattr(self, name)}")
        if not all(v in (-1.0, 1.0) for v in self.sign):
            raise EfficientTrackError(f"PD gains: field 'sign' must be −1 or 1 per joint, got {self.sign}")
        if self.c < 0:
            raise EfficientTrackError(f"PD gains: field 'c' must be ≥ 0 PWM, got {self.c}")
        if self.u_max <= 0:
            raise EfficientTrackError(f"PD gains: field 'u_max' must be > 0 PWM (the saturation), got {self.u_max}")

    def command(self, e: np.ndarray, e_prev: np.ndarray) -> np.ndarray:
        """PWM for errors ``e`` and previous errors ``e_prev``, both (..., 4) rad → (..., 4) PWM."""
        kp, kd, s = np.asarray(self.kp), np.asarray(self.kd), np.asarray(self.sign)
        raw = s * (kp * e + kd * (e - e_prev) + self.c * np.sign(e))
        return np.clip(raw, -self.u_max, self.u_max)

    def step(self, q_ref: np.ndarray, q: np.ndarray, e_prev: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """One step of the law: the PWM and the error ``e = wrap(q_ref − q)`` to pass as ``e_prev`` next step.

        Args:
            q_ref: (..., 4) rad, the reference (target of the next step).
            q: (..., 4) rad, the measured position.
            e_prev: (..., 4) rad, the error of the previous step; None at an episode's first step (taken equal to e).

        Returns:
            u (..., 4) PWM and e (..., 4) rad.
        """
        e = wrap(np.asarray(q_ref, dtype=np.float64) - q)
        return self.command(e, e if e_prev is None else e_prev), e

    @classmethod
    def load(cls, spec: str) -> PDGains:
        """A named preset (``xe75``) or a JSON file with the fields of this class.

        Args:
            spec: a preset name (a key of :data:`PD_PRESETS`) or the path of a JSON file.
        """
        if spec in PD_PRESETS:
            return PD_PRESETS[spec]
        path = Path(spec)
        if not path.is_file():
            raise EfficientTrackError(f"PD gains '{spec}': neither a preset ({', '.join(PD_PRESETS)}) nor a JSON file")
        data: Any = read_mapping_file(path)  # size-capped, duplicated keys refused
        known = [f.name for f in fields(cls)]
        if not isinstance(data, dict):
            raise EfficientTrackError(f"{path}: not a valid PD gains file: expected an object with {', '.join(known)}")
        unknown, missing = sorted(set(data) - set(known)), [name for name in ("kp", "kd", "sign") if name not in data]
        if unknown or missing:
            problem = f"unknown field(s) {', '.join(unknown)}" if unknown else f"missing field(s) {', '.join(missing)}"
            raise EfficientTrackError(f"{path}: not a valid PD gains file: {problem}; fields: {', '.join(known)}")
        try:
            return cls(**data)
        except EfficientTrackError as exc:
            raise EfficientTrackError(f"{path}: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable fields."""
        return asdict(self)


XE75_PD = PDGains(kp=(5000.0, 1000.0, 1000.0, 500.0), kd=(15006.0, 6016.0, 4284.0, 7000.0), sign=(-1.0, -1.0, -1.0, 1.0))
"""The real XE75's PD law, fitted on its logs (data README)."""
PAPER_PD = PDGains(kp=(2090.0, 1320.0, 220.0, 1320.0), kd=(393.6, 143.36, 10.08, 480.0), sign=(-1.0, -1.0, -1.0, 1.0), c=0.0)
"""The PD law of the paper's simulator (research repository, ``simulation/pid_controller.py``): kp = 0.55·(3800, 2400,
400, 2400) and kd = 0.008·Ku·Tu / 50 with Ku = (4000, 1400, 100, 3000), Tu = 500·(1.23, 1.28, 1.26, 2), no constant
push. The original does not clip the PWM; its valves are saturated long before ±1000, so the clip changes nothing."""
PD_PRESETS: dict[str, PDGains] = {"xe75": XE75_PD, "paper": PAPER_PD}


class ClosedLoop:
    """A Plant under PD position control: a ClosedLoopSystem.

    ``step(q_ref)`` computes the PWM from the current position and ``q_ref`` (the target for
    the next step), applies it to the plant and returns the next observation. Batched exactly
    when the plant is.

    Args:
        plant: any Plant (``reset(q0) -> obs``, ``step(u) -> obs``).
        gains: the PD law; the XE75's by default.
    """

    def __init__(self, plant: Any, gains: PDGains = XE75_PD) -> None:
        self.plant = plant
        self.gains = gains
        self.dt = plant.dt
        self.batched = bool(getattr(plant, "batched", False))
        self.last_command: np.ndarray | None = None
        self._q: np.ndarray | None = None
        self._e_prev: np.ndarray | None = None
        self._restarted: np.ndarray | None = None

    @property
    def limits(self) -> Any:
        """The plant's ``limits`` (what the runtime guard may send it), or None when the plant gives none."""
        return getattr(self.plant, "limits", None)

    def reset(self, q0: np.ndarray) -> np.ndarray:
        """Reset the plant at ``q0`` (4,)/(N, 4) rad; return obs (8,)/(N, 8)."""
        obs = np.asarray(self.plant.reset(q0), dtype=np.float64)
        self._q = obs[..., :4]
        self._e_prev = None
        self._restarted = None
        self.last_command = None
        return obs

    def reset_machines(self, index: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Reset some of the N machines at ``q0`` (the plant's ``reset_machines``); the others keep running.

        Their next step is an episode's first (``e_prev = e``), exactly as after :meth:`reset`.

        Args:
            index: (K,) int, which machines (of a batched reset).
            q0: (K, 4) rad, their start positions.

        Returns:
            (K, 8) [rad, rad/s], their observations.
        """
        if self._q is None or self._q.ndim != 2:
            raise EfficientTrackError("ClosedLoop.reset_machines needs a batched reset (N, 4) first")
        if not callable(getattr(self.plant, "reset_machines", None)):
            raise EfficientTrackError("ClosedLoop.reset_machines: the plant cannot reset single machines (no reset_machines)")
        index = np.asarray(index, dtype=np.int64)
        obs = np.asarray(self.plant.reset_machines(index, q0), dtype=np.float64)
        self._q = self._q.copy()
        self._q[index] = obs[:, :4]
        self._restarted = np.zeros(len(self._q), dtype=bool) if self._restarted is None else self._restarted.copy()
        self._restarted[index] = True
        return obs

    def step(self, q_ref: np.ndarray) -> np.ndarray:
        """Track ``q_ref`` (4,)/(N, 4) rad for one step; return obs (8,)/(N, 8)."""
        if self._q is None:
            raise EfficientTrackError("ClosedLoop.step called before reset")
        e_prev = self._e_prev
        if self._restarted is not None and e_prev is not None:  # machines restarted by reset_machines: e_prev = e
            e_prev = np.where(self._restarted[:, None], wrap(np.asarray(q_ref, dtype=np.float64) - self._q), e_prev)
        u, e = self.gains.step(q_ref, self._q, e_prev)
        obs = np.asarray(self.plant.step(u), dtype=np.float64)
        self._e_prev, self._q, self.last_command, self._restarted = e, obs[..., :4], u, None
        return obs
