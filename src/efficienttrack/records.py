"""Episode records: what one run of a machine along one reference produced.

Time alignment (as in the XE75 logs): at step t the controller reads ``q[t]``, ``qd[t]``,
sends ``q_ref[t]`` (the target for step t+1) and applies ``u[t]``; the machine reaches
``q[t+1]`` one step later. ``q_des[t]`` is the desired position for step t+1, so the tracking
error of step t is ``wrap(q[t+1] − q_des[t])``.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import atomic_write

JOINT_FIELDS = ("q", "qd", "q_ref", "q_des", "u")
MAX_ABS_ANGLE = 2 * np.pi
"""Angles beyond ±2π rad are taken for degrees (or garbage) and refused."""


@dataclass
class EpisodeRecord:
    """One episode, T control steps at 20 Hz.

    Attributes:
        q: (T, 4) rad, joint positions measured at step t.
        qd: (T, 4) rad/s, joint velocities measured at step t.
        q_ref: (T, 4) rad, reference sent to the position controller at step t (target of t+1).
        q_des: (T, 4) rad, desired position for step t+1.
        u: (T, 4) PWM applied at step t, or None when the system does not expose it.
        t: (T,) s since the start of the run (informational).
        meta: JSON-serializable facts about the run (reference name, noise σ, fallbacks, ...).
    """

    q: np.ndarray
    qd: np.ndarray
    q_ref: np.ndarray
    q_des: np.ndarray
    u: np.ndarray | None
    t: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        """Number of steps T."""
        return len(self.q)

    @property
    def obs(self) -> np.ndarray:
        """(T, 8) observations [q rad, qd rad/s]."""
        return np.concatenate([self.q, self.qd], axis=1)

    def validate(self, source: str = "record") -> EpisodeRecord:
        """Check shapes, finiteness and units; raise EfficientTrackError naming ``source`` and the field.

        Returns:
            self, with every array as float64.
        """
        for name in (*JOINT_FIELDS, "t"):
            value = getattr(self, name)
            if value is None:
                if name == "u":
                    continue
                raise EfficientTrackError(f"{source}: field '{name}' is missing")
            arr = np.asarray(value, dtype=np.float64) if np.asarray(value).dtype != object else None
            if arr is None:
                raise EfficientTrackError(f"{source}: field '{name}' is not numeric")
            setattr(self, name, arr)
        steps = len(self.q)
        if steps < 2:
            raise EfficientTrackError(f"{source}: needs at least 2 steps, has {steps}")
        for name in JOINT_FIELDS:
            arr = getattr(self, name)
            if arr is None:
                continue
            if arr.shape != (steps, 4):
                raise EfficientTrackError(f"{source}: field '{name}' has shape {arr.shape}, expected ({steps}, 4)")
            bad = ~np.isfinite(arr)
            if bad.any():
                row = int(np.argwhere(bad)[0][0])
                raise EfficientTrackError(f"{source}: field '{name}' has NaN/inf values (first at step {row})")
        if self.t.shape != (steps,):
            raise EfficientTrackError(f"{source}: field 't' has shape {self.t.shape}, expected ({steps},)")
        if not np.all(np.isfinite(self.t)):
            raise EfficientTrackError(f"{source}: field 't' has NaN/inf values")
        for name in ("q", "q_ref", "q_des"):
            peak = float(np.max(np.abs(getattr(self, name))))
            if peak > MAX_ABS_ANGLE:
                raise EfficientTrackError(
                    f"{source}: field '{name}' reaches {peak:.1f}, beyond ±2π rad: angles look like degrees (use radians)"
                )
        dt = np.diff(self.t)
        if np.any(dt <= 0):
            warnings.warn(f"{source}: timestamps are not increasing (time is informational only)", stacklevel=2)
        return self

    def save(self, path: str | Path) -> Path:
        """Write the record to ``path`` (.npz, no pickle) atomically; return the path."""
        path = Path(path)
        arrays = {name: getattr(self, name) for name in (*JOINT_FIELDS, "t") if getattr(self, name) is not None}
        arrays["meta_json"] = np.array(json.dumps(self.meta))
        atomic_write(path, lambda f: np.savez(f, **arrays))
        return path

    @classmethod
    def load(cls, path: str | Path) -> EpisodeRecord:
        """Read and validate a record saved by :meth:`save` or one of the XE75 ``.npz`` logs."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except (OSError, ValueError) as exc:
            raise EfficientTrackError(f"{path}: not a readable .npz episode record ({exc})") from exc
        missing = [name for name in ("q", "qd", "q_ref", "q_des", "t") if name not in arrays]
        if missing:
            raise EfficientTrackError(f"{path}: field(s) {', '.join(missing)} missing")
        meta = json.loads(str(arrays["meta_json"])) if "meta_json" in arrays else {}
        meta.setdefault("name", path.stem)
        record = cls(
            q=arrays["q"],
            qd=arrays["qd"],
            q_ref=arrays["q_ref"],
            q_des=arrays["q_des"],
            u=arrays.get("u"),
            t=arrays["t"],
            meta=meta,
        )
        return record.validate(str(path))
