"""Fit the hydraulic simulator to a machine's logs, and measure how closely a simulator reproduces them.

- :mod:`~efficienttrack.systems.fit.logs`: the logs loaded (:func:`efficienttrack.data.records.load_records`),
  selected by reference jitter, padded time-major and cut into windows.
- :mod:`~efficienttrack.systems.fit.simulate`: the simulator's fast paths on those windows and episodes.
- :mod:`~efficienttrack.systems.fit.calibrate`: the fit (:func:`calibrate`, :class:`FitConfig`, :func:`save_params`).
- :mod:`~efficienttrack.systems.fit.fidelity`: closed-loop MAE ratio, open-loop error and travel (:func:`fidelity`).

Nothing here imports from the learning layers.
"""

from efficienttrack.systems.fit.calibrate import (
    BOUNDS,
    JOINT_FIELDS,
    STEADY_FIELDS,
    CalibrationResult,
    FitConfig,
    Steady,
    calibrate,
    save_params,
    steady_samples,
)
from efficienttrack.systems.fit.fidelity import Fidelity, closed_loop_rollout, fidelity, open_loop_replay, travel_ratio
from efficienttrack.systems.fit.logs import (
    Padded,
    Windows,
    episode_windows,
    estimate_sensor_noise,
    load_logs,
    logged_accel,
    make_windows,
    pad,
    reference_jitter,
    select_by_jitter,
    tracking_mae,
    window_error,
)
from efficienttrack.systems.fit.simulate import rollout_windows, simulate_episodes

__all__ = [
    "BOUNDS",
    "JOINT_FIELDS",
    "STEADY_FIELDS",
    "CalibrationResult",
    "Fidelity",
    "FitConfig",
    "Padded",
    "Steady",
    "Windows",
    "calibrate",
    "closed_loop_rollout",
    "episode_windows",
    "estimate_sensor_noise",
    "fidelity",
    "load_logs",
    "logged_accel",
    "make_windows",
    "open_loop_replay",
    "pad",
    "reference_jitter",
    "rollout_windows",
    "save_params",
    "select_by_jitter",
    "simulate_episodes",
    "steady_samples",
    "tracking_mae",
    "travel_ratio",
    "window_error",
]
