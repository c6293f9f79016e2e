"""The built-in simulator's fast paths on logged windows: every window of a batch stepped at once.

:func:`rollout_windows` starts each window in its logged state (position, velocity and the commands still in
the delay line) and drives it either with the logged PWM (open loop) or by the PD law along the logged
``q_ref`` (closed loop, one :meth:`~efficienttrack.systems.pd.PDGains.step` per step, as
:class:`~efficienttrack.systems.pd.ClosedLoop` runs it). :func:`simulate_episodes` runs whole episodes this way;
tests hold it equal to ``ClosedLoop(HydraulicExcavator(params), gains)`` on the same references.
"""

from __future__ import annotations

import numpy as np

from efficienttrack.systems.fit.logs import Padded, Windows, episode_windows
from efficienttrack.systems.hydraulic import HydraulicParams, initial_state, step
from efficienttrack.systems.pd import PDGains


def rollout_windows(params: HydraulicParams, windows: Windows, gains: PDGains | None = None) -> np.ndarray:
    """Simulate every window from its logged state; return q (H, W, 4) rad, the positions after steps 1 … H.

    Args:
        params: simulator parameters.
        windows: the windows (H steps, W windows).
        gains: None to replay the logged PWM (open loop); a PD law to track the logged ``q_ref`` (closed loop).
    """
    state = initial_state(windows.q0, params, windows.qd0, windows.u_past)
    e_prev = windows.e_prev
    out = np.empty_like(windows.q)
    for k in range(len(windows.u)):
        if gains is None:
            u = windows.u[k]
        else:
            u, e_prev = gains.step(windows.q_ref[k], state.q, e_prev)
        state = step(state, u, params)
        out[k] = state.q
    return out


def simulate_episodes(params: HydraulicParams, data: Padded, gains: PDGains) -> np.ndarray:
    """Closed-loop positions of the logged episodes under ``gains``, reset at their logged starts (as ClosedLoop runs them).

    Args:
        params: simulator parameters.
        data: padded logs (T steps, N episodes); the logged ``q_ref`` is tracked, padding included.
        gains: the PD law.

    Returns:
        q (T, N, 4) rad: ``q[0]`` the logged start, ``q[t+1]`` the position after ``q_ref[t]``.
    """
    return np.concatenate([data.q[:1], rollout_windows(params, episode_windows(data), gains)])
