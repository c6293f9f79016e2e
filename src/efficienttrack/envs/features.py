"""One input for every learner: the environments' flat observation as EfficientTrack's networks see it.

EfficientTrack's model and policy see their inputs relative to the current position and standardized
(:func:`efficienttrack.data.features.relative_features`, statistics from the training data). A reinforcement-learning
baseline given the raw 332 absolute values instead starts from a harder problem: its critic sees absolute angles of
very different scales. :class:`ObservationPipeline` gives every learner the same input: the flat observation
(:func:`~efficienttrack.envs.core.observe`) cut into its histories, turned into the relative features, standardized
with statistics from the training references under the PD controller (never the test references), as float32.

The statistics come from one PD pass over the training references (:func:`pd_pipeline`): in the closed loop the
agent sends a = 0 (the PD controller alone); in the open loop it sends the PD law's own commands, so that the
command history it will see is scaled like a controller's. The pass is deterministic, so a resumed run recomputes the
same statistics and no state needs saving.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import N_JOINTS, OBS_DIM, PWM_SCALE
from efficienttrack.data.features import STD_FLOOR, feature_width, relative_features
from efficienttrack.data.references import Reference
from efficienttrack.envs.core import FUTURE, HISTORY
from efficienttrack.envs.evaluation import evaluate
from efficienttrack.systems.pd import PDGains
from efficienttrack.systems.spec import SystemSpec

See = Callable[[np.ndarray], np.ndarray]
"""What a learner sees of flat observations (N, D_obs): an :class:`ObservationPipeline`, or ``np.asarray`` (raw)."""


def split_observation(flat: np.ndarray, history: int, future: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The flat observations of N machines as their parts.

    Args:
        flat: (N, h·8 + h·4 + F·4), :func:`~efficienttrack.envs.core.observe`'s layout.
        history: h.
        future: F.

    Returns:
        ``o_H`` (N, h, 8) [rad, rad/s], the second history (N, h, 4) (references sent, rad, or the last actions) and
        ``q*_F`` (N, F, 4) rad.
    """
    flat = np.asarray(flat, dtype=np.float64)
    n = len(flat)
    obs_end = history * OBS_DIM
    ref_end = obs_end + history * N_JOINTS
    return (
        flat[:, :obs_end].reshape(n, history, OBS_DIM),
        flat[:, obs_end:ref_end].reshape(n, history, N_JOINTS),
        flat[:, ref_end:].reshape(n, future, N_JOINTS),
    )


def flat_features(flat: np.ndarray, loop: str, history: int, future: int) -> np.ndarray:
    """The relative features of flat observations, before scaling.

    Args:
        flat: (N, D_obs) flat observations.
        loop: ``"closed"`` or ``"open"`` (the second history holds actions, taken as they are).
        history: h.
        future: F.

    Returns:
        (N, D) float64, D = 12h + 4F.
    """
    obs_hist, second, targets = split_observation(flat, history, future)
    return relative_features(obs_hist, second, targets, commands=loop == "open")


class ObservationPipeline:
    """Flat observations → standardized relative features, float32: the input every learner sees.

    Args:
        loop: ``"closed"`` (the second history holds references, seen relative to ``q_t``) or ``"open"`` (it holds
            the last actions, PWM / 1000, taken as they are).
        mean: (D,) feature means.
        std: (D,) feature standard deviations (below :data:`~efficienttrack.data.features.STD_FLOOR`: 1, a constant
            feature is only centred, as the networks do).
        history: h of the observations.
        future: F of the observations.
    """

    def __init__(self, loop: str, mean: np.ndarray, std: np.ndarray, history: int = HISTORY, future: int = FUTURE) -> None:
        self.loop, self.history, self.future = loop, history, future
        self.size = feature_width(history, future)
        """D, the width of the features."""
        self.mean = np.asarray(mean, dtype=np.float64)
        self.std = np.where(np.asarray(std, dtype=np.float64) < STD_FLOOR, 1.0, np.asarray(std, dtype=np.float64))
        if self.mean.shape != (self.size,) or self.std.shape != (self.size,):
            raise EfficientTrackError(f"ObservationPipeline: statistics must be ({self.size},), got {self.mean.shape}")

    def features(self, flat: np.ndarray) -> np.ndarray:
        """The relative features of flat observations, before scaling: :func:`flat_features` (N, D_obs) → (N, D)."""
        return flat_features(flat, self.loop, self.history, self.future)

    def __call__(self, flat: np.ndarray) -> np.ndarray:
        """Standardized features of flat observations (N, D_obs) → (N, D) float32."""
        return ((self.features(flat) - self.mean) / self.std).astype(np.float32)


def pd_pipeline(
    loop: str,
    system: SystemSpec,
    train_refs: Sequence[Reference],
    history: int = HISTORY,
    future: int = FUTURE,
) -> ObservationPipeline:
    """The pipeline with statistics of one PD pass over the training references (see the module docstring).

    Args:
        loop: ``"closed"`` or ``"open"``.
        system: the system the learner trains on (its plant and PD law for the open loop).
        train_refs: the training references (never the test references).
        history: h.
        future: F.

    Returns:
        The fitted pipeline.
    """
    gains = PDGains.load(system.pd_name)
    seen: list[np.ndarray] = []
    previous: list[np.ndarray] = []  # the PD law's last error, for its difference term

    def pd_agent(flat: np.ndarray) -> np.ndarray:
        seen.append(np.asarray(flat, dtype=np.float64))
        if loop == "closed":
            return np.zeros((len(flat), N_JOINTS))
        obs_hist, _, q_des = split_observation(flat, history, future)
        e_prev = previous.pop() if previous and len(previous[-1]) == len(flat) else None
        u, e = gains.step(q_des[:, 0], obs_hist[:, -1, :N_JOINTS], e_prev)
        previous.append(e)
        return u / PWM_SCALE

    evaluate(pd_agent, list(train_refs), loop, system, history, future)
    features = flat_features(np.concatenate(seen), loop, history, future)
    return ObservationPipeline(loop, features.mean(axis=0), features.std(axis=0), history, future)


def learner_input(inputs: str, loop: str, system: SystemSpec, train_refs: Sequence[Reference]) -> See:
    """What a baseline sees: the shared pipeline (``"relative"``, :func:`pd_pipeline`) or the raw observation (``"raw"``).

    Args:
        inputs: ``"relative"`` or ``"raw"`` (a baseline's ``inputs`` setting, checked there).
        loop: ``"closed"`` or ``"open"``.
        system: the system the learner trains on.
        train_refs: the training references.

    Returns:
        Flat observations (N, D_obs) → the learner's input.
    """
    return pd_pipeline(loop, system, train_refs) if inputs == "relative" else np.asarray
